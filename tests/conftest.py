"""Shared pytest setup for the test suite."""

from __future__ import annotations

from maipp_bench.kernels import pin_cpu_kernels

# The kernels of protocol runs (python -m maipp_bench.eval pins them the same way), asked
# for before any import makes MKL's first call: the committed boards' spot checks and the
# in-process evaluations compute rows as a protocol run does.
pin_cpu_kernels()

import pytest  # noqa: E402
import torch  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def _single_torch_thread():
    """Run torch on one intra-op thread: the tests use small tensors, and on a busy 2-core
    machine two OpenMP threads spin-wait each other (benchmarks/linalg_threads.py measures
    it; docs/performance.md). Results never depend on the thread count here."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


TINY_TRAIN = ["env=tiny", "n_envs=3", "steps_per_batch=24", "eval_every=0", "progress=false",
              "algo.epochs=2", "algo.minibatch=32", "algo.net.embed_dim=32",
              "algo.net.ff_dim=64", "algo.net.heads=2"]


def compose_train(*overrides: str):
    """The training config as ``python -m maipp_bench.train <overrides>`` composes it."""
    from hydra import compose, initialize_config_module

    import maipp_bench.train  # noqa: F401  (registers the schema)

    with initialize_config_module("maipp_bench.conf", version_base=None):
        return compose("train", overrides=list(overrides))


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    """A checkpoint of two PPO updates of a small network on the tiny task."""
    from maipp_bench.train import train

    run = tmp_path_factory.mktemp("tiny_run")
    previous = torch.get_num_threads()
    path = train(compose_train(*TINY_TRAIN, "total_updates=2", "checkpoint_every=2"), run)
    torch.set_num_threads(previous)
    return path
