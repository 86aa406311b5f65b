"""The project's procedural scenes (the lab beside the method): written in nerfstudio format, with known
geometry, for the quick start, the tests and the benchmarks.

* :mod:`.courtyard`: a small courtyard of textured boxes, the default scene of ``scalar-nerf-demo``.
* :mod:`.town`: a large town of streets and textured buildings, too big for one hash table, with a
  street-level or aerial capture and true depth.

``scalar-nerf-make-scene`` (scripts/make_scene.py) writes either. The method (everything outside
``scenes/``, ``benchmarking/`` and ``scripts/``) never imports this package.
"""
