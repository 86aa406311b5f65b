"""Sharing benchmark (issue 18): training rays/s of one lone training and of two trainings started together.

For each ``--adapt-threads`` setting: one scalar-nerf training alone, then two started at the same
moment, each in a process of its own with torch's default thread count (``OMP_NUM_THREADS`` and
``MKL_NUM_THREADS`` are removed from the workers' environment, which would otherwise turn the thread
governor off). Each run trains ``--steps`` steps with the method's defaults on the CPU, on the
benchmark runner's set-up (every 8th image held out, no evaluation, previews or checkpoints while
training).

Rays/s is measured on wall clock over whole steps: for a lone run from the end of step ``--warmup``
to its last step; for two concurrent runs over the span in which both had passed ``--warmup`` steps
and neither had finished (so neither is measured while it trains alone). The warm-up should cover
the governor's reaction (two samples 5 s apart, i.e. about 10 s of training). The table gives each
concurrent run's rays/s and its ratio to the lone run's (issue 18's target: >= 0.40 each).

    python benchmarks/bench_sharing.py --data ../shared/data/castle-P30 --downscale 4 --steps 300
    python benchmarks/bench_sharing.py --steps 80 --warmup 20 --adapt-threads True   # a short check
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
TARGET_RATIO = 0.40


def train_one(spec: Dict[str, Any]) -> None:
    """Train one run as ``spec`` says (in its own process, ``--worker``) and write its step times.

    ``spec``: data, downscale, steps, adapt_threads, output_dir, result (the JSON path). The result
    holds ``ends`` (wall-clock time.time() in seconds at the end of every step, [steps]),
    ``threads`` (torch's thread count after every step, [steps]) and ``rays_per_step``.
    """
    import torch

    from scalar_nerfstudio.benchmarking.runner import setup_trainer, trainer_config
    from scalar_nerfstudio.engine.timing import StepClock, time_train_iterations

    overrides = {
        "machine.device_type": "cpu",
        "max_num_iterations": int(spec["steps"]),
        "adapt_threads": bool(spec["adapt_threads"]),
        "steps_per_preview": 0,
    }
    config = trainer_config({"method": "scalar-nerf", "data": spec["data"], "downscale": int(spec["downscale"]),
                             "output_dir": spec["output_dir"], "overrides": overrides})
    config.set_timestamp()
    trainer = setup_trainer(config)
    trainer.save_checkpoint = lambda step: None  # no checkpoint writes inside or after the timed steps
    ends: List[float] = []
    threads: List[int] = []

    def record(step: int, result: Any, clock: StepClock) -> None:
        ends.append(time.time())
        threads.append(torch.get_num_threads())

    time_train_iterations(trainer, record)
    start_threads = torch.get_num_threads()
    trainer.train()
    result = {"ends": ends, "threads": threads, "start_threads": start_threads,
              "rays_per_step": trainer.pipeline.datamanager.get_train_rays_per_batch()}
    Path(spec["result"]).write_text(json.dumps(result))


def window_rays_per_s(ends: Sequence[float], rays_per_step: int, start: float, stop: float) -> float:
    """Rays/s over the steps that ended in [start, stop] (wall-clock seconds); nan with fewer than 2."""
    inside = [t for t in ends if start <= t <= stop]
    if len(inside) < 2 or inside[-1] <= inside[0]:
        return math.nan
    return (len(inside) - 1) * rays_per_step / (inside[-1] - inside[0])


def lone_rays_per_s(run: Dict[str, Any], warmup: int) -> float:
    """Rays/s of a lone run from the end of step ``warmup`` to its last step."""
    ends = run["ends"]
    if len(ends) <= warmup + 1:
        return math.nan
    return window_rays_per_s(ends, run["rays_per_step"], ends[warmup], ends[-1])


def concurrent_rays_per_s(runs: Sequence[Dict[str, Any]], warmup: int) -> Tuple[List[float], float]:
    """Each run's rays/s while all of them trained past their warm-up, and that span's length (s)."""
    if any(len(run["ends"]) <= warmup + 1 for run in runs):
        return [math.nan] * len(runs), 0.0
    start = max(run["ends"][warmup] for run in runs)
    stop = min(run["ends"][-1] for run in runs)
    rates = [window_rays_per_s(run["ends"], run["rays_per_step"], start, stop) for run in runs]
    return rates, max(stop - start, 0.0)


def launch(spec: Dict[str, Any], log: Path, verbose: bool) -> subprocess.Popen:
    """Start one worker process for ``spec``; its output goes to ``log`` (or the terminal with ``verbose``)."""
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    spec_path = Path(spec["result"]).with_suffix(".spec.json")
    spec_path.write_text(json.dumps(spec))
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", str(spec_path)]
    out = None if verbose else log.open("w")
    try:
        return subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT if out else None)
    finally:
        if out is not None:
            out.close()  # the child holds its own descriptor


def run_together(specs: Sequence[Dict[str, Any]], workdir: Path, verbose: bool) -> List[Dict[str, Any]]:
    """Start every spec's worker at the same moment, wait for all, return their results."""
    processes = [launch(spec, workdir / f"{Path(spec['result']).stem}.log", verbose) for spec in specs]
    codes = [process.wait() for process in processes]
    for spec, code in zip(specs, codes):
        if code != 0:
            raise SystemExit(f"bench_sharing: the run {Path(spec['result']).stem} failed (exit {code}); "
                             f"see {workdir / (Path(spec['result']).stem + '.log')}")
    return [json.loads(Path(spec["result"]).read_text()) for spec in specs]


def make_spec(args: argparse.Namespace, adapt: bool, label: str) -> Dict[str, Any]:
    return {"data": str(args.data), "downscale": args.downscale, "steps": args.steps, "adapt_threads": adapt,
            "output_dir": str(args.workdir / "runs" / label), "result": str(args.workdir / f"{label}.json")}


def parse_bool(text: str) -> bool:
    if text.lower() in ("true", "1", "yes", "on"):
        return True
    if text.lower() in ("false", "0", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected True or False, not {text!r}")


def thread_note(run: Dict[str, Any]) -> str:
    """Threads at the start -> at the end (after the last step)."""
    end = run["threads"][-1] if run["threads"] else run["start_threads"]
    return f"{run['start_threads']}->{end}"


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=Path("../shared/data/castle-P30"))
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--steps", type=int, default=300, help="training steps of every run")
    parser.add_argument("--warmup", type=int, default=50, help="steps left out at the start of every run's measurement")
    parser.add_argument("--adapt-threads", type=parse_bool, nargs="+", default=[True, False],
                        help="the --adapt-threads settings to measure, each alone and as a pair")
    parser.add_argument("--workdir", type=Path, default=Path("outputs/bench_sharing"))
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    parser.add_argument("--verbose", action="store_true", help="show the trainings' output instead of logging it to WORKDIR")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)  # one run, in its own process (launch)
    args = parser.parse_args(argv)
    if args.worker:
        train_one(json.loads(args.worker.read_text()))
        return
    if args.warmup + 2 > args.steps:
        parser.error(f"--steps ({args.steps}) must exceed --warmup ({args.warmup}) by at least 2")
    args.workdir.mkdir(parents=True, exist_ok=True)
    dropped = [k for k in THREAD_VARIABLES if k in os.environ]
    if dropped:
        print(f"note: {', '.join(dropped)} removed from the trainings' environment (they train with torch's default threads)")

    rows: List[Dict[str, Any]] = []
    for adapt in args.adapt_threads:
        tag = "adapt" if adapt else "fixed"
        print(f"[{time.strftime('%H:%M:%S')}] --adapt-threads {adapt}: one training alone ({args.steps} steps) ...", flush=True)
        (lone,) = run_together([make_spec(args, adapt, f"{tag}-lone")], args.workdir, args.verbose)
        print(f"[{time.strftime('%H:%M:%S')}] --adapt-threads {adapt}: two trainings together ...", flush=True)
        pair = run_together([make_spec(args, adapt, f"{tag}-pair{i}") for i in (0, 1)], args.workdir, args.verbose)
        lone_rate = lone_rays_per_s(lone, args.warmup)
        rates, overlap_s = concurrent_rays_per_s(pair, args.warmup)
        rows.append({"adapt_threads": adapt, "lone_rays_per_s": lone_rate, "lone_threads": thread_note(lone),
                     "pair_rays_per_s": rates, "pair_ratio": [rate / lone_rate for rate in rates],
                     "pair_threads": [thread_note(run) for run in pair], "overlap_s": overlap_s})

    print(f"\nscene {args.data.name}, downscale {args.downscale}, {args.steps} steps per run, rays/s after step {args.warmup}, "
          f"{os.cpu_count()} CPUs; target: each concurrent run >= {TARGET_RATIO:.2f}x the lone run")
    print(f"{'adapt':<7}{'lone rays/s':>12}{'threads':>9}{'run A rays/s':>14}{'A/lone':>8}{'run B rays/s':>14}{'B/lone':>8}"
          f"{'threads A, B':>14}{'overlap s':>11}  target")
    for row in rows:
        (rate_a, rate_b), (ratio_a, ratio_b) = row["pair_rays_per_s"], row["pair_ratio"]
        met = "met" if min(ratio_a, ratio_b) >= TARGET_RATIO else "missed"
        print(f"{str(row['adapt_threads']):<7}{row['lone_rays_per_s']:>12.0f}{row['lone_threads']:>9}{rate_a:>14.0f}{ratio_a:>8.2f}"
              f"{rate_b:>14.0f}{ratio_b:>8.2f}{', '.join(row['pair_threads']):>14}{row['overlap_s']:>11.0f}  {met}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"scene": args.data.name, "downscale": args.downscale, "steps": args.steps,
                                         "warmup": args.warmup, "cpus": os.cpu_count(), "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
