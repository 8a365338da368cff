"""Round trips of every field of the hybrid-capture format (spec/hybrid-capture.md).

Arrays are compared bit for bit: HDF5 stores the values as they are (deflate and shuffle are lossless)
and nothing is recomputed on the way.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from helpers.captures import CREATED, FRAME_SIZE, sample_capture

import psfmt


def assert_params_equal(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert sorted(a) == sorted(b)
    for key, value in a.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(b[key], value)
        else:
            assert b[key] == value and type(b[key]) is type(value), key


def assert_captures_equal(a: psfmt.Capture, b: psfmt.Capture) -> None:
    """Every stored field of ``a`` equals ``b`` (arrays exactly, metadata with type)."""
    for key in ("description", "creator", "creator_version", "created", "kind"):
        assert getattr(b, key) == getattr(a, key), key
    assert (a.frames is None) == (b.frames is None)
    if a.frames is not None:
        fa, fb = a.frames, b.frames
        np.testing.assert_array_equal(np.asarray(fb.data), np.asarray(fa.data))
        assert np.asarray(fb.data).dtype == np.asarray(fa.data).dtype
        for key in ("color_order", "bit_depth", "saturation", "black_level", "response"):
            assert getattr(fb, key) == getattr(fa, key), key
        for key in ("t_start_us", "t_end_us", "light_direction", "light_intensity"):
            va, vb = getattr(fa, key), getattr(fb, key)
            assert (va is None) == (vb is None), key
            if va is not None:
                np.testing.assert_array_equal(vb, va)
                assert vb.dtype == va.dtype
    assert (a.events is None) == (b.events is None)
    if a.events is not None:
        assert (b.events.width, b.events.height) == (a.events.width, a.events.height)
        ea, eb = a.events.read(), b.events.read()
        for c in "xytp":
            np.testing.assert_array_equal(getattr(eb, c), getattr(ea, c))
            assert getattr(eb, c).dtype == getattr(ea, c).dtype
    assert (a.triggers is None) == (b.triggers is None)
    if a.triggers is not None:
        for c in ("t", "channel", "value"):
            np.testing.assert_array_equal(getattr(b.triggers, c), getattr(a.triggers, c))
    assert (a.lights is None) == (b.lights is None)
    if a.lights is not None:
        assert b.lights.model == a.lights.model
        assert_params_equal(a.lights.params, b.lights.params)
    ca, cb = a.calibration, b.calibration
    for key in ("contrast_pos", "contrast_neg", "refractory_us", "refractory_rule", "camera_model"):
        assert getattr(cb, key) == getattr(ca, key), key
    np.testing.assert_array_equal(cb.view_direction, ca.view_direction)
    for key in ("event_to_frame", "intrinsics"):
        va, vb = getattr(ca, key), getattr(cb, key)
        assert (va is None) == (vb is None), key
        if va is not None:
            np.testing.assert_array_equal(vb, va)
            assert vb.dtype == np.float64, key
    assert (a.ground_truth is None) == (b.ground_truth is None)
    if a.ground_truth is not None:
        for key in ("normal", "mask", "albedo", "depth"):
            np.testing.assert_array_equal(getattr(b.ground_truth, key), getattr(a.ground_truth, key))
        assert b.ground_truth.mask.dtype == np.bool_
        assert sorted(b.ground_truth.materials) == sorted(a.ground_truth.materials)
        for key, value in a.ground_truth.materials.items():
            np.testing.assert_array_equal(b.ground_truth.materials[key], value)
    assert sorted(b.results) == sorted(a.results)
    for name, ra in a.results.items():
        rb = b.results[name]
        assert (rb.name, rb.solver, rb.options, rb.seconds, rb.version, rb.created) == (
            ra.name, ra.solver, ra.options, ra.seconds, ra.version, ra.created)
        assert sorted(rb.maps) == sorted(ra.maps)
        for key, value in ra.maps.items():
            np.testing.assert_array_equal(rb.maps[key], value)


@pytest.mark.parametrize("kind", ["hybrid", "events", "frames"])
def test_every_field_survives_write_and_load(tmp_path: Path, kind: str) -> None:
    capture = sample_capture(kind, seed=3)
    psfmt.write(capture, tmp_path / "c.h5")
    loaded = psfmt.load(tmp_path / "c.h5")
    assert loaded.format_version == psfmt.FORMAT_VERSION_STR == "1.3"
    assert loaded.kind == kind
    assert_captures_equal(capture, loaded)
    report = psfmt.validate(tmp_path / "c.h5")
    assert report.errors == []


@pytest.mark.parametrize("kind", ["hybrid", "events", "frames"])
def test_a_perspective_camera_survives_write_and_load(tmp_path: Path, kind: str) -> None:
    capture = sample_capture(kind, seed=8)
    capture.calibration.camera_model = "perspective"
    # fx, fy, cx, cy and a skew that are not round in binary: compared bit for bit
    capture.calibration.intrinsics = np.array([[812.3456789, 0.1234567, 31.7], [0.0, 809.87654321, 32.05], [0.0, 0.0, 1.0]])
    psfmt.write(capture, tmp_path / "c.h5")
    assert psfmt.validate(tmp_path / "c.h5").errors == []
    loaded = psfmt.load(tmp_path / "c.h5")
    assert loaded.format_version == "1.3" and loaded.calibration.camera_model == "perspective"
    assert_captures_equal(capture, loaded)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert f["calibration"].attrs["camera_model"] == "perspective"
        ds = f["calibration/intrinsics"]
        assert (ds.shape, ds.dtype.str) == ((3, 3), "<f8")
    with psfmt.read(tmp_path / "c.h5") as lazy:
        np.testing.assert_array_equal(lazy.calibration.intrinsics, capture.calibration.intrinsics)


def test_an_orthographic_camera_stores_no_intrinsics(tmp_path: Path) -> None:
    capture = sample_capture("hybrid", seed=9)
    psfmt.write(capture, tmp_path / "c.h5")
    loaded = psfmt.load(tmp_path / "c.h5")
    assert (loaded.calibration.camera_model, loaded.calibration.intrinsics) == ("orthographic", None)
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert "intrinsics" not in f["calibration"] and f["calibration"].attrs["camera_model"] == "orthographic"


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_frame_dtypes_and_sensor_levels_round_trip(tmp_path: Path, dtype: Any) -> None:
    capture = sample_capture("frames", seed=1, dtype=dtype)
    psfmt.write(capture, tmp_path / "c.h5")
    loaded = psfmt.load(tmp_path / "c.h5")
    assert_captures_equal(capture, loaded)
    expected = {np.uint8: (8, 255.0), np.uint16: (16, 65535.0), np.float32: (32, 1.0)}[dtype]
    assert (loaded.frames.bit_depth, loaded.frames.saturation) == expected


def test_sensor_levels_and_grey_frames_round_trip(tmp_path: Path) -> None:
    data = np.arange(2 * 8 * 8, dtype=np.uint16).reshape(2, 8, 8, 1) * 60
    frames = psfmt.Frames(data, t_start_us=[0, 100], t_end_us=[100, 200], color_order="L",
                          bit_depth=12, saturation=4000.0, black_level=64.0)
    capture = psfmt.Capture(frames=frames, created=CREATED, creator_version="2.1")
    psfmt.write(capture, tmp_path / "g.h5")
    loaded = psfmt.load(tmp_path / "g.h5")
    assert_captures_equal(capture, loaded)
    np.testing.assert_allclose(loaded.frames.as_float(1)[0, 1, 0], (data[1, 0, 1, 0] - 64.0) / (4000.0 - 64.0), rtol=1e-6)


def test_sampled_and_near_ring_light_parameters_round_trip(tmp_path: Path) -> None:
    times = np.array([0, 1000, 2500, 4000], dtype=np.int64)
    sampled = psfmt.LightSpec("sampled", {
        "times_us": times,
        "directions": np.array([[0.5, 0.0, 0.866], [0.0, 0.5, 0.866], [-0.5, 0.0, 0.866], [0.0, -0.5, 0.866]]),
        "intensities": np.ones((4, 3)),
        "periodic": True,
        "period_us": 5000,
        "interpolation": "linear-renormalised",
    })
    near = psfmt.LightSpec("near-ring", {
        "radius_mm": 75.0, "height_mm": 70.0, "pixel_pitch_mm": 0.05, "period_us": 33_333,
        "phase_deg": 0.0, "sense": 1, "intensity": np.array([1.0, 1.0, 1.0]), "center_px": np.array([31.5, 31.5]),
    })
    for i, lights in enumerate((sampled, near)):
        capture = sample_capture("events", seed=i)
        capture.lights = lights
        psfmt.write(capture, tmp_path / f"{i}.h5")
        loaded = psfmt.load(tmp_path / f"{i}.h5")
        assert loaded.lights.model == lights.model
        assert_params_equal(lights.params, loaded.lights.params)
        assert psfmt.validate(tmp_path / f"{i}.h5").errors == []


def test_lazy_read_gives_frames_by_index_and_events_by_window(tmp_path: Path) -> None:
    capture = sample_capture("hybrid", seed=2)
    psfmt.write(capture, tmp_path / "c.h5")
    with psfmt.read(tmp_path / "c.h5") as lazy:
        assert isinstance(lazy.frames.data, psfmt.FrameStack)
        assert lazy.frames.data.shape == (3, FRAME_SIZE, FRAME_SIZE, 3)
        np.testing.assert_array_equal(lazy.frames.frame(2), capture.frames.data[2])
        np.testing.assert_array_equal(lazy.frames.data[1, 5:9, :, 0], capture.frames.data[1, 5:9, :, 0])
        assert len(lazy.events) == 5000
        t = capture.events.data.t
        assert (lazy.events.t_first_us, lazy.events.t_last_us) == (int(t[0]), int(t[-1]))
        window = lazy.events.window(10_000, 10_001 + 2_500)
        np.testing.assert_array_equal(window.t, t[(t >= 10_000) & (t < 12_501)])


def test_lazy_capture_copies_to_an_equal_file(tmp_path: Path) -> None:
    capture = sample_capture("hybrid", seed=4)
    psfmt.write(capture, tmp_path / "a.h5")
    with psfmt.read(tmp_path / "a.h5") as lazy:
        psfmt.write(lazy, tmp_path / "b.h5")
    assert_captures_equal(capture, psfmt.load(tmp_path / "b.h5"))


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_same_capture_gives_the_same_bytes(tmp_path: Path) -> None:
    psfmt.write(sample_capture("hybrid", seed=5), tmp_path / "a.h5")
    psfmt.write(sample_capture("hybrid", seed=5), tmp_path / "b.h5")
    psfmt.write(sample_capture("hybrid", seed=6), tmp_path / "c.h5")
    assert _digest(tmp_path / "a.h5") == _digest(tmp_path / "b.h5") != _digest(tmp_path / "c.h5")


def test_layout_on_disk_matches_the_spec(tmp_path: Path) -> None:
    psfmt.write(sample_capture("hybrid", seed=0), tmp_path / "c.h5")
    with h5py.File(tmp_path / "c.h5", "r") as f:
        assert f.attrs["format"] == "hybrid-capture" and f.attrs["format_version"] == "1.3"
        assert set(f) == {"frames", "events", "triggers", "lights", "calibration", "ground_truth", "results"}
        dtypes = {c: f["events"][c].dtype.str for c in "xytp"}
        assert dtypes == {"x": "<u2", "y": "<u2", "t": "<i8", "p": "|i1"}
        for c in "xytp":
            ds = f["events"][c]
            assert ds.compression == "gzip" and ds.shuffle and ds.chunks is not None
        index = f["events/ms_to_idx"]
        assert index.dtype == np.uint64
        t = f["events/t"][()]
        origin = int(f["events"].attrs["ms_origin_us"])
        bounds = origin + 1000 * np.arange(len(index))
        np.testing.assert_array_equal(index[()], np.searchsorted(t, bounds, side="left"))
        assert f["frames/data"].shape == (3, 64, 64, 3) and f["frames/t_start_us"].dtype == np.int64
        assert f["calibration/event_to_frame"].shape == (2, 3)
        assert {k: f["triggers"][k].dtype.str for k in f["triggers"]} == {"t": "<i8", "channel": "|u1", "value": "|i1"}
        assert f["ground_truth/mask"].dtype == np.uint8 and f["ground_truth/normal"].dtype == np.float32
        assert sorted(f["ground_truth/materials"]) == ["f0", "roughness"]


def test_write_result_adds_and_replaces_a_result(tmp_path: Path) -> None:
    capture = sample_capture("events", seed=7)
    psfmt.write(capture, tmp_path / "c.h5")
    normal = np.zeros((FRAME_SIZE, FRAME_SIZE, 3), np.float32)
    normal[..., 2] = 1
    first = psfmt.Result("dualres", {"normal": normal, "mask": np.ones((FRAME_SIZE, FRAME_SIZE), bool)},
                         solver="dualres", options={"epochs": 10}, seconds=2.5, version="0.1.0", created=CREATED)
    psfmt.write_result(tmp_path / "c.h5", first)
    second = psfmt.Result("dualres", {"normal": -normal}, solver="dualres", options={"epochs": 20})
    psfmt.write_result(tmp_path / "c.h5", second)
    loaded = psfmt.load(tmp_path / "c.h5")
    assert sorted(loaded.results) == ["dualres", "eventps"]
    got = loaded.results["dualres"]
    assert got.options == {"epochs": 20} and sorted(got.maps) == ["normal"]
    np.testing.assert_array_equal(got.maps["normal"], -normal)
    capture.results["dualres"] = second
    assert_captures_equal(capture, loaded)
