"""How long an ``ns-*`` command takes to start: nerfstudio's method list imported in a fresh Python, with this
package's hook on nerfstudio's list of external methods (``scalar_nerfstudio/seam/method_list.py``) and with
it undone, alternately in one run.

    python benchmarks/bench_startup.py [--repeats 3] [--threads 1]

Each timing is one fresh ``python -c`` that imports ``nerfstudio.scripts.train`` (what ``ns-train`` imports
before it parses its options; ``ns-eval``, ``ns-render``, ``ns-export`` and ``ns-viewer`` build the same list).
"Undone" replaces the hook with a no-op before nerfstudio loads this package's methods. Prints each
timing, the medians and their ratio, and a one-line JSON summary. Run it with nothing else running.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from typing import Dict, List

IMPORT = "import nerfstudio.scripts.train"
UNDO = "import scalar_nerfstudio.seam.method_list as hook; hook.list_methods_without_reading_sources = lambda: None; "
VARIANTS = {"with the hook": IMPORT, "hook undone": UNDO + IMPORT}


def _time(code: str, threads: int) -> float:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "PYTHONWARNINGS": "ignore"}
    started = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="timings of each variant (alternating)")
    parser.add_argument("--threads", type=int, default=1, help="OMP_NUM_THREADS of each timed process")
    args = parser.parse_args()
    _time(IMPORT, args.threads)  # warm the file cache: the first import after a build reads more from disk
    times: Dict[str, List[float]] = {name: [] for name in VARIANTS}
    for repeat in range(args.repeats):
        for name, code in VARIANTS.items():
            times[name].append(_time(code, args.threads))
            print(f"repeat {repeat + 1}: {name}: {times[name][-1]:.2f} s", flush=True)
    medians = {name: statistics.median(values) for name, values in times.items()}
    ratio = medians["hook undone"] / medians["with the hook"]
    print(f"median: with the hook {medians['with the hook']:.2f} s, hook undone {medians['hook undone']:.2f} s "
          f"({ratio:.2f}x, {medians['hook undone'] - medians['with the hook']:.1f} s saved per command)")
    print(json.dumps({"median_s": medians, "ratio": ratio, "times_s": times, "threads": args.threads}))


if __name__ == "__main__":
    main()
