"""The CPU sent down a device's path (``devices.on_host`` false) beside the host's, for the tests that
hold a device's torch copy to the host's code."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from pstoolkit._shared import devices
from pstoolkit.shadows.base import ShadowMask
from pstoolkit_dualres.preprocess import Preprocessed
from pstoolkit_dualres.problem import Problem, build_problem


@contextmanager
def on_the_host(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Within: the host's path on the CPU, whatever ``devices.on_host`` says around it."""
    with monkeypatch.context() as m:
        m.setattr(devices, "on_host", lambda where: True)
        yield


def masked_problems(pre: Preprocessed, view: np.ndarray, shadows: ShadowMask, frame_samples: int, device: str,
                    monkeypatch: pytest.MonkeyPatch) -> tuple[Problem, Problem]:
    """``build_problem`` of ``pre`` with ``shadows`` applied, down the host's path on the CPU and down the
    device's on ``device`` (the CPU sent down it, for the rest of the test, where that is the CPU)."""
    with on_the_host(monkeypatch):
        host = build_problem(pre, view, device="cpu", frame_samples=frame_samples)
        host.apply_mask(shadows)
    monkeypatch.setattr(devices, "on_host", lambda where: False)
    there = build_problem(pre, view, device=device, frame_samples=frame_samples)
    there.apply_mask(shadows)
    return host, there
