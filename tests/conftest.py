"""Shared pytest setup for the test suite."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _single_torch_thread():
    """Run torch on one intra-op thread: the tests use small tensors, and on a busy 2-core
    machine two OpenMP threads spin-wait each other (benchmarks/linalg_threads.py measures
    it; docs/performance.md). Results never depend on the thread count here."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
