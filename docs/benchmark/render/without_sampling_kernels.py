"""bench_render.py with the C++ sampling kernels hidden (the torch code runs): the "before" of
docs/notebook/defaults.md's sampling-kernel comparison. Same arguments as benchmarks/bench_render.py.

    python docs/benchmark/render/without_sampling_kernels.py --load-config RUN/config.yml --rounds 5
"""

import runpy
import sys
from pathlib import Path

from scalar_nerfstudio.encodings import _cpp

_cpp.sampling_ops = lambda: None  # type: ignore[assignment]
sys.argv[0] = str(Path(__file__).resolve().parents[3] / "benchmarks" / "bench_render.py")
runpy.run_path(sys.argv[0], run_name="__main__")
