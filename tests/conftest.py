"""Fixtures shared by the test packages."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

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


@pytest.fixture
def benchmark_script():
    """A loader of the scripts in ``benchmarks/``: ``benchmark_script("sim")`` is ``benchmarks/sim.py`` imported as
    ``bench_sim``, its folder on ``sys.path`` while it is (the scripts import their sibling ``_common``, as
    ``python benchmarks/<name>.py`` lets them)."""
    folder = Path(__file__).resolve().parents[1] / "benchmarks"

    def load(name: str):
        sys.path.insert(0, str(folder))
        try:
            spec = importlib.util.spec_from_file_location(f"bench_{name}", folder / f"{name}.py")
            module = importlib.util.module_from_spec(spec)
            sys.modules[spec.name] = module
            spec.loader.exec_module(module)
        finally:
            sys.path.remove(str(folder))
        return module

    return load
