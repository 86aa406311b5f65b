#!/usr/bin/env python
"""Mutation check of SCALAR-NeRF's core: does every small break of the method make a test fail?

Each mutant (``tools/mutants.py``) is one small break of the package (a fusion rule, the block split and its
scale-up, automatic K and block capacity, how a block starts from the global model, which block renders which
ray, the fused renderer, volume rendering and sampling, the training length plan) with the fast tests that
claim to cover that part. For each mutant, one at a time, the script

1. refuses to run if the file has uncommitted changes (``git diff --quiet HEAD -- FILE``);
2. writes the mutated file atomically (the snippet ``old`` must occur exactly once);
3. runs ``python -m pytest -q -x -p no:cacheprovider -m "not slow"`` on the mutant's tests (without ``-m "not slow"``
   for a ``slow`` mutant; 900 s at most);
4. always restores the original bytes and modification time (also on Ctrl-C or SIGTERM) and checks with git
   that the file is back to its committed content.

A mutant is *killed* when pytest exits 1 (a test failed), *survived* when it exits 0, and an *error* otherwise
(2 interrupted or a collection error, 4 usage error, 5 no tests collected, a timeout, every test skipped).
First the tests of all the mutants run once on the unmutated code (the baseline): a test that fails there
kills nothing. The exit status is 1 when the baseline fails or any mutant survived or errored.

    python tools/mutation_check.py                        # the baseline, then every mutant (one pytest run each)
    python tools/mutation_check.py --only guard-never-fires idw-exponent-sign
    python tools/mutation_check.py --dry-run              # apply, compile and restore each mutant; run no test
    python tools/mutation_check.py --list [--markdown]    # the table of mutants
    python tools/mutation_check.py --markdown --report outputs/mutants.md   # results as a markdown table

Standard library only. Python's bytecode cache cannot keep a mutant: pytest runs with PYTHONDONTWRITEBYTECODE=1,
a mutant's modification time differs from the original's, and the original's is restored with its bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import py_compile
import re
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, List, Optional, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mutants import MUTANTS, Mutant  # noqa: E402  (tools/mutants.py, beside this script)

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TIMEOUT_S = 900.0


@dataclass(frozen=True)
class Outcome:
    """What one mutant gave: ``result`` killed / survived / error, and the first failing test or the reason."""

    name: str
    result: str
    seconds: float
    detail: str


class MutationError(RuntimeError):
    """A mutant that cannot be applied (its snippet is not in its file exactly once)."""


class RestoreError(MutationError):
    """A mutated file that is not back to its committed content: everything stops."""


# ---------------------------------------------------------------------------------------------- files and git


def uncommitted(path: str) -> Optional[str]:
    """Why ``path`` may not be mutated (not tracked, or changed against HEAD); None when it is committed as is."""
    tracked = subprocess.run(["git", "ls-files", "--error-unmatch", "--", path], cwd=ROOT, capture_output=True, check=False)
    if tracked.returncode != 0:
        return f"{path} is not tracked by git"
    if subprocess.run(["git", "diff", "--quiet", "HEAD", "--", path], cwd=ROOT, check=False).returncode != 0:
        return f"{path} has uncommitted changes: commit or stash them first"
    return None


def write_atomically(path: Path, data: bytes, *, mode: int, mtime_ns: int) -> None:
    """Replace ``path`` by ``data`` in one rename, with permission bits ``mode`` and modification time ``mtime_ns``."""
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".mutant")
    try:
        with os.fdopen(handle, "wb") as out:
            out.write(data)
        os.chmod(temporary, mode)
        os.utime(temporary, ns=(mtime_ns, mtime_ns))
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


@contextlib.contextmanager
def applied(mutant: Mutant) -> Iterator[Path]:
    """The mutant written into its file for the ``with`` block; the original bytes and mtime are always put back,
    then checked against git (:class:`RestoreError` if the file is not back to its committed content)."""
    path = ROOT / mutant.path
    original = path.read_bytes()
    status = path.stat()
    text = original.decode("utf-8")
    count = text.count(mutant.old)
    if count != 1 or mutant.old == mutant.new:
        raise MutationError(f"{mutant.name}: the snippet occurs {count} times in {mutant.path} (it must occur once)"
                            if count != 1 else f"{mutant.name}: old and new are the same")
    mutated = text.replace(mutant.old, mutant.new).encode("utf-8")
    # A modification time of its own (seconds apart), so that no cached bytecode of one passes for the other.
    mutant_ns = max(time.time_ns(), status.st_mtime_ns + 2_000_000_000)
    try:
        with signals_held():
            write_atomically(path, mutated, mode=status.st_mode & 0o7777, mtime_ns=mutant_ns)
        yield path
    finally:
        with signals_held():
            write_atomically(path, original, mode=status.st_mode & 0o7777, mtime_ns=status.st_mtime_ns)
        if path.read_bytes() != original or uncommitted(mutant.path) is not None:
            raise RestoreError(f"{mutant.path} was NOT restored to its committed content: check it with git diff")


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM wait for the end of the block (a file is never left half written), then interrupt."""
    held: List[int] = []
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig in previous:
        signal.signal(sig, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if held:
        raise KeyboardInterrupt(f"signal {held[0]}")


# ---------------------------------------------------------------------------------------------- pytest


def selection_args(tests: Sequence[str]) -> List[str]:
    """pytest arguments of a mutant's test selection (node ids; ``-k EXPR`` entries as ``-k``, ``EXPR``)."""
    args: List[str] = []
    for entry in tests:
        args += ["-k", entry[3:].strip()] if entry.startswith("-k ") else [entry]
    return args


def pytest_command(tests: Sequence[str], slow: bool) -> List[str]:
    """The pytest command line that runs ``tests`` (the quick subset unless they are ``slow``)."""
    marker = [] if slow else ["-m", "not slow"]
    options = ["-q", "-x", "-rfE", "-p", "no:cacheprovider", *marker]
    return [sys.executable, "-m", "pytest", *options, *selection_args(tests)]


def run_pytest(tests: Sequence[str], slow: bool, timeout_s: float) -> Tuple[Optional[int], str, float]:
    """``(exit code or None on timeout, output, seconds)`` of pytest on ``tests``; the run is stopped (its whole
    process group) on timeout or Ctrl-C."""
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    start = time.monotonic()
    process = subprocess.Popen(pytest_command(tests, slow), cwd=ROOT, env=env, stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        output, _ = process.communicate(timeout=timeout_s)
        return process.returncode, output, time.monotonic() - start
    except subprocess.TimeoutExpired:
        _stop(process)
        output, _ = process.communicate()
        return None, output, time.monotonic() - start
    except BaseException:
        _stop(process)
        process.communicate()
        raise


def _stop(process: subprocess.Popen) -> None:
    """Terminate the process group pytest leads (SIGTERM, then SIGKILL after 10 s)."""
    for sig, wait_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, None)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, sig)
        try:
            process.wait(timeout=wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def first_failure(output: str) -> str:
    """The first ``FAILED`` / ``ERROR`` test id of pytest's summary, or its first ``ERROR:`` line."""
    match = re.search(r"^(?:FAILED|ERROR) (\S+)", output, re.M) or re.search(r"^(ERROR: .*)$", output, re.M)
    return match.group(1) if match else ""


def classify(code: Optional[int], output: str, tests: Sequence[str], timeout_s: float) -> Tuple[str, str]:
    """``(killed | survived | error, detail)`` of a mutant's pytest run."""
    counts = {kind: int(n) for n, kind in re.findall(r"(\d+) (passed|failed|skipped|deselected)", output)}
    if code == 1:
        return "killed", first_failure(output) or "a test failed"
    if code == 0 and counts.get("passed", 0) == 0:
        return "error", "every selected test was skipped or deselected"
    if code == 0:
        return "survived", f"{counts['passed']} passed"
    if code is None:
        return "error", f"timed out after {timeout_s:.0f} s"
    if code == 5:
        return "error", f"no tests collected from {' '.join(tests)}"
    reasons = {-1: "not applied", 2: "interrupted or a collection error", 4: "pytest usage error"}
    reason = reasons.get(code, f"pytest exit code {code}")
    last = (output.strip().splitlines() or [""])[-1]
    return "error", f"{reason}: {first_failure(output) or last}"


def tail(output: str, lines: int = 15) -> str:
    """The last ``lines`` lines of ``output``, indented."""
    return "\n".join("    " + line for line in output.rstrip().splitlines()[-lines:])


# ---------------------------------------------------------------------------------------------- the checks


def missing_tests(mutant: Mutant) -> List[str]:
    """The node ids of ``mutant`` whose file or test function does not exist (a static check, nothing is run)."""
    problems = []
    for entry in mutant.tests:
        if entry.startswith("-k "):
            continue
        file, _, name = entry.partition("::")
        source = ROOT / file
        function = name.split("::")[-1].split("[")[0]
        if not source.is_file():
            problems.append(f"{entry}: no file {file}")
        elif function and not re.search(rf"^\s*def {re.escape(function)}\(", source.read_text(), re.M):
            problems.append(f"{entry}: no test {function} in {file}")
    return problems


def dry_run(mutants: Sequence[Mutant]) -> int:
    """Apply each mutant, compile the mutated file (into a temporary file) and restore it; run no test."""
    bad = 0
    with tempfile.TemporaryDirectory() as scratch:
        for mutant in mutants:
            problems = missing_tests(mutant)
            try:
                with applied(mutant) as path:
                    py_compile.compile(str(path), cfile=str(Path(scratch) / "mutant.pyc"), doraise=True)
            except RestoreError:
                raise
            except (MutationError, py_compile.PyCompileError, UnicodeDecodeError) as error:
                problems.append(str(error).strip().splitlines()[-1])
            bad += bool(problems)
            print(f"{mutant.name:<30} {'bad' if problems else 'ok':<4} {mutant.path}", flush=True)
            for problem in problems:
                print(f"    {problem}")
    print(f"dry run: {len(mutants) - bad} of {len(mutants)} mutants apply, compile and restore; {bad} bad")
    return 1 if bad else 0


def baseline(mutants: Sequence[Mutant], timeout_s: float) -> bool:
    """Run the tests of every mutant once on the unmutated code; False (and say which failed) if any fails."""
    for slow in (False, True):
        tests = list(dict.fromkeys(t for m in mutants if m.slow == slow for t in m.tests))
        if not tests:
            continue
        code, output, seconds = run_pytest(tests, slow, timeout_s)
        print(f"{'baseline':<30} {'ok' if code == 0 else 'FAILED':<9} {seconds:7.1f} s  {len(tests)} selections",
              flush=True)
        if code != 0:
            failure = first_failure(output) or f"exit code {code}"
            print(f"the tests fail without any mutant ({failure}): fix them first\n{tail(output)}")
            return False
    return True


def run_mutants(mutants: Sequence[Mutant], timeout_s: float) -> List[Outcome]:
    """Apply each mutant in turn, run its tests, restore the file; one printed line per mutant."""
    outcomes = []
    for mutant in mutants:
        try:
            with applied(mutant):
                code, output, seconds = run_pytest(mutant.tests, mutant.slow, timeout_s)
        except RestoreError:
            raise
        except MutationError as error:
            code, output, seconds = -1, str(error), 0.0
        result, detail = classify(code, output, mutant.tests, timeout_s)
        outcomes.append(Outcome(mutant.name, result, seconds, detail))
        print(f"{mutant.name:<30} {result:<9} {seconds:7.1f} s  {detail}", flush=True)
        if result != "killed":
            print(tail(output))
    return outcomes


def short_test(entry: str) -> str:
    """``tests/test_fusion.py::test_x`` -> ``test_fusion::test_x``."""
    return entry.replace("tests/", "", 1).replace(".py::", "::")


def markdown_table(mutants: Sequence[Mutant], outcomes: Optional[Sequence[Outcome]] = None) -> str:
    """The mutants (and, given ``outcomes``, their results) as a markdown table."""
    by_name = {o.name: o for o in outcomes or ()}
    header = "| mutant | file | what it breaks | tests run |" + (" result | s |" if outcomes else "")
    lines = [header, "|" + "---|" * header.count(" |")]
    for m in mutants:
        row = f"| {m.name} | {m.path.replace('scalar_nerfstudio/', '')} | {m.why} | "
        row += ", ".join(short_test(t) for t in m.tests) + " |"
        if outcomes:
            outcome = by_name.get(m.name)
            row += f" {outcome.result} | {outcome.seconds:.0f} |" if outcome else " not run | |"
        lines.append(row)
    return "\n".join(lines)


def _interrupt(signum: int, frame: object) -> None:
    """SIGTERM as Ctrl-C: the ``finally`` that restores the file runs."""
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: Optional[Sequence[str]] = None) -> int:
    """The command line (see the module's docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run these mutants only")
    parser.add_argument("--dry-run", action="store_true", help="apply, compile and restore each mutant; run no test")
    parser.add_argument("--list", action="store_true", help="print the mutants and exit")
    parser.add_argument("--markdown", action="store_true", help="print the list or the results as a markdown table")
    parser.add_argument("--report", type=Path, help="also write the markdown table of the results to this file")
    parser.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="seconds per pytest run (900)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the run of the tests on the unmutated code")
    args = parser.parse_args(argv)
    known = {m.name: m for m in MUTANTS}
    unknown = [name for name in args.only or () if name not in known]
    if unknown:
        parser.error(f"unknown mutant(s) {', '.join(unknown)}; known: {', '.join(known)}")
    mutants = [known[name] for name in args.only] if args.only else list(MUTANTS)
    if args.list and args.markdown:
        print(markdown_table(mutants))
    elif args.list:
        for m in mutants:
            print(f"{m.name:<30} {m.path:<45} {len(m.tests)} test(s)  {m.why}")
    if args.list:
        return 0
    reasons = (uncommitted(path) for path in sorted({m.path for m in mutants}))
    dirty = [reason for reason in reasons if reason is not None]
    if dirty:
        print("refusing to mutate files with uncommitted changes:\n  " + "\n  ".join(dirty), file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        if args.dry_run:
            return dry_run(mutants)
        start = time.monotonic()
        if not args.no_baseline and not baseline(mutants, args.timeout):
            return 1
        outcomes = run_mutants(mutants, args.timeout)
    except KeyboardInterrupt:
        print("interrupted: the mutated file was restored", file=sys.stderr)
        return 130
    counts = {kind: sum(o.result == kind for o in outcomes) for kind in ("killed", "survived", "error")}
    print(f"{len(outcomes)} mutants: {counts['killed']} killed, {counts['survived']} survived, "
          f"{counts['error']} errors ({time.monotonic() - start:.0f} s)")
    if args.markdown or args.report:
        table = markdown_table(mutants, outcomes)
        if args.markdown:
            print(table)
        if args.report:
            args.report.write_text(table + "\n")
    return 0 if counts["killed"] == len(outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
