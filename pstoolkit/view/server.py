"""The viewer's local HTTP server: the page, the maps as float32, a result folder's files and the
capture's frames, events and lights.

Routes (GET only):

- ``/`` the page; ``/static/<file>`` its scripts and style (the package's ``static/`` folder);
- ``/data/index.json`` what there is (``page_index``); ``/data/<map>.f32`` a map's values as
  little-endian float32, row-major, in the shape the index gives;
- ``/files/<path>`` a file of the result folder — only a regular file inside it once every link is
  resolved; anything else, ``..`` included, is 404. Served inert (``FILE_TYPES``: PNG as an image,
  text, HTML and scripts as ``text/plain``, anything else as an ``application/octet-stream`` attachment)
  with ``nosniff`` and a sandboxing CSP, so a crafted file cannot run in the viewer's origin;
- ``/capture/at?t=US`` (or ``?frame=K``) the frame covering t and the light there (JSON);
  ``/capture/frame/<k>.rgb`` a frame and ``/capture/events.rgb?t0=US&t1=US`` an event image as RGB
  bytes (``Timeline``);
- ``/ready?ms=…&render_ms=…`` the page's beacon that it has drawn (``ViewServer.ready`` records it; the tests and
  the benchmark wait on it) and ``/log?error=…`` a script error it caught (``page_errors``).

The server binds 127.0.0.1 by default and refuses any address that is not a loopback one unless
``allow_remote`` is given (``check_bind``). While bound to loopback it also refuses requests whose
Host header names another host than ``localhost`` or a loopback address at its port, so a web page
elsewhere cannot reach it by pointing a DNS name at 127.0.0.1. Every page response forbids scripts
and styles from anywhere but the server. At most ``MAX_CONNECTIONS`` connections are served at once,
each closed after ``IDLE_TIMEOUT_S`` of silence; the beacons kept are bounded.
"""

from __future__ import annotations

import ipaddress
import json
import math
import os
import re
import shutil
import socket
import threading
import time
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

import numpy as np

from pstoolkit.errors import UserError
from pstoolkit.view.source import MAP_NAMES, ViewData
from pstoolkit.view.timeline import Timeline

CONTENT_TYPES = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".png": "image/png",
    ".json": "application/json",
}
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
       "base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
_TEXT_SUFFIXES = (".json", ".md", ".txt", ".csv", ".html", ".htm", ".js", ".css", ".svg", ".xml")
FILE_TYPES = {".png": "image/png", **dict.fromkeys(_TEXT_SUFFIXES, "text/plain; charset=utf-8")}
"""The types ``/files/`` serves a result folder's files as: PNG as an image, text (HTML, SVG and
scripts included) as plain text a browser shows as its source, anything else as an
``application/octet-stream`` attachment; never a type a browser runs."""
FILE_CSP = "default-src 'none'; sandbox; frame-ancestors 'none'"
"""``/files/``'s policy: even a browser that rendered a file would give it no script, no origin."""
MAX_PAGE_ERRORS = 50
MAX_BEACONS = 1000
"""``/ready`` beacons and page requests kept (the latest): a page left open must not grow the server."""
MAX_CONNECTIONS = 64
"""Connections served at once; one more is closed unanswered until one ends."""
IDLE_TIMEOUT_S = 30.0
"""A connection that sends nothing for this long is closed (its thread ends)."""
_INT = re.compile(r"-?\d{1,17}")
_FRAME = re.compile(r"/capture/frame/(\d{1,9})\.rgb")


def is_loopback(host: str) -> bool:
    """Whether ``host`` (``localhost`` or an IPv4/IPv6 address, brackets allowed) is a loopback address."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_bind(host: str, allow_remote: bool) -> None:
    """Raise UserError when ``host`` is not a loopback address and ``allow_remote`` is False."""
    if not allow_remote and not is_loopback(host):
        raise UserError(
            f"--host {host}: not a loopback address, so anyone who can reach this machine could read the result; "
            "pass --allow-remote to serve it there anyway"
        )


def static_files() -> dict[str, bytes]:
    """The page's files (``static/``), by name."""
    folder = resources.files("pstoolkit.view").joinpath("static")
    return {entry.name: entry.read_bytes() for entry in folder.iterdir() if entry.is_file() and Path(entry.name).suffix in CONTENT_TYPES}


def _clean(value: Any) -> Any:
    """``value`` with every non-finite float as None and numpy scalars as Python ones (JSON carries
    no NaN, and a crafted result.json may hold one)."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def turbo_lut() -> list[list[int]]:
    """OpenCV's Turbo colour map as 256 RGB triples: the page draws error maps as ``error.png`` is."""
    import cv2

    bgr = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(1, 256), cv2.COLORMAP_TURBO)[0]
    return bgr[:, ::-1].astype(int).tolist()


