"""The long fuzz run of ``convert raw`` on RAW and DAT headers (issue 25); the suite runs a short one
(``tests/psfmt/test_evt3_headers.py``).

Each file is a header of ``corpus/raw_headers`` with one to three mutations — lines reordered,
dropped, duplicated, garbled or cut, a junk ``% key value`` line added — before a body: EVT 3.0 or
EVT 2.0 words from psfmt's encoders, DAT records, or random bytes. ``pstoolkit convert raw`` runs on
it in process. The outcomes:

- converted — exit 0 and a capture that validates;
- refused — exit 2 with one ``pstoolkit: error: FILE: …`` line and no output file;
- broken — anything else (a traceback, several lines, an invalid capture, a file left behind).

Prints a table and writes ``benchmarks/results/fuzz_raw_headers.json``.

    python tests/fuzz/fuzz_raw_headers.py [--files 500] [--seed 0]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

import psfmt
from psfmt.eventfiles import dat, evt2, evt3
from psfmt.events import EventArray
from pstoolkit.cli import main as cli

TESTS = Path(__file__).resolve().parents[1]
CORPUS = TESTS / "fuzz" / "corpus" / "raw_headers"
RESULTS = TESTS.parent / "benchmarks" / "results" / "fuzz_raw_headers.json"


def mutate(lines: list[bytes], rng: np.random.Generator) -> tuple[list[bytes], list[str]]:
    """``lines`` with one to three random mutations, and their names."""
    lines = list(lines)
    names = []
    for _ in range(int(rng.integers(1, 4))):
        kind = str(rng.choice(["shuffle", "drop", "duplicate", "garble", "cut", "junk"]))
        names.append(kind)
        k = int(rng.integers(0, max(1, len(lines))))
        if kind == "shuffle":
            rng.shuffle(lines)
        elif kind == "drop" and lines:
            del lines[k]
        elif kind == "duplicate" and lines:
            lines.insert(int(rng.integers(0, len(lines) + 1)), lines[k])
        elif kind == "garble" and lines:
            junk = rng.integers(0, 256, int(rng.integers(1, 8)), dtype=np.uint8).tobytes()
            at = int(rng.integers(2, max(3, len(lines[k]))))
            lines[k] = lines[k][:at] + junk + lines[k][at + len(junk):]
        elif kind == "cut" and lines:
            lines[k] = lines[k][: int(rng.integers(0, len(lines[k]) + 1))]
        elif kind == "junk":
            key = str(rng.choice(["geometry", "format", "Width", "Height", "system_ID", "plugin_name", "evt", "sensor_generation"]))
            value = str(rng.choice(["1280x720", "EVT3;height=720;width=1280", "640", "48", "99", "hal_plugin_gen3_fx3", "3.0", "2.0", "x", "0", "-1"]))
            lines.insert(int(rng.integers(0, len(lines) + 1)), f"% {key} {value}\n".encode())
    return lines, names


def body(rng: np.random.Generator) -> bytes:
    n = int(rng.integers(0, 400))
    events = EventArray(rng.integers(0, 1400, n), rng.integers(0, 800, n), np.sort(rng.integers(0, 1 << 26, n)), rng.choice([-1, 1], n))
    kind = int(rng.integers(0, 4))
    if kind == 0:
        return evt3.encode(events)
    if kind == 1:
        return evt2.encode(events)[0]
    if kind == 2:
        return bytes([12, 8]) + dat.encode(events)
    return rng.integers(0, 256, int(rng.integers(0, 600)), dtype=np.uint8).tobytes()


def probe(src: Path, out: Path) -> tuple[str, str]:
    """(outcome, detail) of ``convert raw SRC -o OUT``."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            code = cli(["convert", "raw", str(src), "-o", str(out), "-q"])
    except BaseException as exc:  # noqa: BLE001 - every escape is a finding
        return "broken", f"{type(exc).__name__}: {exc}"
    err = stderr.getvalue()
    if code == 0:
        ok = out.is_file() and psfmt.validate(out).valid
        out.unlink(missing_ok=True)
        return ("converted", "") if ok else ("broken", "exit 0 without a valid capture")
    one_line = err.count("\n") == 1 and err.startswith(f"pstoolkit: error: {src}")
    if code == 2 and one_line and not out.exists():
        return "refused", err.strip()
    return "broken", f"exit {code}: {err.strip()[:300]}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    cases = sorted(p for p in CORPUS.glob("*.hdr"))
    counts: Counter[str] = Counter()
    by_mutation: dict[str, Counter[str]] = {}
    examples: list[dict[str, object]] = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n in range(args.files):
            case = cases[int(rng.integers(0, len(cases)))]
            lines, names = mutate(case.read_bytes().splitlines(keepends=True), rng)
            src = folder / ("case.dat" if rng.random() < 0.2 else "case.raw")
            src.write_bytes(b"".join(lines) + body(rng))
            outcome, detail = probe(src, folder / "out.h5")
            counts[outcome] += 1
            for name in set(names):
                by_mutation.setdefault(name, Counter())[outcome] += 1
            if outcome == "broken":
                examples.append({"case": case.name, "mutations": names, "detail": detail})
            if (n + 1) % 100 == 0:
                print(f"{n + 1} files, {dict(counts)}", file=sys.stderr, flush=True)
    summary = {
        "files": args.files,
        "seed": args.seed,
        "outcomes": dict(counts),
        "by_mutation": {k: dict(v) for k, v in sorted(by_mutation.items())},
        "broken": examples[:50],
        "wall_s": round(time.perf_counter() - start, 1),
    }
    print(f"{'outcome':<12}{'files':>8}")
    for outcome in ("converted", "refused", "broken"):
        print(f"{outcome:<12}{counts.get(outcome, 0):>8}")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(summary, indent=2) + "\n")
    print(f"wrote {RESULTS}")
    if counts.get("broken"):
        sys.exit(1)


if __name__ == "__main__":
    main()
