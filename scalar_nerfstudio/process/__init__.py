"""Real captures to nerfstudio scenes: structure-from-motion on photos (pycolmap, CPU), the capture's
frame (metric east-north-up from EXIF GPS), and exports mapped back to that frame.

The method (``scalar_nerfstudio`` outside this package) never imports it. Only ``sfm`` needs
pycolmap (the ``process`` extra); the other modules need numpy, PIL and plyfile.
"""
