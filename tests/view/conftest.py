"""Result folders, captures and running servers for the viewer's tests."""

from __future__ import annotations

import http.client
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.captures import sample_capture

import psfmt
from pstoolkit.view.sample import write_sphere_result
from pstoolkit.view.server import ViewServer
from pstoolkit.view.source import load_result_folder
from pstoolkit.view.timeline import Timeline

SIZE = 48


@pytest.fixture(scope="module")
def hybrid_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small hybrid capture (3 exposures, events, ring light, a stored result, ground truth)."""
    path = tmp_path_factory.mktemp("view-capture") / "hybrid.h5"
    psfmt.write(sample_capture("hybrid"), path)
    return path


@pytest.fixture(scope="module")
def ggx_folder(tmp_path_factory: pytest.TempPathFactory, hybrid_capture: Path) -> Path:
    """A GGX sphere result folder (normal, albedo, f0, roughness, error, depth) naming the capture."""
    folder = tmp_path_factory.mktemp("view-ggx") / "sphere-sample"
    write_sphere_result(folder, SIZE, capture=hybrid_capture)
    return folder


@pytest.fixture(scope="module")
def lambertian_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Lambertian sphere result folder without depth and without a capture."""
    folder = tmp_path_factory.mktemp("view-lambertian") / "sphere-matte"
    write_sphere_result(folder, SIZE, material="lambertian", depth=False)
    return folder


def serve(folder: Path, capture: Path | None = None) -> ViewServer:
    """A started server on a free loopback port for ``folder`` (and ``capture``, if given)."""
    data = load_result_folder(folder, capture)
    timeline = Timeline(data.capture, (data.height, data.width)) if data.capture is not None else None
    return ViewServer(data, timeline).start()


@pytest.fixture
def ggx_server(ggx_folder: Path, hybrid_capture: Path) -> Iterator[ViewServer]:
    server = serve(ggx_folder, hybrid_capture)
    yield server
    server.close()


def get(server: ViewServer, path: str, host: str | None = None) -> tuple[int, bytes, str]:
    """(status, body, content type) of GET ``path`` sent as is (no normalisation of ``..``)."""
    connection = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        connection.putrequest("GET", path, skip_host=True)
        connection.putheader("Host", host or f"127.0.0.1:{server.port}")
        connection.endheaders()
        answer = connection.getresponse()
        return answer.status, answer.read(), answer.getheader("Content-Type", "")
    finally:
        connection.close()
