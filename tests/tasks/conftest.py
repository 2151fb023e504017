"""The simulator's tensors are tiny: intra-op threads only add contention (other test processes share the
two CI cores), so the task tests run single-threaded."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _single_thread(single_thread):
    """Every task test on one thread (tests/conftest.py's single_thread)."""
