"""The log of a batch run (``batch.json`` in its output folder): what became of each pair; the
report lists the failed ones."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pstoolkit.errors import UserError
from pstoolkit.io.textdata import read_json

LOG_FILE = "batch.json"


@dataclass(frozen=True)
class Outcome:
    """What became of a pair: ``status`` is done, skipped (its result folder was already complete) or
    failed with a one-line ``error`` (and the ``traceback`` of an unexpected exception);
    ``seconds`` is the solver time of a pair done now."""

    object: str
    solver: str
    capture: str
    folder: str
    status: str
    error: str | None = None
    seconds: float | None = None
    traceback: str | None = None


def read_failures(outdir: Path) -> list[Outcome]:
    """The failed pairs of the last batch run in ``outdir`` (none without ``batch.json``)."""
    path = outdir / LOG_FILE
    if not path.is_file():
        return []
    data = read_json(path)
    try:
        return [Outcome(**entry) for entry in data["pairs"] if entry["status"] == "failed"]
    except (ValueError, KeyError, TypeError) as exc:
        raise UserError(f"{path}: not a batch log written by `pstoolkit batch` ({exc})") from None
