"""How the two AEDAT4 readers from the package registries take damaged files (extra ``aedat4``).

Writes a small DAVIS-like recording with dv-processing (64×48, 3000 events, 3 frames, 6 triggers),
makes ``--files`` copies with 1 to 5 random bytes changed after the magic line (seeded), and reads
each copy to the end in a child process with ``aedat.Decoder``, with dv-processing's
``dv.io.MonoCameraRecording`` and with the ``aedat4`` converter, each under ``--timeout`` seconds.
Counts per reader: read to the end, refused in one line (the converter's UserError), another Python
exception, hung (killed at the timeout), crashed (killed by a signal). This is why ``convert aedat4``
reads with ``aedat``, and what its own checks before the decoder add. Prints a table and writes ``benchmarks/results/aedat4_readers.json``.

    python benchmarks/aedat4_readers.py [--files 25] [--timeout 8] [--seed 1]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

import dv_processing as dv
import numpy as np
from results_io import write_results

RESULTS = Path(__file__).resolve().parent / "results" / "aedat4_readers.json"
MAGIC_BYTES = 14

READERS = {
    "aedat": "import sys, aedat\nfor packet in aedat.Decoder(sys.argv[1]):\n    pass\n",
    "dv-processing": (
        "import sys, dv_processing as dv\n"
        "r = dv.io.MonoCameraRecording(sys.argv[1])\n"
        "for read in (r.getNextEventBatch, r.getNextFrame, r.getNextTriggerBatch):\n"
        "    while read() is not None:\n"
        "        pass\n"
    ),
    "convert aedat4": (
        "import sys\nfrom pathlib import Path\nfrom pstoolkit import UserError\nfrom pstoolkit_eventfiles.aedat4 import Aedat4\n"
        "options = {'lights': '', 'calibration': '', 'allow_empty': True}\n"
        "try:\n"
        "    Aedat4().convert(Path(sys.argv[1]), Path(sys.argv[1] + '.h5'), options, lambda *_: None)\n"
        "except UserError:\n"
        "    sys.exit(2)\n"
    ),
}


def write_recording(path: Path, seed: int) -> None:
    width, height, n = 64, 48, 3000
    rng = np.random.default_rng(seed)
    writer = dv.io.MonoCameraWriter(str(path), dv.io.MonoCameraWriter.DAVISConfig("DAVIS346_test", (width, height)))
    store = dv.EventStore()
    for t, x, y, on in zip(np.sort(rng.integers(1000, 100_000, n)).tolist(), rng.integers(0, width, n).tolist(),
                           rng.integers(0, height, n).tolist(), (rng.random(n) < 0.5).tolist()):
        store.push_back(t, x, y, on)
    writer.writeEvents(store)
    for k in range(3):
        writer.writeFrame(dv.Frame(10_000 + 30_000 * k, 5000, 0, 0, rng.integers(0, 256, (height, width), dtype=np.uint8), dv.FrameSource.SENSOR))
        writer.writeTrigger(dv.Trigger(9000 + 30_000 * k, dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE))
        writer.writeTrigger(dv.Trigger(16_000 + 30_000 * k, dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE))
    del writer  # closing writes the file's table


def outcome(reader: str, path: Path, timeout_s: float) -> str:
    try:
        done = subprocess.run([sys.executable, "-c", READERS[reader], str(path)], capture_output=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return "hung"
    return {0: "read", 1: "exception", 2: "refused"}.get(done.returncode, "crashed")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=25)
    parser.add_argument("--timeout", type=float, default=8.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    counts: dict[str, Counter[str]] = {reader: Counter() for reader in READERS}
    with tempfile.TemporaryDirectory() as tmp:
        original = Path(tmp) / "rec.aedat4"
        write_recording(original, args.seed)
        blob = original.read_bytes()
        for k in range(args.files):
            damaged = bytearray(blob)
            for _ in range(int(rng.integers(1, 6))):
                damaged[int(rng.integers(MAGIC_BYTES, len(damaged)))] = int(rng.integers(0, 256))
            path = Path(tmp) / f"damaged_{k}.aedat4"
            path.write_bytes(bytes(damaged))
            for reader in READERS:
                counts[reader][outcome(reader, path, args.timeout)] += 1
    kinds = ("read", "refused", "exception", "hung", "crashed")
    print(f"{args.files} copies of a {len(blob):,}-byte AEDAT4 file with 1–5 random bytes changed (seed {args.seed}, timeout {args.timeout:g} s)")
    print(f"{'reader':16}" + "".join(f"{k:>11}" for k in kinds))
    for reader, c in counts.items():
        print(f"{reader:16}" + "".join(f"{c[k]:>11}" for k in kinds))
    write_results(RESULTS, {"files": args.files, "seed": args.seed, "timeout_s": args.timeout, "bytes": len(blob),
                            "outcomes": {reader: {k: c[k] for k in kinds} for reader, c in counts.items()}})


if __name__ == "__main__":
    main()
