"""The simulator's tensors are tiny: intra-op threads only add contention (other test processes share the
two CI cores), so the task tests run single-threaded."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
