"""``pstoolkit batch`` on a two-worker LocalCluster: the same numbers as serial runs, a worker killed
mid-run and a rerun that recomputes only the lost pair, a corrupt capture that fails alone, and the
planning rules (options per solver, unique objects).

Besides frameps and eventps, the workers load a test solver ``gate``: the flat normal (0, 0, 1)
inside the lit pixels, which logs each call, raises on a capture named ``explode`` and, while a file
``block-<object>`` exists, blocks after announcing its process id, so the test can kill the worker
running it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import dask
import numpy as np
import pytest
from distributed import Client
from helpers.batch import session_captures
from helpers.interrupt import interruptible

from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.evaluation.batchlog import Outcome
from pstoolkit.plugin import manager as plugins
from pstoolkit.solve.batch import expand_captures, is_complete, plan, run_batch, run_pair, solver_options
from pstoolkit.solve.cluster import local_cluster
from pstoolkit.testing import fake_distribution

SOLVERS = ("frameps", "eventps")
GATE_ENV = "PSK_GATE_DIR"

GATE_PLUGIN = """
    import os
    import time
    from pathlib import Path

    import numpy as np

    from pstoolkit import Solver, SolverResult, hookimpl


    class Gate(Solver):
        name = "gate"
        summary = "the flat normal (0, 0, 1) on lit pixels; blocks while block-<object> exists"
        needs = frozenset({"frames"})

        def solve(self, capture, options, progress):
            gates = Path(os.environ["PSK_GATE_DIR"])
            obj = Path(capture.path).stem
            with open(gates / "calls.log", "a") as log:
                log.write(f"{obj}\\n")
            if obj == "explode":
                raise RuntimeError("gate: a solver bug")
            if (gates / f"block-{obj}").exists():
                (gates / f"running-{os.getpid()}").touch()
                time.sleep(60)  # the test kills this worker long before
                raise RuntimeError("gate: the test did not kill this worker")
            lit = capture.frames.as_float().max(axis=(0, 3)) > 0.02
            normal = np.zeros((*lit.shape, 3), np.float32)
            normal[..., 2] = 1.0
            return SolverResult(normal=normal, mask=lit)


    @hookimpl
    def pstoolkit_register_solvers(registry):
        registry.register(Gate)
"""




@pytest.fixture(scope="session")
def captures(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    return session_captures(tmp_path_factory)


@pytest.fixture(scope="module")
def gates(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The plugin set of this module (core, frameps, eventps, gate) in this process and the workers."""
    root = tmp_path_factory.mktemp("gate")
    site = fake_distribution(root / "site", "pskfake-gate", "1.0", {"gate": "pskfake_gate"}, {"pskfake_gate": GATE_PLUGIN})
    with pytest.MonkeyPatch.context() as mp:
        mp.syspath_prepend(str(site))
        mp.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")])))
        mp.delenv(plugins.DISABLE_ENV, raising=False)
        mp.setenv(plugins.ALLOW_ENV, "core,frameps,eventps,gate")
        mp.setenv(GATE_ENV, str(root))
        plugins.reset()
        yield root
    plugins.reset()


@pytest.fixture(scope="module")
def client(gates: Path) -> Iterator[Client]:
    """Two single-thread worker processes; a pair whose worker dies fails at once (no retry), so the
    killed-worker test sees the loss."""
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        cluster = local_cluster(2)
    with Client(cluster, set_as_default=False) as dask_client:
        yield dask_client
    cluster.close()


def _result(folder: str | Path) -> dict:
    return json.loads((Path(folder) / "result.json").read_text())


