"""Batch runs on Dask distributed: every (capture, solver) pair is one task.

The client plans the pairs (``plan``), skips those whose result folder is already complete and
submits the rest; a worker opens the capture from its path, runs the solver and writes the result
folder under a temporary name, then renames it into place (``run_pair``), so a folder named
``<object>-<solver>`` with ``result.json`` is always complete and a rerun after a crash or a killed
worker recomputes only what is missing. Tasks carry paths and options and return a small record, so
no image data passes through the scheduler; with one thread per worker a worker holds one capture at
a time. A pair that fails (a corrupt capture, a solver error, a worker that died) is recorded with
its error in ``batch.json`` and the other pairs go on.
"""

from __future__ import annotations

import json
import secrets
import shutil
import traceback
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import psfmt
from psfmt.atomic import temporary_sibling
from psfmt.isolate import isolated
from pstoolkit._shared.progress import Progress, no_progress
from pstoolkit.errors import UserError
from pstoolkit.evaluation.batchlog import LOG_FILE, Outcome
from pstoolkit.evaluation.scoring import RESULT_FILE
from pstoolkit.io.folders import replace_folder
from pstoolkit.io.textdata import read_json, summary_json
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import resolve_device, resolve_options
from pstoolkit.solve.results import result_summary, solve_capture, write_result_folder

CAPTURE_SUFFIXES = (".h5", ".hdf5")
STATUSES = ("done", "skipped", "failed")


@dataclass(frozen=True)
class Pair:
    """One task: run ``solver`` with ``options`` on the capture file ``capture`` (absolute path) and
    write the result folder ``folder`` (absolute path, named ``<object>-<solver>``)."""

    capture: str
    object: str
    solver: str
    options: dict[str, Any]
    folder: str
    device: str = "auto"
    error_max_deg: float = 30.0


def expand_captures(paths: Sequence[Path]) -> list[Path]:
    """Capture files as given, and the ``*.h5``/``*.hdf5`` files directly inside each given folder,
    as absolute paths; a missing path or a folder without captures is a UserError."""
    captures: list[Path] = []
    for path in paths:
        if path.is_dir():
            inside = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in CAPTURE_SUFFIXES)
            if not inside:
                raise UserError(f"{path}: no capture files ({', '.join(CAPTURE_SUFFIXES)}) in this folder")
            captures += inside
        elif path.is_file():
            captures.append(path)
        else:
            raise UserError(f"{path}: no such file or folder")
    return [p.resolve() for p in captures]


def solver_options(solvers: Sequence[str], assignments: Sequence[str]) -> dict[str, dict[str, Any]]:
    """The full options of each solver, resolved (``solve.base.resolve_options``: what the result
    folders record and a rerun compares): ``NAME.key=value`` sets an option of solver NAME only, a
    plain ``key=value`` every listed solver that has the option ``key`` (a key none has is a UserError)."""
    if not solvers:
        raise UserError("--solver: give at least one solver")
    duplicates = sorted({s for s in solvers if solvers.count(s) > 1})
    if duplicates:
        raise UserError(f"--solver {duplicates[0]!r} is given twice")
    entries = {name: get_registries().solvers.get(name) for name in solvers}
    mine: dict[str, list[str]] = {name: [] for name in solvers}
    for pair in assignments:
        key = pair.partition("=")[0].strip()
        owner = next((name for name in solvers if key.startswith(f"{name}.")), None)
        if owner is not None:
            mine[owner].append(pair[pair.index(".", len(owner)) + 1 :])
            continue
        takers = [name for name, entry in entries.items() if any(o.name == key for o in entry.options)]
        if not takers:
            if "=" not in pair or not key:
                raise UserError(f"--set {pair!r}: expected key=value or SOLVER.key=value")
            raise UserError(f"--set {pair!r}: none of the solvers {', '.join(solvers)} has an option {key!r}")
        for name in takers:
            mine[name].append(pair)
    return {name: resolve_options(entries[name], entries[name].parse_options(mine[name])) for name in solvers}


def check_output_folder(outdir: Path) -> None:
    """Prove, before any pair runs and leaving nothing behind, that results can be written to
    ``outdir``: a file is written and removed in it, or in its nearest existing parent when it does not
    exist yet. A read-only or full folder, or a file in the way, is a UserError now, not after every
    capture was solved."""
    existing = outdir
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise UserError(f"{outdir}: cannot write the results there ({existing} is not a folder)")
    probe = temporary_sibling(existing / LOG_FILE)
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"{outdir}: cannot write the results there ({exc.strerror or exc})") from None


def plan(
    captures: Sequence[Path],
    options: dict[str, dict[str, Any]],
    outdir: Path,
    *,
    device: str = "auto",
    error_max_deg: float = 30.0,
) -> list[Pair]:
    """Every (capture, solver) pair, capture by capture; the object is the capture's stem, which must
    be unique, and the result folder ``outdir/<object>-<solver>``."""
    stems: dict[str, Path] = {}
    for capture in captures:
        if capture.stem in stems:
            raise UserError(f"captures {stems[capture.stem]} and {capture} have the same name {capture.stem!r}: rename one")
        stems[capture.stem] = capture
    root = outdir.resolve()
    pairs = [
        Pair(str(capture), capture.stem, solver, opts, str(root / f"{capture.stem}-{solver}"), device, error_max_deg)
        for capture in captures
        for solver, opts in options.items()
    ]
    folders: dict[str, Pair] = {}
    for pair in pairs:
        other = folders.setdefault(pair.folder, pair)
        if other is not pair:
            raise UserError(
                f"{other.object} × {other.solver} and {pair.object} × {pair.solver} would share the result folder {pair.folder}: rename a capture"
            )
    return pairs


