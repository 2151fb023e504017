"""Fixtures shared by the test packages."""

from __future__ import annotations

import os

# MKL picks its code path per call from the processor and the operands' sizes and alignment; on some processors
# (AMD EPYC with AVX-512) a member's matmuls inside a population's batch then round differently from its run alone.
# The bit-for-bit tests check that members never mix, which needs one code path: MKL's conditional numerical
# reproducibility mode. Set before torch (and MKL) load; subprocesses of the tests inherit it.
os.environ.setdefault("MKL_CBWR", "COMPATIBLE")

import pytest
import torch


@pytest.fixture
def single_thread():
    """torch on one intra-op thread for the test, then as before."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
