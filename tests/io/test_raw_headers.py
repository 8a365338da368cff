"""Issue 25: ``convert raw`` on recordings as they come off the camera: the two headers of the issue
convert with no option, the capture records where the geometry came from and keeps every header
line, ``--geometry`` overrides, and a file that names no geometry is one line saying what was sought."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers.prophesee import GEN3_EVT2, GEN41_EVT3

import psfmt
from psfmt.eventfiles import evt2, evt3
from psfmt.events import EventArray
from pstoolkit.cli import main


def recording(width: int, height: int, n: int = 3000, seed: int = 0) -> EventArray:
    """Sorted events whose x reaches width − 1 and y height − 1 (x up to 1279, y up to 719 for the Gen4.1 file)."""
    rng = np.random.default_rng(seed)
    x, y = rng.integers(0, width, n), rng.integers(0, height, n)
    x[7], y[11] = width - 1, height - 1
    return EventArray(x, y, np.sort(rng.integers(0, 40 << 20, n)), rng.choice([-1, 1], n))


@pytest.mark.parametrize(
    "name,text,geometry,source",
    [
        ("gen41_recording.raw", GEN41_EVT3, (1280, 720), "system_ID 48 (Gen4.1)"),
        ("gen3_recording.raw", GEN3_EVT2, (640, 480), "system_ID 21 (Gen3.0)"),
    ],
)
def test_real_headers_convert_with_no_edit_and_no_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str, text: str, geometry: tuple[int, int], source: str
) -> None:
    events = recording(*geometry)
    encoded = evt3.encode(events) if "evt 3.0" in text else evt2.encode(events)[0]
    src = tmp_path / name
    src.write_bytes(text.encode("ascii") + encoded)
    out = tmp_path / "a.h5"
    assert main(["convert", "raw", str(src), "-o", str(out)]) == 0
    assert capsys.readouterr().out == f"wrote {out}\n"
    with psfmt.read(out) as capture:
        assert (capture.events.width, capture.events.height) == geometry
        decoded = capture.events.read()
        assert len(decoded) == len(events) and all(np.array_equal(getattr(decoded, c), getattr(events, c)) for c in "xytp")
        lines = capture.description.splitlines()
    # where the geometry came from, then every header line (the unknown ones included), in file order
    assert lines == [f"{name} converted by pstoolkit convert raw", f"geometry_source = {source}", "raw_header:", *text.splitlines()]
    assert psfmt.validate(out).valid
    assert main(["info", "--json", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert f"geometry_source = {source}" in info["description"] and (info["events"]["width"], info["events"]["height"]) == geometry
    assert main(["info", str(out)]) == 0
    assert f"geometry_source = {source} raw_header: % Date" in capsys.readouterr().out


def test_geometry_option_overrides_and_a_nameless_file_says_what_was_sought(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    events = recording(64, 48, 400)
    src = tmp_path / "lab_rig.raw"
    src.write_bytes(b"% evt 3.0\n% integrator_name Acme\n% system_ID 48\n% rig_id ring-7\n" + evt3.encode(events))
    out = tmp_path / "rig.h5"
    assert main(["convert", "raw", str(src), "-o", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"pstoolkit: error: {src}: RAW header declares no sensor geometry: no % geometry WxH, no width=/height= in % format, "
        "no % Width/% Height, and no Prophesee sensor known from system_ID, plugin_name, sensor_name or sensor_generation "
        "(integrator Acme: Prophesee's sensor tables do not apply to system_ID 48); give the sensor size with --geometry WxH\n"
    )
    assert not out.exists()
    assert main(["convert", "raw", str(src), "-o", str(out), "--geometry", "64x48", "-q"]) == 0
    with psfmt.read(out) as capture:
        assert (capture.events.width, capture.events.height, len(capture.events)) == (64, 48, 400)
        assert capture.description.splitlines()[1:3] == ["geometry_source = --geometry 64x48", "raw_header:"]
        assert "% rig_id ring-7" in capture.description.splitlines()
    # the override also wins over a header's own geometry: events beyond it are dropped and counted
    declared = tmp_path / "declared.raw"
    evt3.write_raw(declared, [events], 64, 48)
    assert main(["convert", "raw", str(declared), "-o", str(tmp_path / "small.h5"), "--geometry", "32x48", "-q"]) == 0
    with psfmt.read(tmp_path / "small.h5") as capture:
        assert len(capture.events) == int((events.x < 32).sum()) and capture.events.width == 32
    for bad, why in (("64", "option geometry: expected WxH (e.g. 1280x720), got '64'"),
                     ("0x48", "RAW header declares a 0×48 sensor; each side must be 1…65536 pixels")):
        capsys.readouterr()
        assert main(["convert", "raw", str(src), "-o", str(tmp_path / "bad.h5"), "--geometry", bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("pstoolkit: error: ") and err.rstrip().endswith(why) and err.count("\n") == 1


def test_a_long_or_hostile_header_is_kept_within_bounds(tmp_path: Path) -> None:
    lines = [f"% note_{k} {'x' * 100}" for k in range(400)]
    src = tmp_path / "chatty.raw"
    src.write_bytes(("% evt 3.0\n% format EVT3;height=4;width=4\n% esc \x1b]0;title\x07 here\n" + "\n".join(lines) + "\n").encode()
                    + evt3.encode(recording(4, 4, 20)))
    out = tmp_path / "chatty.h5"
    assert main(["convert", "raw", str(src), "-o", str(out), "-q"]) == 0
    with psfmt.read(out) as capture:
        kept = capture.description.splitlines()
    assert kept[1] == "geometry_source = format EVT3;height=4;width=4" and kept[5] == "% esc ]0;title here"
    assert kept[-1].startswith("% … ") and kept[-1].endswith("more header line(s) not kept") and len(capture.description) < 20000
