"""The long fuzz run of the capture reader and validator (issue 19); the suite runs a short one.

Each file is a small valid capture (hybrid, frames or events) with one to three random mutations
(``tests/mutations.py``: bit flips, overwritten or zeroed bytes, a cut file, datasets that declare far
more than they hold, hostile attribute values, deleted or retyped items, links out of the file, times
beyond float64 precision). A fresh child process validates and reads it *in process*
(``mutations.probe(isolated=False)``); the parent limits its time and reads its peak memory. The
outcomes:

- valid / invalid / clean error — ``validate`` gave a report (valid, or its findings) or one
  FormatError, and the reader agreed (read it all, or refused it with the same line);
- traceback — any other exception, or the reader and the validator disagreeing;
- hang, crash — the child ran past ``--timeout`` or died of a signal: HDF5 itself looping or crashing
  in C. Each such file is then checked as the ``pstoolkit`` command checks it (in a child process,
  ``psfmt.isolate``), and the run counts whether that gave one line in bounded time.

Prints a table, and with ``--out FILE`` writes the summary as JSON there; the checkout is left as it
was (the captures go to a temporary folder, no bytecode is cached).

    python tests/fuzz/fuzz_captures.py [--files 1000] [--seed 0] [--timeout 60] [--out FILE.json]
"""

from __future__ import annotations

import argparse
import json
import resource
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

TESTS = Path(__file__).resolve().parents[1]
# the checkout before tests/: its folder tests/psfmt must not stand in for the package psfmt
sys.path[:0] = [str(TESTS.parent), str(TESTS)]
sys.dont_write_bytecode = True

from helpers.mutations import BASES, MUTATIONS, base_capture, category, mutate  # noqa: E402

import psfmt  # noqa: E402
from psfmt import isolate  # noqa: E402

CHILD = f"""
import json, sys
sys.dont_write_bytecode = True
sys.path[:0] = [{str(TESTS.parent)!r}, {str(TESTS)!r}]
from helpers.mutations import probe
print(json.dumps(probe(__import__("pathlib").Path(sys.argv[1]), isolated=False)))
"""


def run_child(path: Path, timeout_s: float) -> tuple[str, str, float]:
    """(outcome, detail, seconds) of probing ``path`` in a fresh child process."""
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = child.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        child.kill()
        child.communicate()
        return "hang", f"no answer in {timeout_s:g} s", time.perf_counter() - start
    seconds = time.perf_counter() - start
    if child.returncode < 0:
        return "crash", signal.Signals(-child.returncode).name, seconds
    if child.returncode != 0:
        last = err.strip().splitlines()[-1] if err.strip() else f"exit code {child.returncode}"
        return "traceback", last, seconds
    outcome = json.loads(out.strip().splitlines()[-1])
    return category(outcome), outcome, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds a child may take before it counts as a hang")
    parser.add_argument("--out", type=Path, default=None, help="write the summary as JSON to this file")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    names = sorted(MUTATIONS)
    counts: Counter[str] = Counter()
    by_mutation: dict[str, Counter[str]] = {name: Counter() for name in names}
    examples: dict[str, list[dict[str, object]]] = {}
    slowest = 0.0
    isolated_ok = 0
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        bases = {kind: base_capture(folder / f"{kind}.h5", kind) for kind in BASES}
        for n in range(args.files):
            kind = str(rng.choice(BASES))
            kinds = [str(k) for k in rng.choice(names, size=int(rng.integers(1, 4)))]
            seed = int(rng.integers(0, 2**32))
            path = mutate(bases[kind], folder / "case.h5", kinds, seed)
            outcome, detail, seconds = run_child(path, args.timeout)
            counts[outcome] += 1
            for k in set(kinds):
                by_mutation[k][outcome] += 1
            slowest = max(slowest, seconds)
            if outcome in ("hang", "crash", "traceback"):
                case = {"base": kind, "mutations": kinds, "seed": seed, "detail": detail}
                if outcome in ("hang", "crash"):
                    try:
                        isolate.inspect(path, content=True, quiet_s=10.0)
                        case["isolated"] = "read"
                    except psfmt.FormatError as exc:
                        case["isolated"] = exc.message
                        isolated_ok += 1
                examples.setdefault(outcome, []).append(case)
            if (n + 1) % 100 == 0:
                print(f"{n + 1} files, {dict(counts)}", file=sys.stderr, flush=True)
    # the largest resident set of any child (kB on Linux): every file was read in one of them
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    summary = {
        "files": args.files,
        "seed": args.seed,
        "timeout_s": args.timeout,
        "outcomes": dict(counts),
        "by_mutation": {k: dict(v) for k, v in by_mutation.items()},
        "slowest_s": round(slowest, 2),
        "peak_child_rss_mb": round(peak_mb, 1),
        "hangs_and_crashes_caught_by_isolation": isolated_ok,
        "examples": examples,
        "wall_s": round(time.perf_counter() - start, 1),
    }
    print(f"{'outcome':<14}{'files':>8}")
    for outcome in ("valid", "invalid", "error", "traceback", "hang", "crash"):
        print(f"{outcome:<14}{counts.get(outcome, 0):>8}")
    print(f"slowest file {slowest:.2f} s, peak child memory {peak_mb:.0f} MB; "
          f"in-process hangs/crashes answered in one line by the isolated check: {isolated_ok}")
    if args.out is not None:
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
