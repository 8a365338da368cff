"""Loading the viewer's page in headless Chromium: a screenshot or the DOM, without a display.

The tests compare the page's relit canvas with ``display.relight`` through ``load_page``, and
``benchmarks/view.py`` times page loads with ``open_page``. Chromium runs with a fresh profile in a temporary
folder, no sandbox (containers run as root), no GPU, and none of its background network traffic;
in ``load_page`` ``--virtual-time-budget`` lets the page's fetches and drawing finish before the
screenshot or the DOM is taken (the page's clock then runs on virtual time, so time nothing there).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "chrome")
ENV = "PSTOOLKIT_CHROMIUM"
"""Environment variable naming the Chromium binary to use instead of searching ``PATH``."""
FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--hide-scrollbars", "--force-device-scale-factor=1", "--force-color-profile=srgb",
    "--disable-extensions", "--mute-audio",
)


def find_chromium() -> str | None:
    """The Chromium binary: ``$PSTOOLKIT_CHROMIUM``, else the first of ``CANDIDATES`` on PATH, else
    /usr/bin/chromium if it exists; None when there is none."""
    named = os.environ.get(ENV)
    if named:
        return named if Path(named).is_file() else None
    for name in CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    return "/usr/bin/chromium" if Path("/usr/bin/chromium").is_file() else None


@contextmanager
def open_page(url: str, *, window: tuple[int, int] = (800, 600), chromium: str | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """Chromium showing ``url`` in real time (no virtual time: the page's clock is the wall clock)
    for the duration of the block, then ended. For timing; the caller learns that the page is done
    from the page itself (the viewer's ``/ready`` beacon). Raises FileNotFoundError without Chromium."""
    binary = chromium or find_chromium()
    if binary is None:
        raise FileNotFoundError("no Chromium binary (install chromium, or name one in $PSTOOLKIT_CHROMIUM)")
    with tempfile.TemporaryDirectory(prefix="pstoolkit-chromium-") as profile:
        args = [binary, *FLAGS, f"--user-data-dir={profile}", f"--window-size={window[0]},{window[1]}", url]
        process = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            yield process
        finally:
            process.terminate()
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def load_page(
    url: str,
    *,
    screenshot: Path | None = None,
    window: tuple[int, int] = (800, 600),
    budget_ms: int = 10_000,
    timeout_s: float = 120.0,
    chromium: str | None = None,
) -> str:
    """Load ``url`` in headless Chromium and return the DOM it ends with (``--dump-dom``), or write
    a ``window`` (width, height) CSS-pixel screenshot PNG to ``screenshot`` (and return "").

    ``budget_ms`` is the virtual time the page gets to settle. Raises FileNotFoundError without a
    Chromium binary, subprocess.TimeoutExpired after ``timeout_s``, RuntimeError when Chromium fails
    or writes no screenshot."""
    binary = chromium or find_chromium()
    if binary is None:
        raise FileNotFoundError("no Chromium binary (install chromium, or name one in $PSTOOLKIT_CHROMIUM)")
    with tempfile.TemporaryDirectory(prefix="pstoolkit-chromium-") as profile:
        args = [binary, *FLAGS, f"--user-data-dir={profile}", f"--window-size={window[0]},{window[1]}", f"--virtual-time-budget={budget_ms}"]
        args += [f"--screenshot={screenshot}"] if screenshot is not None else ["--dump-dom"]
        done = subprocess.run([*args, url], capture_output=True, text=True, timeout=timeout_s, stdin=subprocess.DEVNULL)
    if done.returncode != 0 or (screenshot is not None and not screenshot.is_file()):
        tail = (done.stderr or "").strip().splitlines()[-3:]
        raise RuntimeError(f"chromium exited with {done.returncode}: {' / '.join(tail)}")
    return "" if screenshot is not None else done.stdout
