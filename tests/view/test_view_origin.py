"""Issue 33, items 4–8: the viewer serves a result folder's files inert, accepts the address it binds,
reads no map from outside the folder, bounds its connections, threads and beacons, and answers a
crafted record or .npy header with one line.

Item 4 is checked on the HTTP answers (type, disposition, nosniff, sandbox) and, where Chromium is
installed, in the browser: a script the folder holds never runs in the viewer's origin."""

from __future__ import annotations

import shutil
import socket
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import get, serve

from pstoolkit.cli import main
from pstoolkit.errors import UserError
from pstoolkit.view import server as server_module
from pstoolkit.view.headless import find_chromium, load_page
from pstoolkit.view.server import ViewServer
from pstoolkit.view.source import load_result_folder, read_map


def headers(server: ViewServer, path: str) -> tuple[int, dict[str, str]]:
    connection = socket.create_connection(("127.0.0.1", server.port), timeout=30)
    try:
        connection.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\nConnection: close\r\n\r\n".encode())
        data = b""
        while chunk := connection.recv(65536):
            data += chunk
    finally:
        connection.close()
    head = data.split(b"\r\n\r\n", 1)[0].decode().split("\r\n")
    return int(head[0].split()[1]), {k.lower(): v for k, v in (line.split(": ", 1) for line in head[1:])}


@pytest.fixture
def evil_folder(tmp_path: Path, lambertian_folder: Path) -> Path:
    folder = tmp_path / "evil"
    shutil.copytree(lambertian_folder, folder)
    (folder / "evil.html").write_text('<html><head><script src="/files/evil.js"></script></head><body>x</body></html>')
    (folder / "evil.js").write_text("fetch('/log?error=ran-in-the-viewer-origin'); document.title = 'owned';")
    (folder / "evil.svg").write_text('<svg xmlns="http://www.w3.org/2000/svg"><script>alert(1)</script></svg>')
    return folder


# --- 4. /files/ is inert ------------------------------------------------------------------------------

def test_files_are_served_inert(evil_folder: Path) -> None:
    server = serve(evil_folder)
    try:
        (evil_folder / "evil.bin").write_bytes(b"\x00<script>")
        for name, kind in (("evil.html", "text/plain; charset=utf-8"), ("evil.js", "text/plain; charset=utf-8"),
                           ("evil.svg", "text/plain; charset=utf-8"), ("evil.bin", "application/octet-stream"),
                           ("normal.npy", "application/octet-stream")):
            status, head = headers(server, f"/files/{name}")
            assert (status, head["content-type"]) == (200, kind), name
            assert head.get("content-disposition") == ("attachment" if kind == "application/octet-stream" else None)
            assert head["x-content-type-options"] == "nosniff"
            assert "sandbox" in head["content-security-policy"] and "script-src" not in head["content-security-policy"]
        status, head = headers(server, "/files/normal.png")
        assert (status, head["content-type"]) == (200, "image/png") and "content-disposition" not in head
        status, head = headers(server, "/files/result.json")
        assert head["content-type"] == "text/plain; charset=utf-8"
        status, body, kind = get(server, "/")  # the page itself keeps its own policy
        assert status == 200 and kind.startswith("text/html")
    finally:
        server.close()


@pytest.mark.skipif(find_chromium() is None, reason="no Chromium binary: `apt-get install chromium`")
def test_a_script_in_the_folder_never_runs_in_the_browser(evil_folder: Path) -> None:
    server = serve(evil_folder)
    try:
        dom = load_page(server.url + "files/evil.html", window=(400, 300), chromium=find_chromium())
        load_page(server.url, window=(400, 300), chromium=find_chromium())  # the page itself still runs
        assert server.ready
    finally:
        server.close()
    assert "&lt;script src=\"/files/evil.js\"&gt;" in dom  # shown as its source text
    assert "<title>owned</title>" not in dom
    assert server.page_errors == []


# --- 5. the address bound is the address accepted --------------------------------------------------

def test_a_loopback_address_other_than_127_0_0_1_is_served(lambertian_folder: Path) -> None:
    server = ViewServer(load_result_folder(lambertian_folder), host="127.0.0.2").start()
    try:
        port = server.port
        connection = socket.create_connection(("127.0.0.2", port), timeout=30)
        connection.sendall(f"GET /data/index.json HTTP/1.1\r\nHost: 127.0.0.2:{port}\r\nConnection: close\r\n\r\n".encode())
        answer = b""
        while chunk := connection.recv(65536):
            answer += chunk
        connection.close()
        assert answer.startswith(b"HTTP/1.1 200 OK") and b'"width"' in answer
        for host, allowed in ((f"127.0.0.2:{port}", True), (f"localhost:{port}", True), (f"[::1]:{port}", True),
                              (f"evil.example:{port}", False), (f"127.0.0.2:{port + 1}", False), ("127.0.0.2", port == 80)):
            assert server.host_allowed(host) is allowed, host
    finally:
        server.close()


