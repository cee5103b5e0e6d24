"""Counter-based RNG: determinism per key, range and moments, independence of streams."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from maipp_bench.envs import rng

N = 100_000


def test_uniform_deterministic_per_key():
    key = rng.seed_key(123)
    a = rng.uniform(key, (N,))
    b = rng.uniform(rng.seed_key(123), (N,))
    assert a.dtype == torch.float64 and a.shape == (N,)
    assert torch.equal(a, b)


def test_uniform_range_and_moments():
    u = rng.uniform(rng.seed_key(7), (N,))
    assert float(u.min()) >= 0.0 and float(u.max()) < 1.0
    assert abs(float(u.mean()) - 0.5) < 0.005  # std of the mean: 0.29 / sqrt(1e5) ~ 1e-3
    assert abs(float(u.var()) - 1.0 / 12.0) < 0.002
    # Every tenth of [0, 1) gets its share.
    counts = torch.bincount((u * 10).long(), minlength=10).double() / N
    assert torch.all((counts - 0.1).abs() < 0.005)


def test_different_keys_give_different_streams():
    a = rng.uniform(rng.seed_key(1), (N,))
    b = rng.uniform(rng.seed_key(2), (N,))
    assert not torch.equal(a, b)
    assert (a == b).double().mean() < 1e-3
    # Uncorrelated.
    assert abs(float(torch.corrcoef(torch.stack([a, b]))[0, 1])) < 0.02
    # Derived keys differ by tag and are themselves deterministic.
    key = rng.seed_key(1)
    c1 = rng.uniform(rng.derive(key, 1), (1000,))
    c2 = rng.uniform(rng.derive(key, 2), (1000,))
    assert not torch.equal(c1, c2)
    assert torch.equal(c1, rng.uniform(rng.derive(rng.seed_key(1), 1), (1000,)))


def test_batched_keys_match_single_keys():
    keys = rng.derive(rng.seed_key(5), torch.arange(4))
    batch = rng.uniform(keys, (3, 50))
    assert batch.shape == (4, 3, 50)
    for i in range(4):
        assert torch.equal(batch[i], rng.uniform(keys[i], (3, 50)))


def test_normal_moments():
    z = rng.normal(rng.seed_key(11), (N,))
    assert z.dtype == torch.float64 and z.shape == (N,)
    assert torch.isfinite(z).all()
    assert abs(float(z.mean())) < 0.015
    assert abs(float(z.std()) - 1.0) < 0.015
    assert abs(float((z.abs() <= 1.0).double().mean()) - 0.6827) < 0.01
    assert torch.equal(z, rng.normal(rng.seed_key(11), (N,)))


def test_randint_inclusive_range():
    r = rng.randint(rng.seed_key(3), 8, 12, (N,))
    assert r.dtype == torch.int64
    assert int(r.min()) == 8 and int(r.max()) == 12
    freq = torch.bincount(r - 8, minlength=5).double() / N
    assert torch.all((freq - 0.2).abs() < 0.01)


def test_integer_tags_mix_to_the_bits_of_tensor_tags():
    """derive() mixes a Python-int tag without tensors: the same bits as a tensor tag."""
    values = [0, 1, -1, 7, 2**62, -(2**63), 2**63 - 1, 123456789012345]
    assert [rng.mix_int(v) for v in values] == rng.mix(torch.tensor(values)).tolist()
    key = rng.seed_key(5)
    keys = rng.derive(key, torch.arange(4))
    for tag in values:
        assert torch.equal(rng.derive(keys, tag), rng.derive(keys, torch.tensor(tag)))
    assert torch.equal(rng.derive(keys, np.int64(7)), rng.derive(keys, 7))
    with pytest.raises(OverflowError, match="int64"):
        rng.derive(keys, 2**63)