def page_index(data: ViewData, timeline: Timeline | None) -> dict[str, Any]:
    """``/data/index.json``: ``label``, ``width``, ``height``, ``brdf`` (``ggx`` or ``lambertian``),
    ``exposure`` (the default display gain), ``maps`` (name → ``url``, ``shape`` [H, W, C], the
    display ``range`` [lo, hi], ``png`` URL or None) in ``order``, ``info``, ``options``, ``notes``,
    ``colormap`` (256 RGB triples), ``capture`` (``Timeline.info`` or None)."""
    maps = {}
    for name, array in data.maps.items():
        png = data.folder is not None and (data.folder / f"{name}.png").is_file()
        maps[name] = {
            "url": f"/data/{name}.f32",
            "shape": [data.height, data.width, array.shape[2] if array.ndim == 3 else 1],
            "range": list(data.value_range(name)),
            "png": f"/files/{name}.png" if png else None,
        }
    notes = list(data.notes) + (timeline.notes if timeline is not None else [])
    return _clean({
        "label": data.label,
        "width": data.width,
        "height": data.height,
        "brdf": data.brdf,
        "exposure": data.exposure(),
        "maps": maps,
        "order": [name for name in MAP_NAMES if name in maps],
        "info": data.info,
        "options": data.options,
        "notes": notes,
        "colormap": turbo_lut(),
        "capture": timeline.info() if timeline is not None else None,
    })