def _plain(options: dict[str, Any]) -> Any:
    """Options as they read back from result.json (tuples become lists)."""
    return json.loads(summary_json(options))


def is_complete(pair: Pair) -> bool:
    """True when the pair's folder holds a result.json of the same solver, capture and options."""
    path = Path(pair.folder) / RESULT_FILE
    try:
        data = read_json(path)
    except UserError:
        return False
    return (
        isinstance(data, dict)
        and data.get("solver") == pair.solver
        and data.get("capture") == pair.capture
        and data.get("options") == _plain(pair.options)
    )


def _failed(pair: Pair, error: str, trace: str | None = None) -> Outcome:
    return Outcome(pair.object, pair.solver, pair.capture, pair.folder, "failed", error=error, traceback=trace)


def run_pair(pair: Pair) -> Outcome:
    """Worker side: solve one pair and write its result folder atomically (a temporary sibling folder,
    renamed when complete). Every error becomes a failed outcome, so nothing but this small record
    travels back (exceptions of plugins may not survive pickling). The capture is checked in a child
    process first, as ``pstoolkit run`` does (``psfmt.isolate``)."""
    partial = temporary_sibling(pair.folder)
    try:
        entry = get_registries().solvers.get(pair.solver)
        device = resolve_device(pair.device)
        capture = Path(pair.capture)
        with isolated():
            solved = solve_capture(entry, capture, pair.options, device=device)
        summary = result_summary(
            solved,
            entry=entry,
            name=pair.solver,
            obj=pair.object,
            capture=capture,
            device=device,
            options=pair.options,
            error_max_deg=pair.error_max_deg,
        )
        write_result_folder(partial, solved, summary)
        replace_folder(partial, Path(pair.folder))
    except (UserError, psfmt.FormatError) as exc:
        return _failed(pair, str(exc))
    except Exception as exc:  # a broken solver must not stop the batch: record it with its traceback
        return _failed(pair, f"{type(exc).__name__}: {exc}".splitlines()[0], traceback.format_exc())
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return Outcome(pair.object, pair.solver, pair.capture, pair.folder, "done", seconds=solved.seconds)


def _remove_partials(pair: Pair) -> None:
    """Temporary folders a killed worker left behind for this pair."""
    folder = Path(pair.folder)
    for stale in folder.parent.glob(f".{folder.name}.*.tmp"):
        shutil.rmtree(stale, ignore_errors=True)


def _lost(exc: BaseException) -> str:
    """The error line of a task that returned no outcome (its worker died, or it was cancelled)."""
    if type(exc).__name__ == "KilledWorker":
        return "the worker running this pair died (killed, or out of memory)"
    return f"{type(exc).__name__}: {exc}".splitlines()[0]


def run_batch(pairs: Sequence[Pair], client: Any, progress: Progress = no_progress) -> list[Outcome]:
    """Run the pairs on the Dask ``client`` (a ``distributed.Client``; unused, and may be None, when
    every pair is complete): complete ones are skipped, the others submitted as one task each;
    returns an outcome per pair, in the order of ``pairs``."""
    outcomes: dict[int, Outcome] = {}
    for index, pair in enumerate(pairs):
        if is_complete(pair):
            outcomes[index] = Outcome(pair.object, pair.solver, pair.capture, pair.folder, "skipped")
    todo = [index for index in range(len(pairs)) if index not in outcomes]
    for folder in sorted({Path(pair.folder).parent for pair in pairs}):
        folder.mkdir(parents=True, exist_ok=True)
    for index in todo:
        _remove_partials(pairs[index])
    total = len(pairs)

    def report() -> None:
        progress(len(outcomes) / total if total else 1.0, f"{len(outcomes)}/{total} pairs")

    report()
    if not todo:
        return [outcomes[index] for index in range(total)]
    from distributed import as_completed  # deferred: only batch runs need dask

    token = secrets.token_hex(8)
    # One submission for all pairs, so the scheduler sees the whole group at once and queues it,
    # handing each worker a pair only when it is idle.
    submitted = client.map(run_pair, [pairs[i] for i in todo], key=[f"pstoolkit-batch-{token}-{i}" for i in todo], retries=0)
    futures = dict(zip(submitted, todo))
    try:
        for future in as_completed(futures, loop=client.loop):
            index = futures[future]
            if future.status == "finished":
                outcomes[index] = future.result()
            else:
                outcomes[index] = _failed(pairs[index], _lost(future.exception()))
            future.release()
            report()
    except BaseException:
        client.cancel(list(futures))
        raise
    return [outcomes[index] for index in range(total)]


def status_counts(outcomes: Sequence[Outcome]) -> dict[str, int]:
    """How many pairs are done, skipped and failed."""
    return {status: sum(o.status == status for o in outcomes) for status in STATUSES}


def write_log(outdir: Path, outcomes: Sequence[Outcome]) -> Path:
    """``batch.json`` in ``outdir``: every pair's outcome of the last run and the counts by status."""
    path = outdir / LOG_FILE
    with psfmt.atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"counts": status_counts(outcomes), "pairs": [asdict(o) for o in outcomes]}, indent=2) + "\n", encoding="utf-8")
    return path