def _assert_same_maps(a: Path, b: Path) -> None:
    """The maps of two result folders agree to float rounding: the .npy values to 1e-6, the 16-bit
    normal PNG to one count and the error PNG in all but a few pixels (a rounding change there moves
    one pixel to the next colour of the scale)."""
    for name in ("normal.npy", "error.npy"):
        np.testing.assert_allclose(np.load(a / name), np.load(b / name), rtol=0, atol=1e-6, equal_nan=True, err_msg=str(a / name))
    normal = [cv2.imread(str(folder / "normal.png"), cv2.IMREAD_UNCHANGED).astype(np.int64) for folder in (a, b)]
    assert np.abs(normal[0] - normal[1]).max() <= 1, a
    error = [cv2.imread(str(folder / "error.png"), cv2.IMREAD_UNCHANGED) for folder in (a, b)]
    assert np.count_nonzero(np.any(error[0] != error[1], axis=-1)) <= 0.001 * error[0].shape[0] * error[0].shape[1], a


def test_batch_gives_the_numbers_of_serial_runs(
    client: Client, captures: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pairs = plan(expand_captures(captures), solver_options(SOLVERS, []), tmp_path / "batch", device="cpu")
    ticks: list[tuple[float, str]] = []
    outcomes = run_batch(pairs, client, lambda fraction, message: ticks.append((fraction, message)))
    assert [(o.object, o.solver, o.status, o.error) for o in outcomes] == [
        (c.stem, s, "done", None) for c in captures for s in SOLVERS
    ]
    assert ticks[0] == (0.0, "0/6 pairs") and ticks[-1] == (1.0, "6/6 pairs") and len(ticks) == 7
    for pair in pairs:
        serial = tmp_path / "serial" / Path(pair.folder).name
        assert main(["run", pair.capture, "--solver", pair.solver, "-o", str(serial), "--device", "cpu"]) == 0
        mine, theirs = _result(pair.folder), _result(serial)
        for key in ("n_pixels", "coverage", "data_rate", "options", "object", "capture", "maps"):
            assert mine[key] == theirs[key], (pair.folder, key)
        # a Dask worker runs with one BLAS/OpenMP thread (its nanny sets OMP_NUM_THREADS=1), this process
        # with the machine's: the same numbers to rounding, not necessarily the same bits
        for key in ("mae_deg", "mae_solved_deg", "median_deg", "below_11_25"):
            assert mine[key] == pytest.approx(theirs[key], rel=1e-9, abs=1e-12), (pair.folder, key)
        _assert_same_maps(Path(pair.folder), serial)
    assert _result(pairs[0].folder)["mae_deg"] < 10.0  # frameps on the sphere: a real result, not a blank
    capsys.readouterr()
    # all complete: the rerun needs no cluster, so an unreachable scheduler does not matter
    rerun = ["batch", *map(str, captures), "--solver", "frameps", "--solver", "eventps", "-o", str(tmp_path / "batch")]
    assert main([*rerun, "--device", "cpu", "--scheduler", "tcp://127.0.0.1:9", "--quiet"]) == 0
    assert capsys.readouterr().out == f"6 pairs: 0 done, 6 skipped, 0 failed → {tmp_path / 'batch'} (log batch.json)\n"


def test_killed_worker_then_rerun_recomputes_only_the_lost_pair(
    client: Client, gates: Path, captures: list[Path], tmp_path: Path
) -> None:
    (gates / "calls.log").unlink(missing_ok=True)
    pairs = plan(expand_captures(captures), solver_options(["frameps", "gate"], []), tmp_path / "batch", device="cpu")
    blocked = "blobs"
    (gates / f"block-{blocked}").touch()
    outcomes: list[Outcome] = []
    runner = threading.Thread(target=lambda: outcomes.extend(run_batch(pairs, client)))
    runner.start()
    deadline = time.monotonic() + 30
    while not (running := list(gates.glob("running-*"))) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert running, "the gate solver never started on the blocked capture"
    (gates / f"block-{blocked}").unlink()
    os.kill(int(running[0].name.split("-")[1]), signal.SIGKILL)
    running[0].unlink()
    runner.join(60)
    assert not runner.is_alive()
    lost = [o for o in outcomes if o.status == "failed"]
    assert [(o.object, o.solver, o.error) for o in lost] == [
        (blocked, "gate", "the worker running this pair died (killed, or out of memory)")
    ]
    assert sum(o.status == "done" for o in outcomes) == 5
    assert not Path(lost[0].folder).exists()
    finished = {o.folder: (Path(o.folder) / "result.json").stat().st_mtime_ns for o in outcomes if o.status == "done"}
    # what a worker killed while writing leaves behind: the rerun clears it
    stale = Path(lost[0].folder).with_name(f".{Path(lost[0].folder).name}.999.0badf00d.tmp")
    stale.mkdir()
    (stale / "normal.npy").write_bytes(b"partial")
    rerun = run_batch(pairs, client)
    assert [(o.object, o.solver, o.status) for o in rerun] == [
        (o.object, o.solver, "done" if o.status == "failed" else "skipped") for o in outcomes
    ]
    assert {folder: (Path(folder) / "result.json").stat().st_mtime_ns for folder in finished} == finished
    assert _result(lost[0].folder)["object"] == blocked
    assert not stale.exists()
    calls = (gates / "calls.log").read_text().split()
    assert sorted(calls) == sorted(["ball", "blobs", "blobs", "relief"])  # only the lost pair ran again


def test_corrupt_capture_fails_alone_through_the_cli(
    client: Client, captures: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "captures"
    folder.mkdir()
    for capture in captures[:2]:
        shutil.copy(capture, folder / capture.name)
    corrupt = folder / "corrupt.h5"
    corrupt.write_bytes(captures[0].read_bytes()[:4096])
    out = tmp_path / "batch"
    args = ["batch", str(folder), "--solver", "frameps", "--solver", "gate", "-o", str(out)]
    code = main([*args, "--scheduler", client.scheduler.address, "--device", "cpu", "--quiet"])
    captured = capsys.readouterr()
    assert code == 1
    failed = [line for line in captured.err.splitlines() if line.startswith("pstoolkit: failed:")]
    assert len(failed) == 2 and all(line.startswith("pstoolkit: failed: corrupt × ") and str(corrupt.resolve()) in line for line in failed)
    assert captured.out.strip() == f"6 pairs: 4 done, 0 skipped, 2 failed → {out} (log batch.json)"
    log = json.loads((out / "batch.json").read_text())
    assert log["counts"] == {"done": 4, "skipped": 0, "failed": 2}
    errors = {p["solver"]: p["error"] for p in log["pairs"] if p["status"] == "failed"}
    assert set(errors) == {"frameps", "gate"} and errors["frameps"] == errors["gate"]
    assert errors["frameps"].startswith(f"{corrupt.resolve()}: ")
    assert sorted(p.name for p in out.iterdir()) == ["ball-frameps", "ball-gate", "batch.json", "blobs-frameps", "blobs-gate"]
    assert main([*args, "--scheduler", client.scheduler.address, "--quiet"]) == 1
    assert "6 pairs: 0 done, 4 skipped, 2 failed" in capsys.readouterr().out


def test_options_go_to_the_solvers_that_have_them(gates: Path) -> None:
    options = solver_options(["frameps", "gate"], ["frames=2", "frameps.robust=true"])
    assert options["frameps"]["frames"] == 2 and options["frameps"]["robust"] is True
    assert options["gate"] == {}
    with pytest.raises(UserError, match=r"^--set 'nope=1': none of the solvers frameps, gate has an option 'nope'$"):
        solver_options(["frameps", "gate"], ["nope=1"])
    with pytest.raises(UserError, match=r"^--solver 'gate' is given twice$"):
        solver_options(["gate", "gate"], [])


def test_bad_input_is_one_line_exit_2(gates: Path, captures: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    twin = tmp_path / "other" / captures[0].name
    twin.parent.mkdir()
    shutil.copy(captures[0], twin)
    cases = {
        (str(captures[0]), str(twin)): f"captures {captures[0].resolve()} and {twin.resolve()} have the same name 'ball': rename one",
        (str(tmp_path / "missing.h5"),): f"{tmp_path / 'missing.h5'}: no such file or folder",
        (str(tmp_path / "other"), "--workers", "0"): "--workers 0: need at least one worker",
        (str(tmp_path / "other"), "--scheduler", "tcp://127.0.0.1:9", "--workers", "2"): (
            "--workers: only for the local cluster; an existing scheduler (--scheduler) has its own workers"
        ),
    }
    for args, message in cases.items():
        assert main(["batch", *args, "--solver", "gate", "-o", str(tmp_path / "out")]) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {message}\n"
    assert not (tmp_path / "out").exists()


def test_a_result_of_other_options_is_replaced_not_skipped(gates: Path, captures: list[Path], tmp_path: Path) -> None:
    (first,) = plan(expand_captures(captures[:1]), solver_options(["frameps"], []), tmp_path, device="cpu")
    assert not is_complete(first)
    assert run_pair(first).status == "done" and is_complete(first)
    # (not robust=true: three long exposures leave nothing to drop, which is an error)
    (other,) = plan(expand_captures(captures[:1]), solver_options(["frameps"], ["threshold=0.01"]), tmp_path, device="cpu")
    assert other.folder == first.folder and not is_complete(other)
    assert run_pair(other).status == "done"
    assert is_complete(other) and not is_complete(first)
    assert _result(other.folder)["options"]["threshold"] == 0.01
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball-frameps"]  # no temporary or outdated folder left


def test_an_unexpected_solver_error_is_recorded_with_its_traceback(gates: Path, captures: list[Path], tmp_path: Path) -> None:
    explode = tmp_path / "explode.h5"
    shutil.copy(captures[0], explode)
    (pair,) = plan([explode], solver_options(["gate"], []), tmp_path / "out", device="cpu")
    outcome = run_pair(pair)
    assert (outcome.status, outcome.error) == ("failed", "RuntimeError: gate: a solver bug")
    assert outcome.traceback is not None and 'raise RuntimeError("gate: a solver bug")' in outcome.traceback
    assert not (tmp_path / "out").exists()  # no result folder, no temporary one left


def test_an_output_folder_that_cannot_be_written_is_refused_before_any_pair(
    captures: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 19, item 13: the output folder is tried before any pair runs (here no scheduler is even
    asked: the address is unreachable)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    cases = {blocker / "results": f"{blocker} is not a folder"}
    if os.geteuid() != 0:  # root writes into read-only folders
        readonly = tmp_path / "readonly"
        readonly.mkdir(mode=0o555)
        cases[readonly] = "Permission denied"
    for out, reason in cases.items():
        args = ["batch", str(captures[0]), "--solver", "frameps", "-o", str(out), "--scheduler", "tcp://127.0.0.1:9"]
        assert main(args) == 2
        assert capsys.readouterr().err == f"pstoolkit: error: {out}: cannot write the results there ({reason})\n"


def _command() -> list[str]:
    """The ``pstoolkit`` console script of this environment (or the same entry point through -c)."""
    script = Path(sys.executable).with_name("pstoolkit")
    return [str(script)] if script.is_file() else [sys.executable, "-c", "from pstoolkit.cli import main; main()"]


def test_ctrl_c_on_a_running_batch_is_one_line(captures: list[Path], tmp_path: Path) -> None:
    """Issue 19, item 14: Ctrl-C at a terminal reaches every process of the command (its process
    group); the workers ignore it, the command cancels and closes the cluster and says one line."""
    out = tmp_path / "out"
    command = [*_command(), "batch", *map(str, captures), "--solver", "frameps", "--solver", "eventps", "-o", str(out), "--workers", "2"]
    child = interruptible(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and child.poll() is None and not any(out.glob("*")):
        time.sleep(0.05)  # a pair is being written: the workers run
    os.killpg(child.pid, signal.SIGINT)
    try:
        stdout, stderr = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            os.killpg(child.pid, signal.SIGKILL)
    assert (child.returncode, stdout, stderr) == (130, "", "pstoolkit: error: interrupted\n")
