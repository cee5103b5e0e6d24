"""MAIPP environments: the batched TorchRL env and its building blocks."""

from maipp_bench.envs.belief import GPBelief, GPPrior
from maipp_bench.envs.config import MAIPPConfig
from maipp_bench.envs.maipp_env import METRICS, NODE_FEATURES, STATE_FEATURES, MAIPPEnv
from maipp_bench.envs.masked_random import MaskedRandomPolicy

__all__ = [
    "GPBelief", "GPPrior", "MAIPPConfig", "MAIPPEnv", "METRICS", "MaskedRandomPolicy",
    "NODE_FEATURES", "STATE_FEATURES",
]
