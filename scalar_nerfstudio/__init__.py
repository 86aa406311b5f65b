"""SCALAR-NeRF as a nerfstudio method plugin."""
