"""``pstoolkit._shared.allocator``: after ``keep_freed_memory`` a large array comes from the heap, not from
fresh mmap pages, and the CLI sets it at start."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

from pstoolkit.cli import main

# the module, not the package's ``app`` object of the same name
cli_app = importlib.import_module("pstoolkit.cli.app")

PROBE = """
import ctypes, sys
import numpy as np
class Info(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                                                     "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = Info
if sys.argv[1] == "keep":
    from pstoolkit._shared.allocator import keep_freed_memory
    assert keep_freed_memory()
before = libc.mallinfo2().hblkhd
block = np.ones(8 << 20, dtype=np.uint8)
mapped = libc.mallinfo2().hblkhd - before
del block
kept = libc.mallinfo2().fordblks
print(mapped, kept)
"""


def probe(mode: str) -> tuple[int, int]:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True).stdout
    mapped, kept = (int(v) for v in out.split())
    return mapped, kept


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_large_block_stays_in_the_heap_for_reuse() -> None:
    mapped, _ = probe("default")
    assert mapped >= 8 << 20  # glibc's default: a fresh mapping, handed back when freed
    mapped, kept = probe("keep")
    assert mapped == 0
    assert kept >= 8 << 20  # freed into the heap, where the next array of that size finds it


def test_the_cli_keeps_freed_memory(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    monkeypatch.setattr(cli_app, "keep_freed_memory", lambda: calls.append(True) or True)
    # through the console entry point, which imports the commands before the app runs
    assert main(["plugins", "--json"]) == 0
    assert calls == [True]
