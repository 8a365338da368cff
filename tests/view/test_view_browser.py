"""The page in a real browser (headless Chromium): its relit canvas is the toolkit's BRDF under the
light in the URL, the whole page draws without script errors (maps, relighting, capture, surface),
the surface turns, and strings from files reach the page as text, never as markup.

Tolerance of the relit canvas against ``pstoolkit.view.display.relight`` (torch GGX/Lambertian in
float64, the same display encoding) inside the object: mean absolute difference under 2/255 and 99th
percentile under 8/255 (JavaScript shades in float64 from the float32 maps, so only the rounding of a
value at a display level's edge may differ, by one level); outside it, exactly the background.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SIZE, serve

from pstoolkit.view.display import BACKGROUND, relight
from pstoolkit.view.headless import find_chromium, load_page
from pstoolkit.view.source import load_result_folder

CHROMIUM = find_chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium binary: `apt-get install chromium` (.ci/run installs it)")
MEAN_TOLERANCE = 2 / 255
P99_TOLERANCE = 8 / 255
ORBIT_SIDE = 384


def _screenshot(folder: Path, query: str, shot: Path, window: tuple[int, int]) -> np.ndarray:
    """RGB screenshot of the page for ``folder`` with ``query``, after the page signalled it had drawn."""
    server = serve(folder)
    try:
        load_page(server.url + query, screenshot=shot, window=window, chromium=CHROMIUM)
        assert server.ready, "the page never signalled that it had drawn"
        assert server.page_errors == []
    finally:
        server.close()
    image = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert image is not None
    return image[..., ::-1]


@pytest.mark.parametrize(
    ("material", "light", "exposure"),
    [("ggx", (0.3, 0.2, 0.93), 1.1), ("ggx", (-0.55, 0.45, 0.7), 0.9), ("lambertian", (0.3, 0.2, 0.93), 1.0)],
)
def test_relit_canvas_matches_toolkit_brdf(
    request: pytest.FixtureRequest, tmp_path: Path, material: str, light: tuple[float, float, float], exposure: float
) -> None:
    folder = request.getfixturevalue(f"{material}_folder")
    query = f"?view=relight&light={','.join(map(str, light))}&exposure={exposure}"
    image = _screenshot(folder, query, tmp_path / "relit.png", (320, 320))  # Chromium keeps windows above ~200 px
    data = load_result_folder(folder)
    expected = relight(data.maps, data.mask, light, exposure)
    canvas = image[:SIZE, :SIZE]
    difference = np.abs(canvas.astype(np.float64) - expected)[data.mask] / 255.0
    assert difference.mean() < MEAN_TOLERANCE, difference.mean() * 255
    assert np.percentile(difference, 99) < P99_TOLERANCE, np.percentile(difference, 99) * 255
    assert np.all(canvas[~data.mask] == BACKGROUND)
    assert not image[:, SIZE + 1 :].any() and not image[SIZE + 1 :].any()  # the canvas is 1:1, the page black around it
    assert expected[data.mask].std() > 20  # a picture with shading to compare, not a flat one
    if material == "ggx":  # the highlight is there: brighter than the same surface without it
        matte = relight({k: v for k, v in data.maps.items() if k not in ("f0", "roughness")}, data.mask, light, exposure)
        assert (canvas[data.mask].astype(int) - matte[data.mask]).max() > 40


def test_orbit_turns_the_depth_map(ggx_folder: Path, tmp_path: Path) -> None:
    """Seen head-on the points form the disc of the relit image (its colours, the centre pixel's at
    the centre); turned by 90° the hemisphere's profile covers half of that disc."""
    window = (ORBIT_SIDE + 40, ORBIT_SIDE + 40)
    light = "0.3,0.2,0.93"
    front = _screenshot(ggx_folder, f"?view=orbit&yaw=0&pitch=0&light={light}&exposure=1", tmp_path / "front.png", window)
    side = _screenshot(ggx_folder, f"?view=orbit&yaw=90&pitch=0&light={light}&exposure=1", tmp_path / "side.png", window)
    background = np.array([17, 17, 20])
    covered_front = np.any(front[:ORBIT_SIDE, :ORBIT_SIDE] != background, axis=-1)
    covered_side = np.any(side[:ORBIT_SIDE, :ORBIT_SIDE] != background, axis=-1)
    # the cloud's farthest point (the rim, behind the mean depth) is 0.48 of the side from the centre:
    # the rim's disc has a radius of 0.48 · 21.4 / hypot(21.4, 14.4) ≈ 0.40 of the side, π·0.40² ≈ 0.5
    assert 0.42 < covered_front.mean() < 0.6
    columns = [np.ptp(np.flatnonzero(covered.any(axis=0))) for covered in (covered_front, covered_side)]
    rows = [np.ptp(np.flatnonzero(covered.any(axis=1))) for covered in (covered_front, covered_side)]
    assert 0.4 < columns[1] / columns[0] < 0.6  # from the side: the hemisphere's depth, its radius
    assert abs(rows[1] / rows[0] - 1.0) < 0.1  # turning about the vertical axis keeps the height
    data = load_result_folder(ggx_folder)
    relit = relight(data.maps, data.mask, (0.3, 0.2, 0.93), 1.0)
    centre = front[ORBIT_SIDE // 2 - 2 : ORBIT_SIDE // 2 + 3, ORBIT_SIDE // 2 - 2 : ORBIT_SIDE // 2 + 3].reshape(-1, 3)
    expected = relit[SIZE // 2 - 1 : SIZE // 2 + 1, SIZE // 2 - 1 : SIZE // 2 + 1].reshape(-1, 3)
    assert np.abs(centre.astype(int).mean(axis=0) - expected.mean(axis=0)).max() < 6


def test_whole_page_with_capture(ggx_folder: Path, hybrid_capture: Path) -> None:
    server = serve(ggx_folder, hybrid_capture)
    try:
        dom = load_page(server.url + "?t=12000&light=0.5,0.3,0.8", window=(1200, 1600), chromium=CHROMIUM)
        assert server.ready and server.page_errors == []
    finally:
        server.close()
    assert 'data-ready="1"' in dom
    assert "<title>sphere · sample · pstoolkit view</title>" in dom
    for text in ("frame 2 of 3 · exposure 10.0 ms–20.0 ms", "red positive, blue negative", "result under the capture's light (",
                 "light (0.51, 0.30, 0.81)", "GGX: diffuse albedo", "capture scrubbed"):
        assert text in dom, text
    assert dom.count("<figcaption>") >= 6  # six map panels, then the capture's three


def test_strings_from_files_are_text(tmp_path: Path, lambertian_folder: Path) -> None:
    folder = tmp_path / "hostile"
    shutil.copytree(lambertian_folder, folder)
    evil = "<img src=x onerror=\"fetch('/log?error=injected')\"><b>bold</b>"
    summary = json.loads((folder / "result.json").read_text())
    summary.update(name=evil, object="</title><script>fetch('/log?error=title')</script>", options={evil: evil})
    (folder / "result.json").write_text(json.dumps(summary))
    server = serve(folder)
    try:
        dom = load_page(server.url, window=(900, 900), chromium=CHROMIUM)
        assert server.ready and server.page_errors == []
    finally:
        server.close()
    assert "&lt;img src=x onerror=" in dom and "&lt;b&gt;bold&lt;/b&gt;" in dom
    assert not re.search(r"<img[^>]*src=\"?x", dom) and "<b>bold" not in dom
    assert "<script>fetch" not in dom
