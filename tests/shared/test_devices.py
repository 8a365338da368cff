"""Where the stages with a torch copy run (``pstoolkit._shared.devices``), and how much of a device's
memory a batch of their work may take."""

from __future__ import annotations

import pytest

from pstoolkit._shared import devices


def test_the_host_is_the_cpu_by_any_name() -> None:
    assert devices.on_host("cpu") and devices.on_host("cpu:0")
    assert not devices.on_host("cuda") and not devices.on_host("cuda:1") and not devices.on_host("meta")


def test_off_a_gpu_the_budget_is_the_cap() -> None:
    assert devices.memory_budget("cpu", 123) == 123


@pytest.mark.cuda
def test_on_a_gpu_the_budget_is_a_share_of_its_free_memory() -> None:
    import torch

    free_bytes, _ = torch.cuda.mem_get_info()
    budget = devices.memory_budget("cuda", 1 << 40)
    assert 64 << 20 <= budget <= max(64 << 20, free_bytes // 4 + 1)
    assert devices.memory_budget("cuda", 1) == 64 << 20
