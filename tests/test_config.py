"""MAIPPConfig: PROTOCOL v1 defaults and validation of bad values."""

from __future__ import annotations

import math

import pytest
import torch

from maipp_bench.envs import MAIPPConfig, MAIPPEnv

# PROTOCOL v1 values, written out here independently of the dataclass.
PROTOCOL_DEFAULTS = {
    "n_agents": 3,
    "grid_size": 30,
    "k_neighbors": 20,
    "n_nodes": 200,
    "sample_spacing": 0.2,
    "length_scale": 0.25,
    "kernel": "matern32",
    "prior_variance": 1.0,
    "measurement_noise_std": 0.01,
    "gp_noise_variance": 1e-4,
    "interest_beta": 1.0,
    "interest_threshold": 0.4,
    "risk_beta": 1.0,
    "risk_mix_lambda": 0.5,
    "risk_mask_threshold": 0.7,
    "trap_threshold": 0.9,
    "comm_range": math.inf,
    "intent_cov_floor": (1.0 / 28.0) ** 2,
    "backtrack_penalty": 0.1,
    "backtrack_window": 2,
    "collision_penalty": 0.2,
    "overflow_penalty": 1.0,
    "risk_penalty_threshold": 0.7,
    "terminal_scale": 1.0 / 900.0,
    "interest_bumps_min": 8,
    "interest_bumps_max": 12,
    "risk_bumps_min": 4,
    "risk_bumps_max": 6,
    "bump_std_min": 0.08,
    "bump_std_max": 0.12,
    "detect_radius": 0.05,
}


@pytest.mark.parametrize("name", sorted(PROTOCOL_DEFAULTS))
def test_default_equals_protocol(name):
    value = getattr(MAIPPConfig(), name)
    expected = PROTOCOL_DEFAULTS[name]
    assert type(value) is type(expected), (name, value)
    assert value == expected, (name, value, expected)


def test_derived_quantities():
    cfg = MAIPPConfig(n_agents=3, budget=2.0)
    assert cfg.team_budget == 6.0
    assert cfg.n_grid == 900
    assert cfg.n_roadmap_nodes == 201
    # Start measurements of every agent plus one per 0.2 of the shared pool.
    assert cfg.measurement_capacity >= 3 + 30
    assert cfg.torch_dtype is torch.float64
    assert MAIPPConfig(dtype="float32").torch_dtype is torch.float32
    assert MAIPPConfig().shared_belief and not MAIPPConfig(comm_range=0.3).shared_belief


BAD_VALUES = [
    ("budget", {"budget": -1.0}),
    ("budget", {"budget": 0.0}),
    ("budget", {"budget": math.inf}),
    ("k_neighbors", {"n_nodes": 30, "k_neighbors": 30}),
    ("k_neighbors", {"n_nodes": 30, "k_neighbors": 31}),
    ("kernel", {"kernel": "matern99"}),
    ("n_agents", {"n_agents": 0}),
    ("n_agents", {"n_agents": -2}),
    ("length_scale", {"length_scale": float("nan")}),
    ("budget", {"budget": float("nan")}),
    ("comm_range", {"comm_range": float("nan")}),
    ("n_agents", {"n_agents": 2.5}),
    ("n_agents", {"n_agents": True}),
    ("risk_enabled", {"risk_enabled": 1}),
    ("kernel", {"kernel": 3}),
    ("dtype", {"dtype": "float16"}),
    ("dtype", {"dtype": "bfloat16"}),
    ("comm_range", {"comm_range": 0.0}),
    ("aoi_bias", {"aoi_bias": 1.5}),
    ("risk_mix_lambda", {"risk_mix_lambda": -0.1}),
    ("gp_noise_variance", {"gp_noise_variance": 0.0}),
    ("sample_spacing", {"sample_spacing": 0.0}),
    ("interest_bumps_max", {"interest_bumps_min": 5, "interest_bumps_max": 4}),
    ("max_steps", {"max_steps": 0}),
    ("seed", {"seed": -1}),
]


@pytest.mark.parametrize(("field", "kwargs"), BAD_VALUES, ids=[repr(k) for _, k in BAD_VALUES])
def test_bad_value_raises_naming_field(field, kwargs):
    with pytest.raises(ValueError, match=rf"\b{field}\b"):
        MAIPPConfig(**kwargs)


def test_replace_revalidates():
    cfg = MAIPPConfig(budget=2.0)
    assert cfg.replace(budget=4.0).budget == 4.0
    with pytest.raises(ValueError, match="budget"):
        cfg.replace(budget=-1.0)


def test_from_dict_round_trip_and_unknown_key():
    cfg = MAIPPConfig(budget=2.0, n_agents=4, comm_range=0.6, dtype="float32")
    assert MAIPPConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError) as info:
        MAIPPConfig.from_dict({"budget": 2.0, "n_agent": 3})
    msg = str(info.value)
    assert "n_agent" in msg
    # The message lists the valid fields so the typo can be fixed.
    for name in ("n_agents", "budget", "comm_range", "length_scale"):
        assert name in msg


def test_constructor_rejects_unknown_field():
    with pytest.raises(TypeError):
        MAIPPConfig(n_agent=3)  # type: ignore[call-arg]


@pytest.mark.parametrize("batch_size", [[2, 3], [], [0]])
def test_env_rejects_bad_batch_size(batch_size):
    with pytest.raises(ValueError, match="batch_size"):
        MAIPPEnv(MAIPPConfig(budget=1.0, n_nodes=30, k_neighbors=6), batch_size=batch_size)


def test_env_overrides_are_validated():
    env = MAIPPEnv(MAIPPConfig(n_nodes=30, k_neighbors=6), batch_size=[1], budget=1.5)
    assert env.config.budget == 1.5
    with pytest.raises(ValueError, match="budget"):
        MAIPPEnv(MAIPPConfig(n_nodes=30, k_neighbors=6), batch_size=[1], budget=-1.0)


def test_numpy_scalars_are_accepted_as_python_numbers():
    import numpy as np

    cfg = MAIPPConfig(n_agents=np.int64(2), length_scale=np.float32(0.25), budget=3)
    assert (cfg.n_agents, cfg.length_scale, cfg.budget) == (2, 0.25, 3.0)
    assert type(cfg.n_agents) is int and type(cfg.length_scale) is type(cfg.budget) is float
    with pytest.raises(ValueError, match="n_agents"):
        MAIPPConfig(n_agents=np.float64(2.0))


def test_bad_devices_are_clear_errors(monkeypatch):
    from maipp_bench.envs.config import check_device

    assert check_device("cpu") == torch.device("cpu")
    for bad in ("gpu", "mps", 3.5):
        with pytest.raises(ValueError, match=r"device=.* is invalid: expected 'cpu', 'cuda'"):
            MAIPPEnv(MAIPPConfig(), batch_size=[1], device=bad)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    with pytest.raises(ValueError, match="CUDA is not available here"):
        check_device("cuda", "device")
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert check_device("cuda:0") == torch.device("cuda", 0)
    with pytest.raises(ValueError, match="only 1 CUDA device"):
        check_device("cuda:1", "--device")
