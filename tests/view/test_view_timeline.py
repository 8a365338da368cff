"""Scrubbing a capture: the light at t is the capture's light model's, the frame is the one whose
exposure covers t, the event image counts the window's events by polarity, and captures whose frames
carry their own lights are scrubbed by frame. A capture given as PATH shows its stored result or,
without one, its ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import get, serve
from helpers.captures import sample_capture

import psfmt
from pstoolkit.errors import UserError
from pstoolkit.optics.lights import build_light_model
from pstoolkit.view.display import to_display
from pstoolkit.view.server import ViewServer
from pstoolkit.view.source import load_capture_maps
from pstoolkit.view.timeline import MAX_WINDOW_US, Timeline


def test_light_frame_and_events_at_t(ggx_folder: Path, hybrid_capture: Path) -> None:
    server = serve(ggx_folder, hybrid_capture)
    try:
        capture = psfmt.load(hybrid_capture)
        info = json.loads(get(server, "/data/index.json")[1])["capture"]
        frames, events = capture.frames, capture.events
        assert info["span_us"] == [0, max(int(frames.t_end_us.max()), int(events.t_last_us) + 1)]
        assert info["frames"]["windows"] == np.stack([frames.t_start_us, frames.t_end_us], 1).tolist()
        assert info["events"] == {"width": events.width, "height": events.height, "count": len(events)}
        model = build_light_model(capture.lights)
        for t in (0, 7_777, 10_000, 29_999):
            at = json.loads(get(server, f"/capture/at?t={t}")[1])
            direction, intensity = model.evaluate(np.array([float(t)]))
            np.testing.assert_allclose(at["light"], direction[0], atol=1e-12)
            np.testing.assert_allclose(at["intensity"], intensity[0], atol=1e-12)
            expected = int(np.flatnonzero((frames.t_start_us <= t) & (t < frames.t_end_us))[0])
            assert at["frame"] == expected and at["t_us"] == t
        assert json.loads(get(server, "/capture/at?t=40000")[1])["frame"] is None  # after the last exposure
        status, body, _ = get(server, "/capture/frame/1.rgb")
        assert status == 200
        np.testing.assert_array_equal(np.frombuffer(body, np.uint8).reshape(frames.height, frames.width, 3), to_display(frames.as_float(1)))
        t0, t1 = 5_000, 9_000
        status, body, _ = get(server, f"/capture/events.rgb?t0={t0}&t1={t1}")
        image = np.frombuffer(body, np.uint8).reshape(events.height, events.width, 3)
        window = events.data.window(t0, t1)
        positive = np.zeros((events.height, events.width), bool)
        negative = np.zeros_like(positive)
        positive[window.y[window.p > 0], window.x[window.p > 0]] = True
        negative[window.y[window.p < 0], window.x[window.p < 0]] = True
        np.testing.assert_array_equal(image[..., 0] > 0, positive)
        np.testing.assert_array_equal(image[..., 2] > 0, negative)
        assert not image[~(positive | negative)].any()
        for bad in ("/capture/at?t=abc", "/capture/at?t=1e3", "/capture/at", "/capture/frame/3.rgb", "/capture/events.rgb?t0=1"):
            assert get(server, bad)[0] == 400, bad
        assert get(server, "/capture/frame/-1.rgb")[0] == 404
    finally:
        server.close()


def test_events_window_is_bounded(hybrid_capture: Path) -> None:
    timeline = Timeline(hybrid_capture)
    try:
        everything = timeline.events_rgb(-(10**15), 10**15)  # cut to MAX_WINDOW_US from its start
        assert not np.frombuffer(everything, np.uint8).any()
        assert MAX_WINDOW_US > 30_000
        assert np.frombuffer(timeline.events_rgb(0, 30_000), np.uint8).any()
    finally:
        timeline.close()


def test_frames_with_their_own_lights_scrub_by_frame(tmp_path: Path) -> None:
    path = tmp_path / "classic.h5"
    capture = sample_capture("frames")
    psfmt.write(capture, path)
    timeline = Timeline(path)
    try:
        info = timeline.info()
        assert info["mode"] == "frames" and info["events"] is None and info["frames"]["count"] == 6
        for k in range(6):
            at = timeline.at(frame=k)
            direction = capture.frames.light_direction[k]
            np.testing.assert_allclose(at["light"], direction / np.linalg.norm(direction), atol=1e-12)
            np.testing.assert_allclose(at["intensity"], capture.frames.light_intensity[k])
        with pytest.raises(ValueError):
            timeline.at(frame=6)
    finally:
        timeline.close()


def test_capture_as_path_shows_stored_result_or_ground_truth(tmp_path: Path, hybrid_capture: Path) -> None:
    capture = psfmt.load(hybrid_capture)
    with psfmt.read(hybrid_capture) as opened:
        data = load_capture_maps(opened, hybrid_capture)
        assert data.label == "hybrid · eventps" and set(data.maps) == {"normal", "albedo"}
        np.testing.assert_array_equal(data.maps["albedo"], capture.results["eventps"].maps["albedo"])
        with pytest.raises(UserError, match="no stored result 'nope'"):
            load_capture_maps(opened, hybrid_capture, "nope")
    bare = tmp_path / "truth.h5"
    capture.results = {}
    psfmt.write(capture, bare)
    timeline = Timeline(bare)
    try:
        data = load_capture_maps(timeline.capture, bare)
        gt = capture.ground_truth
        assert data.label == "truth · ground truth"
        assert set(data.maps) == {"normal", "albedo", "depth", "f0", "roughness"} and data.brdf == "ggx"
        np.testing.assert_array_equal(data.mask, gt.mask & np.any(gt.normal != 0, axis=-1))
        assert np.isnan(data.maps["depth"][~data.mask]).all()
        server = ViewServer(data, timeline).start()
        try:
            index = json.loads(get(server, "/data/index.json")[1])
            assert index["capture"]["path"] == str(bare) and get(server, "/files/normal.png")[0] == 404
        finally:
            server.close()  # closes the timeline too
    finally:
        timeline.close()
