"""``scalar-nerf-benchmark``'s machinery: speed against error of every variant on one scene.

* :mod:`.variants`: the benchmark's settings and the variant plan (which variants, their configs and
  budgets); pure.
* :mod:`.schedule`: sets up the scene and runs the variants, each in a subprocess, in order.
* :mod:`.runner`: that subprocess (``python -m scalar_nerfstudio.benchmarking.runner SPEC.json``):
  trains and evaluates one variant.
* :mod:`.report`: the table (with its Pareto fronts), the blocks against the better one-model schedule,
  results.json, results.md and the plots.
* :mod:`.heldout_view`: one held-out view side by side (truth, one model, blocks, block colours).

``scalar-nerf-benchmark`` (scripts/benchmark.py) is the command line around these.
"""
