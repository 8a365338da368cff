"""Hostile variants of small captures, and the property every one of them must keep.

Shared by the property test (``test_fuzz.py``, a few dozen seeded examples in the suite) and the long
fuzz run (``tests/fuzz/fuzz_captures.py``). ``mutate`` applies random damage of one of ``MUTATIONS``
kinds to a valid capture: bit flips, overwritten or zeroed bytes, a cut file, datasets that declare
far more than they hold, hostile attribute values, deleted or retyped items, links out of the file,
times beyond float64 precision. ``probe`` then checks the property: ``validate`` gives a report or one
FormatError, the reader agrees with it, and a file that validates reads completely.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

import psfmt
from helpers.captures import sample_capture

BASES = ("hybrid", "frames", "events")
HOSTILE_VALUES: tuple[object, ...] = (
    2**63 - 1,
    -(2**62),
    0,
    -1,
    float("nan"),
    float("inf"),
    1e308,
    "\x1b]0;title\x07\x1b[2J",
    "x" * 5000,
    b"\xff\xfe\xfa",
    "",
    np.arange(7),
    True,
    "[" * 5000,
    '{"a": 1}',
)
HUGE = (10**3, 10**6, 10**9, 10**12)
UNREADABLE = ("HDF5 made no progress", "HDF5 crashed")
SMALL_BYTES = 1 << 24
"""Datasets a mutation reads whole (a retyped or shifted one): a previous mutation may have declared
one of terabytes, which the mutation leaves alone."""


def base_capture(path: Path, kind: str) -> Path:
    """A small valid capture of ``kind`` (with ground truth, triggers and a stored result for hybrid)."""
    psfmt.write(sample_capture(kind, seed=0, n_events=600), path)
    return path


def _objects(f: h5py.File) -> list[str]:
    names: list[str] = []
    f.visit(names.append)
    return names


def _datasets(f: h5py.File) -> list[str]:
    return [n for n in _objects(f) if isinstance(f.get(n), h5py.Dataset)]


def _small(ds: object) -> bool:
    return isinstance(ds, h5py.Dataset) and ds.size * ds.dtype.itemsize <= SMALL_BYTES


def _flip_bits(path: Path, rng: np.random.Generator) -> None:
    raw = bytearray(path.read_bytes())
    for _ in range(int(rng.integers(1, 5))):
        # half the flips hit the first 16 KiB, where HDF5 keeps most of its metadata
        end = min(len(raw), 16384) if rng.random() < 0.5 else len(raw)
        raw[int(rng.integers(0, end))] ^= 1 << int(rng.integers(0, 8))
    path.write_bytes(bytes(raw))


def _overwrite(path: Path, rng: np.random.Generator) -> None:
    raw = bytearray(path.read_bytes())
    n = int(rng.integers(1, 65))
    at = int(rng.integers(0, max(1, len(raw) - n)))
    raw[at : at + n] = rng.integers(0, 256, n, dtype=np.uint8).tobytes() if rng.random() < 0.7 else bytes(n)
    path.write_bytes(bytes(raw))


def _truncate(path: Path, rng: np.random.Generator) -> None:
    raw = path.read_bytes()
    path.write_bytes(raw[: int(rng.integers(0, len(raw)))])


def _declare_huge(f: h5py.File, rng: np.random.Generator) -> None:
    name = str(rng.choice(_datasets(f)))
    ds = f[name]
    shape = tuple(int(d) for d in ds.shape) or (1,)
    axis = int(rng.integers(0, len(shape)))
    shape = shape[:axis] + (int(rng.choice(HUGE)),) + shape[axis + 1 :]
    dtype = ds.dtype
    del f[name]
    chunks = tuple(max(1, min(s, 64)) for s in shape)
    if rng.random() < 0.5:
        f.create_dataset(name, shape=shape, dtype=dtype, chunks=chunks, compression="gzip")
    else:
        f.create_dataset(name, shape=shape, dtype=dtype)


def _attribute(f: h5py.File, rng: np.random.Generator) -> None:
    name = str(rng.choice(["/", *_objects(f)]))
    obj = f[name]
    keys = list(obj.attrs) or ["width"]
    key = str(rng.choice([*keys, "ms_origin_us", "width", "options", "model", "format_version"]))
    value = HOSTILE_VALUES[int(rng.integers(0, len(HOSTILE_VALUES)))]
    obj.attrs[key] = np.void(value) if isinstance(value, bytes) and rng.random() < 0.3 else value


def _delete(f: h5py.File, rng: np.random.Generator) -> None:
    name = str(rng.choice(_objects(f)))
    if rng.random() < 0.5 and f[name].attrs:
        del f[name].attrs[str(rng.choice(list(f[name].attrs)))]
    else:
        del f[name]


def _retype(f: h5py.File, rng: np.random.Generator) -> None:
    name = str(rng.choice(_datasets(f)))
    if not _small(f[name]):
        return
    values = f[name][()]
    del f[name]
    choice = int(rng.integers(0, 4))
    if choice == 0:
        f[name] = np.asarray(values).astype(np.float64) * 1e300
    elif choice == 1:
        f[name] = np.asarray(values).reshape(-1)[::-1].copy()
    elif choice == 2:
        f[name] = np.bytes_(b"\x00" * 8)
    else:
        f[name] = np.asarray(values).astype(np.int64) + 2**62


def _link(f: h5py.File, rng: np.random.Generator) -> None:
    name = str(rng.choice(["frames", "events", "lights", "calibration", "ground_truth", "results", "triggers"]))
    if name in f:
        del f[name]
    choice = int(rng.integers(0, 3))
    if choice == 0:
        f[name] = h5py.ExternalLink("/etc/passwd", "/")
    elif choice == 1:
        f[name] = h5py.SoftLink(f"/{name}")
    else:
        f[name] = h5py.SoftLink("/nowhere")


def _times(f: h5py.File, rng: np.random.Generator) -> None:
    offset = int(rng.choice([2**53 + 1, 2**62, -(2**62)]))
    for name in ("events/t", "frames/t_start_us", "frames/t_end_us", "triggers/t"):
        if name in f and _small(f[name]):
            values = f[name][()] + offset
            del f[name]
            f[name] = values
    if "events" in f:
        f["events"].attrs["ms_origin_us"] = offset


def _in_file(edit: Callable[[h5py.File, np.random.Generator], None]) -> Callable[[Path, np.random.Generator], None]:
    def apply(path: Path, rng: np.random.Generator) -> None:
        with h5py.File(path, "r+") as f:
            edit(f, rng)

    return apply


MUTATIONS: dict[str, Callable[[Path, np.random.Generator], None]] = {
    "flip bits": _flip_bits,
    "overwrite bytes": _overwrite,
    "truncate": _truncate,
    "declare huge": _in_file(_declare_huge),
    "hostile attribute": _in_file(_attribute),
    "delete": _in_file(_delete),
    "retype": _in_file(_retype),
    "link": _in_file(_link),
    "times": _in_file(_times),
}


def mutate(base: Path, path: Path, kinds: list[str], seed: int) -> Path:
    """``base`` copied to ``path`` with the mutations ``kinds`` applied in order, seeded by ``seed``."""
    shutil.copyfile(base, path)
    rng = np.random.default_rng(seed)
    for kind in kinds:
        try:
            MUTATIONS[kind](path, rng)
        except (OSError, KeyError, ValueError, TypeError, RuntimeError):
            # an h5py edit of an already damaged file may fail: the file is what it is
            pass
    return path


def outcome(action: Callable[[], object]) -> str:
    try:
        report = action()
    except psfmt.FormatError as exc:
        return f"error: {exc.message}"
    if isinstance(report, psfmt.ValidationReport):
        return "valid" if report.valid else f"invalid: {report.errors[0].text}"
    return "valid"


def read_everything(path: Path) -> None:
    """Read every part of the capture at ``path`` the way a solver and ``info`` would."""
    from pstoolkit.cli.info import describe

    with psfmt.read(path, verify=True, isolate_check=False) as capture:
        describe(capture)
        if capture.frames is not None:
            for k in range(capture.frames.count):
                capture.frames.as_float(k)
        if capture.events is not None:
            for block in capture.events.chunks():
                assert block.is_sorted()
            capture.events.window(-(2**40), 2**40)
        if capture.triggers is not None:
            capture.triggers.read()
        for result in capture.results.values():
            dict(result.maps)


def probe(path: Path, *, isolated: bool = True) -> str:
    """The property, on one file: ``validate`` answers with a report or one FormatError; the reader
    refuses exactly what it reports (the same first line) and reads all of a valid file. Returns
    "valid", "invalid: <first error>" or "error: <message>"; raises AssertionError when the reader and
    the validator disagree, and lets any other exception through (a traceback is a bug)."""
    checked = outcome(lambda: psfmt.validate(path, isolate_check=isolated))
    if checked.startswith("error: ") and any(word in checked for word in UNREADABLE):
        return checked  # HDF5 hangs or crashes on it: only a child process may touch it
    # the reader raises the validator's first error, or the same FormatError, or reads it all
    expected = checked if category(checked) != "invalid" else f"error: {checked.split(': ', 1)[1]}"
    read = outcome(lambda: read_everything(path))
    assert read == expected, (path, checked, read)
    return checked


def category(outcome: str) -> str:
    """"valid", "invalid" (a finding) or "error" (unreadable: a one-line FormatError)."""
    return outcome.split(":", 1)[0]