def test_port_80_is_reached_without_a_port_in_the_host(lambertian_folder: Path) -> None:
    try:
        server = ViewServer(load_result_folder(lambertian_folder), port=80).start()
    except OSError:
        pytest.skip("port 80 cannot be bound here (not root, or in use)")
    try:
        assert get(server, "/data/index.json", host="127.0.0.1")[0] == 200
        assert get(server, "/data/index.json", host="localhost")[0] == 200
        assert get(server, "/data/index.json", host="evil.example")[0] == 403
    finally:
        server.close()


# --- 6. the folder rule for the maps --------------------------------------------------------------------

def test_maps_linked_from_outside_the_folder_are_not_read(tmp_path: Path, lambertian_folder: Path, ggx_folder: Path) -> None:
    folder = tmp_path / "linked"
    shutil.copytree(lambertian_folder, folder)
    outside = tmp_path / "secret.npy"
    shutil.copy(ggx_folder / "albedo.npy", outside)
    (folder / "albedo.npy").unlink()
    (folder / "albedo.npy").symlink_to(outside)
    data = load_result_folder(folder)
    assert "albedo" not in data.maps
    assert any("albedo" in note and "leads out of the result folder" in note for note in data.notes)
    server = ViewServer(data).start()
    try:
        assert get(server, "/data/albedo.f32")[0] == 404
    finally:
        server.close()
    (folder / "normal.npy").unlink()
    (folder / "normal.npy").symlink_to(ggx_folder / "normal.npy")
    with pytest.raises(UserError, match="normal.npy: leads out of the result folder"):
        load_result_folder(folder)
    inside = tmp_path / "inside"
    shutil.copytree(lambertian_folder, inside)
    (inside / "normal-copy.npy").write_bytes((inside / "normal.npy").read_bytes())
    (inside / "normal.npy").unlink()
    (inside / "normal.npy").symlink_to("normal-copy.npy")  # a link that stays inside is fine
    assert load_result_folder(inside).maps["normal"].shape[2] == 3


# --- 7. idle connections, threads, beacons ------------------------------------------------------------

def test_idle_connections_time_out_and_threads_are_bounded(lambertian_folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server_module, "MAX_CONNECTIONS", 4)
    monkeypatch.setattr(server_module._Handler, "timeout", 1.0)
    before = threading.active_count()
    server = serve(lambertian_folder)
    idle = [socket.create_connection(("127.0.0.1", server.port), timeout=60) for _ in range(12)]
    try:
        # every connection ends: the four served time out, the others are closed at once
        assert all(connection.recv(1) == b"" for connection in idle)
        assert threading.active_count() <= before + 1 + 4
        assert get(server, "/data/index.json")[0] == 200  # and the server goes on serving
    finally:
        for connection in idle:
            connection.close()
        server.close()


def test_beacons_are_bounded(lambertian_folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(server_module, "MAX_BEACONS", 10)
    server = serve(lambertian_folder)
    try:
        for k in range(30):
            assert get(server, f"/ready?ms={k}&render_ms=1")[0] == 204
        assert len(server.ready) == 10 and server.ready[-1][1] == 29.0
    finally:
        server.close()


# --- 8. crafted records and .npy headers: one line ----------------------------------------------------

@pytest.mark.parametrize("shape", [(-32, 32, 3), (2**62, 2**62, 3)])
def test_crafted_npy_headers_are_one_line(tmp_path: Path, lambertian_folder: Path, shape: tuple[int, ...],
                                         capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "crafted"
    shutil.copytree(lambertian_folder, folder)
    path = folder / "normal.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": shape})
        fh.write(b"\0" * 64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's overflow warnings would be printed before the line
        with pytest.raises(UserError, match="normal.npy: the .npy header declares"):
            read_map(path, None)
    capsys.readouterr()
    assert main(["view", str(folder), "--no-browser", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "normal.npy: the .npy header declares" in err


def test_overflowing_number_in_result_json_is_one_line(tmp_path: Path, lambertian_folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = tmp_path / "overflow"
    shutil.copytree(lambertian_folder, folder)
    (folder / "result.json").write_text('{"mae_deg": 1' + "0" * 400 + "}")
    capsys.readouterr()
    assert main(["view", str(folder), "--no-browser", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == f"pstoolkit: error: {folder / 'result.json'}: not valid JSON (an integer of 401 digits)"