class ViewServer(ThreadingHTTPServer):
    """Serves ``data`` (and ``timeline``, when given) on ``host``:``port`` (0: a free port).

    Raises UserError for a non-loopback ``host`` without ``allow_remote``, OSError when the address
    cannot be bound. ``ready`` lists each ``/ready`` beacon as (server seconds, page milliseconds
    since navigation began, milliseconds of one relighting), ``requested`` the server seconds of each
    request for the page (server seconds: ``time.perf_counter``)."""

    daemon_threads = True

    def __init__(self, data: ViewData, timeline: Timeline | None = None, *, host: str = "127.0.0.1", port: int = 0,
                 allow_remote: bool = False) -> None:
        check_bind(host, allow_remote)
        self.address_family = socket.AF_INET6 if ":" in host else socket.AF_INET
        super().__init__((host.strip("[]"), port), _Handler)
        self.data, self.timeline = data, timeline
        self.loopback = is_loopback(host)
        try:
            self.static = static_files()
            self.index = json.dumps(page_index(data, timeline), allow_nan=False).encode()
            self.blobs = {name: np.ascontiguousarray(array, dtype="<f4").tobytes() for name, array in data.maps.items()}
        except BaseException:
            self.server_close()
            raise
        self.requested: deque[float] = deque(maxlen=MAX_BEACONS)
        self.ready: deque[tuple[float, float, float]] = deque(maxlen=MAX_BEACONS)
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.ready_event = threading.Event()
        self.page_errors: list[str] = []
        self._thread: threading.Thread | None = None

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    @property
    def url(self) -> str:
        host = str(self.server_address[0])
        return f"http://{'[' + host + ']' if ':' in host else host}:{self.port}/"

    def host_allowed(self, header: str) -> bool:
        """Whether a request's Host header may reach this server: any, unless bound to loopback; then
        ``localhost`` or a loopback address (the one bound among them) at the bound port, which a
        browser leaves out for port 80. A DNS name other than localhost is refused (DNS rebinding)."""
        if not self.loopback:
            return True
        match = re.fullmatch(r"(\[[0-9a-fA-F:.]+\]|[^:\[\]]+)(?::(\d{1,5}))?", header)
        if match is None:
            return False
        return is_loopback(match[1]) and int(match[2] or 80) == self.port

    def process_request(self, request: Any, client_address: Any) -> None:
        """Serve the connection on a thread of its own while fewer than ``MAX_CONNECTIONS`` are;
        else close it unanswered (the browser retries), so idle or hostile connections cannot grow
        the threads without bound."""
        if not self.slots.acquire(blocking=False):
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def start(self) -> ViewServer:
        """Serve on a background thread (for tests and benchmarks); ``close`` stops it."""
        self._thread = threading.Thread(target=self.serve_forever, name="pstoolkit-view", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop serving (if started with ``start``), release the socket and close the capture."""
        if self._thread is not None:
            self.shutdown()
            self._thread.join()
        self.server_close()
        if self.timeline is not None:
            self.timeline.close()


class _Handler(BaseHTTPRequestHandler):
    server: ViewServer
    protocol_version = "HTTP/1.1"  # keep-alive: the page fetches a dozen files at once
    server_version = "pstoolkit-view"
    timeout = IDLE_TIMEOUT_S  # the socket's: an idle keep-alive connection ends, and its thread

    def log_message(self, format: str, *args: Any) -> None:
        """Quiet: a request log would bury the one line the command prints."""

    def do_GET(self) -> None:
        try:
            self._route()
        except (BrokenPipeError, ConnectionResetError):
            pass  # the page went away mid-answer (a slider moved on): nothing to answer
        except Exception as exc:  # a damaged capture read mid-way: answer this request, keep serving
            try:
                self._send(500, f"{type(exc).__name__}: {exc}".encode(), "text/plain; charset=utf-8")
            except OSError:
                pass
            self.close_connection = True  # a file may have failed mid-answer: the stream is unusable

    def _send(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self._common_headers()
        self.end_headers()
        self.wfile.write(body)

    def _common_headers(self, csp: str = CSP) -> None:
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("Content-Security-Policy", csp)

    def _not_found(self) -> None:
        self._send(404, b"not found\n", "text/plain; charset=utf-8")

    def _json(self, value: Any) -> None:
        self._send(200, json.dumps(_clean(value), allow_nan=False).encode(), CONTENT_TYPES[".json"])

    def _route(self) -> None:
        server = self.server
        if not server.host_allowed(self.headers.get("Host", "")):
            self._send(403, b"wrong host\n", "text/plain; charset=utf-8")
            return
        url = urlsplit(self.path)
        path, query = url.path, parse_qs(url.query)
        if path in ("/", "/index.html"):
            server.requested.append(time.perf_counter())
            self._send(200, server.static["index.html"], CONTENT_TYPES[".html"])
        elif path.startswith("/static/") and path[8:] in server.static:
            self._send(200, server.static[path[8:]], CONTENT_TYPES[Path(path).suffix])
        elif path == "/data/index.json":
            self._send(200, server.index, CONTENT_TYPES[".json"])
        elif path.startswith("/data/") and path.endswith(".f32") and path[6:-4] in server.blobs:
            self._send(200, server.blobs[path[6:-4]], "application/octet-stream")
        elif path.startswith("/files/"):
            self._file(unquote(path[7:]))
        elif path.startswith("/capture/") and server.timeline is not None:
            self._capture(path, query, server.timeline)
        elif path == "/ready":
            page_ms, render_ms = (_number(query.get(key, ["nan"])[0]) for key in ("ms", "render_ms"))
            server.ready.append((time.perf_counter(), page_ms, render_ms))
            server.ready_event.set()
            self._send(204, b"", "text/plain")
        elif path == "/log":
            if len(server.page_errors) < MAX_PAGE_ERRORS:
                server.page_errors.append(query.get("error", [""])[0][:500])
            self._send(204, b"", "text/plain")
        else:
            self._not_found()

    def _file(self, relative: str) -> None:
        """A regular file inside the result folder, streamed; 404 for anything outside it (``..``,
        an absolute path, a link leading out), a folder or a missing file."""
        folder = self.server.data.folder
        if folder is None or not relative or "\x00" in relative or "\\" in relative:
            self._not_found()
            return
        root = folder.resolve()
        try:
            target = (root / relative).resolve()
        except (OSError, RuntimeError):  # a link loop
            self._not_found()
            return
        if target == root or not target.is_relative_to(root) or not target.is_file():
            self._not_found()
            return
        with open(target, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            kind = FILE_TYPES.get(target.suffix.lower(), "application/octet-stream")
            self.send_response(200)
            # never a type a browser runs: a crafted file in the folder must not act in the page's origin
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(size))
            if kind == "application/octet-stream":
                self.send_header("Content-Disposition", "attachment")
            self._common_headers(FILE_CSP)
            self.end_headers()
            shutil.copyfileobj(fh, self.wfile)

    def _capture(self, path: str, query: dict[str, list[str]], timeline: Timeline) -> None:
        try:
            if path == "/capture/at":
                frame = _int(query, "frame") if "frame" in query else None
                self._json(timeline.at(t_us=_int(query, "t") if "t" in query else None, frame=frame))
            elif match := _FRAME.fullmatch(path):
                self._send(200, timeline.frame_rgb(int(match[1])), "application/octet-stream")
            elif path == "/capture/events.rgb":
                self._send(200, timeline.events_rgb(_int(query, "t0"), _int(query, "t1")), "application/octet-stream")
            else:
                self._not_found()
        except ValueError as exc:
            self._send(400, f"{exc}\n".encode(), "text/plain; charset=utf-8")


def _int(query: dict[str, list[str]], key: str) -> int:
    text = query.get(key, [""])[0]
    if not _INT.fullmatch(text):
        raise ValueError(f"{key}: expected an integer")
    return int(text)


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        return math.nan
