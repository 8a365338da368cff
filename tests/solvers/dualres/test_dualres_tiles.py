"""``dualres`` in spatial tiles on Dask: the tiled normals agree with the untiled ones with no seam,
a local cluster and a separate ``dask scheduler`` with two ``dask worker`` processes on loopback give
the same maps, progress counts tiles, the memory budget picks the tiles, and options that cannot
apply are refused with one line."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import psfmt
from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.evaluation.metrics import angular_error_deg
from pstoolkit.plugin.manager import get_registries
from pstoolkit.solve.base import run_solver
from pstoolkit_dualres.tiling import TILE_BYTES_PER_PIXEL, WORKER_BASE_BYTES, plan

EPOCHS = "epochs=30"
TILES = ("tile_px=24", "overlap_px=8")


def _solve(capture: psfmt.Capture, *assignments: str, progress=None) -> tuple:
    entry = get_registries().solvers.get("dualres")
    kwargs = {} if progress is None else {"progress": progress}
    return run_solver(entry, capture, entry.parse_options([EPOCHS, *assignments]), workers=2 if "tile_px=-1" not in assignments else None,
                      **kwargs)[0], entry


def test_tiles_agree_with_the_whole_capture_without_a_seam(blobs_48: Path) -> None:
    messages: list[str] = []
    with psfmt.read(blobs_48) as capture:
        truth = capture.ground_truth
        whole, _ = _solve(capture, "tile_px=-1")
        tiled, _ = _solve(capture, *TILES, progress=lambda fraction, message: messages.append(message))
    assert tiled.diagnostics["tiling"]["tiles"] == 4 and tiled.mask.all()
    assert messages[0] == "tile 0/4" and messages[-1] == "tile 4/4" and "ETA" in messages[1]
    error_whole = angular_error_deg(whole.normal, truth.normal, truth.mask)
    error_tiled = angular_error_deg(tiled.normal, truth.normal, truth.mask)
    # measured: 0.524° whole, 0.527° tiled; at the seams 0.748° and 0.741°
    assert abs(error_tiled[truth.mask].mean() - error_whole[truth.mask].mean()) < 0.1
    # no seam: along the tile boundaries (the blending bands) the tiles are as good as the whole solve
    seam = np.zeros_like(truth.mask)
    seam[20:28, :] = seam[:, 20:28] = True
    inside = truth.mask & seam
    assert error_tiled[inside].mean() < error_whole[inside].mean() + 0.1
    for name in ("albedo", "roughness", "cast_shadow"):
        assert tiled.maps[name].shape[:2] == (48, 48)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture()
def loopback_cluster() -> Iterator[str]:
    """``dask scheduler`` and two single-thread ``dask worker`` processes on 127.0.0.1."""
    dask = str(Path(sys.executable).with_name("dask"))
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    processes = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], **quiet)]
    try:
        processes += [subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1"], **quiet)
                      for _ in range(2)]
        from distributed import Client

        with Client(address, timeout="30s", set_as_default=False) as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for process in reversed(processes):
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()


SETS = [arg for option in (EPOCHS, *TILES) for arg in ("--set", option)]


@pytest.fixture(scope="module")
def local_normal(blobs_48: Path, tmp_path_factory: pytest.TempPathFactory) -> np.ndarray:
    """The tiled normals of ``pstoolkit run --workers 2`` (a local cluster), which the other clusters
    are held to."""
    out = tmp_path_factory.mktemp("local") / "run"
    assert main(["run", str(blobs_48), "--solver", "dualres", *SETS, "--workers", "2", "-q", "-o", str(out)]) == 0
    return np.load(out / "normal.npy")


def test_a_scheduler_with_two_workers_gives_what_the_local_cluster_gives(blobs_48: Path, tmp_path: Path, loopback_cluster: str,
                                                                          local_normal: np.ndarray) -> None:
    started = time.perf_counter()
    assert main(["run", str(blobs_48), "--solver", "dualres", *SETS, "--scheduler", loopback_cluster, "-q",
                 "-o", str(tmp_path / "remote")]) == 0
    assert time.perf_counter() - started < 600
    local, remote = local_normal, np.load(tmp_path / "remote" / "normal.npy")
    mask = np.linalg.norm(local, axis=-1) > 0
    angle = np.degrees(np.arccos(np.clip(np.sum(local * remote, axis=-1), -1.0, 1.0)))[mask]
    # the same code on the same crops, one torch thread each: measured 0.028° at most, 0.0003° on average
    assert angle.mean() < 0.005 and angle.max() < 0.1


def test_the_memory_budget_decides_when_and_how_to_tile() -> None:
    options = {"tile_px": 0, "memory_gb": 0.0, "overlap_px": 32}
    assert plan((64, 64), options, scheduler=None, workers=None) is None
    assert plan((64, 64), {**options, "tile_px": 32, "overlap_px": 8}, scheduler=None, workers=None) is not None
    assert plan((64, 64), {**options, "tile_px": -1}, scheduler="tcp://x:1", workers=None) is None
    # a scheduler always gets tiles, even one
    assert len(plan((64, 64), options, scheduler="tcp://127.0.0.1:1", workers=None)) == 1
    # 2048 × 2448 under 3 GB on two local workers: tiles whose predicted peak fits
    tiles = plan((2048, 2448), {**options, "memory_gb": 3.0}, scheduler=None, workers=2)
    largest = max(t.crop_pixels for t in tiles)
    assert len(tiles) > 4 and 2 * (WORKER_BASE_BYTES + TILE_BYTES_PER_PIXEL * largest) < 3e9
    # 1024² whole fits 3 GB (measured 2.41 GB), so a budget of 3 GB solves it in one piece
    assert plan((1024, 1024), {**options, "memory_gb": 3.0}, scheduler=None, workers=2) is None
    with pytest.raises(UserError, match=r"memory_gb = 0.50 leaves room for tiles of only \d+ px"):
        plan((4096, 4096), {**options, "memory_gb": 0.5}, scheduler=None, workers=2)


@pytest.mark.parametrize(("args", "message"), [
    (["--solver", "frameps", "--scheduler", "tcp://127.0.0.1:1"], "solver 'frameps' does not work in tiles"),
    (["--solver", "dualres", "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "--workers: only for the local cluster"),
    (["--solver", "dualres", "--workers", "0"], "--workers 0: need at least one worker"),
])
def test_options_that_cannot_apply_are_one_line(blobs_48: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                args: list[str], message: str) -> None:
    assert main(["run", str(blobs_48), *args, "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_a_batch_pair_sends_its_tiles_to_the_batch_cluster(blobs_48: Path, tmp_path: Path, local_normal: np.ndarray) -> None:
    assert main(["batch", str(blobs_48), "--solver", "dualres", *SETS, "--workers", "2", "-q", "-o", str(tmp_path / "batch")]) == 0
    folder = next((tmp_path / "batch").glob("*-dualres"))
    tiling = json.loads((folder / "result.json").read_text())["diagnostics"]["tiling"]
    assert tiling["tiles"] == 4 and tiling["where"] == "the running Dask cluster"
    run, batch = local_normal, np.load(folder / "normal.npy")
    mask = np.linalg.norm(run, axis=-1) > 0
    angle = np.degrees(np.arccos(np.clip(np.sum(run * batch, axis=-1), -1.0, 1.0)))[mask]
    assert angle.mean() < 0.005 and angle.max() < 0.1
