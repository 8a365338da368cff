"""``pstoolkit view``'s server: it binds loopback unless told otherwise, serves nothing from outside
the result folder, describes the maps correctly in index.json and sends them as float32, and reads
hostile result folders without trusting them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from conftest import SIZE, get, serve
from helpers.interrupt import interruptible

from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.view.server import ViewServer, is_loopback
from pstoolkit.view.source import DISPLAY_WHITE, MAX_PIXELS, load_result_folder, read_map

TRAVERSALS = [
    "/files/../result.json",
    "/files/../../../../../../etc/passwd",
    "/files/%2e%2e/%2e%2e/%2e%2e/etc/passwd",
    "/files/..%2f..%2f..%2fetc%2fpasswd",
    "/files//etc/passwd",
    "/files/%2fetc%2fpasswd",
    "/files/outside.txt",
    "/files/",
    "/files/.",
    "/files/normal.png%00.json",
    "/static/../server.py",
    "/static/..%2fserver.py",
    "/data/../source.py",
    "/data/..%2fnormal.f32",
    "/data/mask.f32",
    "/capture/../../etc/passwd",
]


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.10", "::", "example.org"])
def test_cli_refuses_non_loopback_host(ggx_folder: Path, host: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["view", str(ggx_folder), "--host", host, "--no-browser", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"pstoolkit: error: --host {host}: not a loopback address")
    assert "--allow-remote" in err


def test_server_refuses_non_loopback_unless_allowed(ggx_folder: Path) -> None:
    data = load_result_folder(ggx_folder)
    with pytest.raises(UserError, match="--allow-remote"):
        ViewServer(data, host="0.0.0.0")
    server = ViewServer(data, host="0.0.0.0", allow_remote=True)
    try:
        assert server.server_address[0] == "0.0.0.0"
        assert server.host_allowed("example.org:80")  # remote clients name the machine as they know it
    finally:
        server.close()
    assert all(is_loopback(h) for h in ("127.0.0.1", "127.3.4.5", "localhost", "::1", "[::1]"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "10.0.0.1", "localhost.example.org", ""))


def test_cli_serves_until_interrupted(ggx_folder: Path) -> None:
    """The real command: prints its address, serves index.json, stops cleanly (exit 0) at Ctrl-C."""
    process = interruptible(
        [sys.executable, "-c", "from pstoolkit.cli import main; main()", "view", str(ggx_folder), "--port", "0", "--no-browser"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        line = process.stdout.readline()
        assert line.startswith("serving sphere · sample at http://127.0.0.1:"), line + process.stderr.read()
        url = line.split(" at ", 1)[1].split(" ", 1)[0]
        with urllib.request.urlopen(url + "data/index.json", timeout=30) as answer:
            assert json.loads(answer.read())["label"] == "sphere · sample"
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=60) == 0
        assert "stopped" in process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()


def test_path_traversal_refused(ggx_server: ViewServer, tmp_path: Path) -> None:
    folder = ggx_server.data.folder
    (folder.parent / "outside.txt").write_text("secret")
    link = folder / "outside.txt"
    if not link.exists():
        os.symlink(folder.parent / "outside.txt", link)  # a link inside the folder that leads out of it
    for path in TRAVERSALS:
        status, body, _ = get(ggx_server, path)
        assert status == 404, path
        assert b"secret" not in body and b"root:" not in body
    status, body, kind = get(ggx_server, "/files/normal.png")
    assert (status, kind) == (200, "image/png")
    assert body == (folder / "normal.png").read_bytes()
    status, body, _ = get(ggx_server, "/files/result.json")
    assert status == 200 and json.loads(body)["object"] == "sphere"


def test_wrong_host_header_refused(ggx_server: ViewServer) -> None:
    """A page elsewhere cannot reach the server through a DNS name pointed at 127.0.0.1."""
    assert get(ggx_server, "/data/index.json", host=f"attacker.example:{ggx_server.port}")[0] == 403
    assert get(ggx_server, "/data/index.json", host=f"localhost:{ggx_server.port}")[0] == 200


def test_page_headers_forbid_foreign_scripts(ggx_server: ViewServer) -> None:
    with urllib.request.urlopen(ggx_server.url, timeout=30) as answer:
        csp = answer.headers["Content-Security-Policy"]
        assert "script-src 'self'" in csp and "default-src 'none'" in csp
        assert answer.headers["X-Content-Type-Options"] == "nosniff"
        page = answer.read().decode()
    assert "http://" not in page and "https://" not in page  # nothing from the network
    for name in ("main.js", "shading.js", "maps.js", "orbit.js", "timeline.js", "viewer.css"):
        status, body, _ = get(ggx_server, f"/static/{name}")
        assert status == 200 and b"innerHTML" not in body and b"https://" not in body, name


def test_index_json(ggx_server: ViewServer, ggx_folder: Path) -> None:
    index = json.loads(get(ggx_server, "/data/index.json")[1])
    assert index["order"] == ["normal", "albedo", "f0", "roughness", "error", "depth"]
    assert (index["width"], index["height"], index["brdf"], index["label"]) == (SIZE, SIZE, "ggx", "sphere · sample")
    channels = {"normal": 3, "albedo": 3, "f0": 3, "roughness": 1, "error": 1, "depth": 1}
    for name, entry in index["maps"].items():
        assert entry["shape"] == [SIZE, SIZE, channels[name]]
        assert entry["url"] == f"/data/{name}.f32" and entry["png"] == f"/files/{name}.png"
        status, body, kind = get(ggx_server, entry["url"])
        assert (status, kind) == (200, "application/octet-stream")
        values = np.frombuffer(body, dtype="<f4").reshape(entry["shape"])
        stored = np.load(ggx_folder / f"{name}.npy").reshape(entry["shape"])
        np.testing.assert_array_equal(values, stored)
    albedo = np.load(ggx_folder / "albedo.npy")
    mask = np.any(np.load(ggx_folder / "normal.npy") != 0, axis=-1)
    assert index["exposure"] == pytest.approx(DISPLAY_WHITE / np.percentile(albedo.max(axis=-1)[mask], 99.0), rel=1e-6)
    assert index["maps"]["normal"]["range"] == [-1.0, 1.0]
    assert index["maps"]["error"]["range"] == [0.0, 30.0]
    assert index["maps"]["roughness"]["range"] == [0.0, 1.0]
    depth = np.load(ggx_folder / "depth.npy")
    assert index["maps"]["depth"]["range"] == pytest.approx([np.nanmin(depth), np.nanmax(depth)])
    assert len(index["colormap"]) == 256
    assert index["info"]["solver"] == "sample" and index["options"] == {"material": "ggx"}
    assert index["capture"]["mode"] == "time" and index["notes"] == []


def test_index_lambertian_without_depth(lambertian_folder: Path) -> None:
    server = serve(lambertian_folder)
    try:
        index = json.loads(get(server, "/data/index.json")[1])
        assert index["order"] == ["normal", "albedo", "error"]
        assert index["brdf"] == "lambertian" and index["capture"] is None
        assert get(server, "/data/depth.f32")[0] == 404
        assert get(server, "/capture/at?t=0")[0] == 404
    finally:
        server.close()


def test_hostile_result_folder(tmp_path: Path, lambertian_folder: Path) -> None:
    """Crafted strings pass through as JSON strings (the page shows them as text); non-finite numbers,
    nested options, oversized and mis-sized maps are left out; a capture path that does not exist is a note."""
    folder = tmp_path / "hostile"
    folder.mkdir()
    for name in ("normal.npy", "albedo.npy"):
        (folder / name).write_bytes((lambertian_folder / name).read_bytes())
    evil = "<img src=x onerror=alert(1)></td><script>alert(2)</script>"
    (folder / "result.json").write_text(json.dumps({
        "name": evil, "object": 7, "solver": ["x"], "mae_deg": float("nan"), "seconds": 1e400,
        "options": {evil: evil, "nested": {"a": 1}, "inf": float("inf"), "ok": 3},
        "capture": str(tmp_path / "missing.h5"), "error_max_deg": "30",
    }))
    np.save(folder / "roughness.npy", np.zeros((SIZE + 1, SIZE), np.float32))  # another size
    header = tmp_path / "huge.npy"  # a header claiming 4 GB in a few bytes
    with open(header, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (32768, 32768)})
    (folder / "f0.npy").write_bytes(header.read_bytes())
    data = load_result_folder(folder)
    assert set(data.maps) == {"normal", "albedo"}
    assert data.info == {"name": evil, "capture": str(tmp_path / "missing.h5")}
    assert data.options == {evil: evil, "ok": 3}
    assert data.capture is None and data.error_max_deg == 30.0
    # the capture result.json names is never opened, only mentioned
    assert any(f"names the capture {tmp_path / 'missing.h5'}: pass --capture FILE" in note for note in data.notes)
    assert any(note.startswith("left out roughness") for note in data.notes)
    assert any(note.startswith("left out f0") for note in data.notes)
    server = ViewServer(data).start()
    try:
        index = json.loads(get(server, "/data/index.json")[1])
        assert index["label"] == evil and index["info"]["name"] == evil
    finally:
        server.close()


def test_read_map_checks_sizes_before_allocating(tmp_path: Path) -> None:
    path = tmp_path / "claims.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (8, 8)})
        fh.write(b"\0" * 16)  # 16 of the 256 bytes the header claims
    with pytest.raises(UserError, match="claims.npy: the .npy header declares 256 bytes of data, the file holds 16"):
        read_map(path, None)
    side = int(np.sqrt(MAX_PIXELS)) + 1
    big = np.lib.format.open_memmap(tmp_path / "big.npy", mode="w+", dtype=np.uint8, shape=(side, side))
    del big  # sparse on disk: the reader must refuse it from the header, not by reading it
    with pytest.raises(UserError, match="over the viewer's"):
        read_map(tmp_path / "big.npy", None)
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(UserError):
        read_map(tmp_path / "objects.npy", None)
    with pytest.raises(UserError, match="no normal.npy"):
        load_result_folder(tmp_path)
