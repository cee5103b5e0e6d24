"""Typed configuration of the MAIPP task: every number of PROTOCOL v1 is a field here.

Each field's comment names its source: ``paper`` (the LaTeX source), ``ref`` (the public
reference code of CAtNIPP and its multi-agent line), or ``ours`` (a maipp_bench decision,
argued in docs/environment.md).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, fields
from typing import Any

import torch

from maipp_bench.envs.kernels import KERNELS

_DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class MAIPPConfig:
    """All parameters of one MAIPP task setting, validated on construction.

    A bad value raises ``ValueError`` naming the field and what is allowed; an unknown
    field raises ``TypeError`` (constructor) or ``ValueError`` (:meth:`from_dict`).

    Example:
        >>> cfg = MAIPPConfig(n_agents=3, budget=2.0)
        >>> cfg.team_budget
        6.0
    """

    # --- team and budget ------------------------------------------------------------
    n_agents: int = 3  # paper: m = 3 in training and Table 1
    budget: float = 3.0  # per-agent equivalent budget B; ours: default mid-range of Table 1
    budget_min: float = 0.0  # ours: > 0 draws each episode's B uniformly from [budget_min, budget]
    max_steps: int = 1000  # ours: safety cap; episodes normally end on the budget

    # --- world (ground truth) -----------------------------------------------------
    grid_size: int = 30  # paper: 30 x 30 evaluation grid, Tr(P_0) = 900
    interest_bumps_min: int = 8  # paper: 8-12 Gaussian components
    interest_bumps_max: int = 12
    risk_bumps_min: int = 4  # paper: 4-6 risk zones
    risk_bumps_max: int = 6
    bump_std_min: float = 0.08  # ref: effective per-axis std of the reference fields
    bump_std_max: float = 0.12
    risk_enabled: bool = True  # paper Table 1: risk on; Table 2: risk off
    risk_mix_lambda: float = 0.5  # paper: y_mix = y_it * (1 - lambda * y_rk)
    detect_radius: float = 0.05  # ours: evidence site discovered within this distance

    # --- area of interest (dual-domain) --------------------------------------------
    aoi_enabled: bool = False  # ours: AOI prior given to agents (aoi_bias suite)
    aoi_fraction: float = 0.25  # ours: AOI rectangle area / workspace area
    aoi_bias: float = 0.0  # ours: fraction of evidence placed outside the AOI
    aoi_outside_weight: float = 0.5  # ours: objective weight of grid cells outside AOI

    # --- belief (GP) -----------------------------------------------------------------
    kernel: str = "matern32"  # paper: Matern nu = 3/2
    length_scale: float = 0.25  # ref: multi-agent line (single-agent CAtNIPP: 0.45)
    prior_variance: float = 1.0  # PROTOCOL: prior variance 1, prior mean 0
    measurement_noise_std: float = 0.01  # PROTOCOL: N(0, 0.01^2) sensor noise
    gp_noise_variance: float = 1e-4  # ours: GP noise term, also keeps float32 stable
    interest_beta: float = 1.0  # ref: X_I = {mu + beta sigma >= mu_th}
    interest_threshold: float = 0.4  # ref: mu_th
    risk_beta: float = 1.0  # paper: risk UCB mu_rk + beta sigma_rk

    # --- roadmap and motion ----------------------------------------------------------
    n_nodes: int = 200  # paper: 200 PRM nodes (plus the start node)
    k_neighbors: int = 20  # paper: k = 20 nearest neighbours
    node_encoding_dim: int = 0  # ours: > 0 adds the roadmap's Laplacian encoding (paper: 32)
    sample_spacing: float = 0.2  # paper: a measurement every 0.2 of travelled path
    prune_risky_nodes: bool = False  # paper: baselines without risk get risky nodes removed

    # --- safety ----------------------------------------------------------------------------
    risk_mask_threshold: float = 0.7  # paper: hard risk threshold (applied to risk mean)
    trap_threshold: float = 0.9  # ours: true risk >= this at a waypoint traps the agent

    # --- communication and intent ------------------------------------------------------
    comm_range: float = math.inf  # paper Table 3: {0.3, 0.6, inf}
    intent_cov_floor: float = (1.0 / 28.0) ** 2  # ref: sample covariance + (1/28)^2 I

    # --- reward --------------------------------------------------------------------------
    backtrack_penalty: float = 0.1  # paper
    backtrack_window: int = 2  # ref: last 2 nodes
    collision_penalty: float = 0.2  # paper
    overflow_penalty: float = 1.0  # paper (also terminates)
    risk_penalty_threshold: float = 0.7  # paper: true risk above 0.7 is penalised
    terminal_scale: float = 1.0 / 900.0  # paper: lambda_term = 1/900

    # --- numerics and seeding --------------------------------------------------------
    dtype: str = "float64"  # ours: exact float64 belief; float32 optional
    seed: int = 0  # ours: base seed of the counter-based world RNG

    def __post_init__(self) -> None:
        self._validate()

    # ------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> MAIPPConfig:
        """Build from a mapping (e.g. a Hydra node); unknown keys raise ``ValueError``."""
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ValueError(
                f"MAIPPConfig: unknown field(s) {unknown}; valid fields are {sorted(names)}"
            )
        return cls(**dict(values))

    def to_dict(self) -> dict[str, Any]:
        """Plain-dict view of the public fields (for logs, leaderboards and hashing)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def replace(self, **changes: Any) -> MAIPPConfig:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------------------------
    @property
    def torch_dtype(self) -> torch.dtype:
        return _DTYPES[self.dtype]

    @property
    def team_budget(self) -> float:
        """B_team = m * B: the shared pool every move draws from (its largest value when
        ``budget_min`` > 0 draws B per episode)."""
        return self.n_agents * self.budget

    @property
    def n_grid(self) -> int:
        return self.grid_size * self.grid_size

    @property
    def n_roadmap_nodes(self) -> int:
        """Sampled nodes plus the shared start node (index 0)."""
        return self.n_nodes + 1

    @property
    def measurement_capacity(self) -> int:
        """Upper bound on the team's measurements in one episode.

        Each agent measures at the start and then once per ``sample_spacing`` of its own
        path, so the team takes at most m + floor(B_team / spacing) measurements.
        """
        return self.n_agents + int(math.floor(self.team_budget / self.sample_spacing + 1e-9)) + 1

    @property
    def shared_belief(self) -> bool:
        """With unlimited range every agent holds the same belief: keep one per env."""
        return math.isinf(self.comm_range)

    # ------------------------------------------------------------------------------------
    def _validate(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            expected = f.type if isinstance(f.type, str) else f.type.__name__
            if expected == "bool":
                if not isinstance(value, bool):
                    _bad(f.name, value, "a bool")
            elif expected == "int":
                if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                    _bad(f.name, value, "an int")
                object.__setattr__(self, f.name, int(value))  # numpy ints become Python ints
            elif expected == "str":
                if not isinstance(value, str):
                    _bad(f.name, value, "a str")
            elif expected == "float":
                if isinstance(value, bool) or not isinstance(value, numbers.Real):
                    _bad(f.name, value, "a number")
                value = float(value)  # numpy and int values become Python floats
                object.__setattr__(self, f.name, value)
                if math.isnan(value):
                    _bad(f.name, value, "a number, not NaN")
        # Range checks: (field, predicate, what is allowed).
        finite = math.isfinite
        rules = [
            ("n_agents", lambda v: v >= 1, "an int >= 1"),
            ("budget", lambda v: v > 0 and finite(v), "a finite number > 0"),
            ("budget_min", lambda v: 0 <= v <= self.budget,
             f"a number in [0, budget] = [0, {self.budget}] (0: fixed budget)"),
            ("max_steps", lambda v: v >= 1, "an int >= 1"),
            ("grid_size", lambda v: v >= 2, "an int >= 2"),
            ("interest_bumps_min", lambda v: v >= 1, "an int >= 1"),
            ("interest_bumps_max", lambda v: v >= self.interest_bumps_min,
             f"an int >= interest_bumps_min ({self.interest_bumps_min})"),
            ("risk_bumps_min", lambda v: v >= 1, "an int >= 1"),
            ("risk_bumps_max", lambda v: v >= self.risk_bumps_min,
             f"an int >= risk_bumps_min ({self.risk_bumps_min})"),
            ("bump_std_min", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("bump_std_max", lambda v: self.bump_std_min <= v and finite(v),
             f"a finite number >= bump_std_min ({self.bump_std_min})"),
            ("risk_mix_lambda", lambda v: 0 <= v <= 1, "a number in [0, 1]"),
            ("detect_radius", lambda v: 0 <= v and finite(v), "a finite number >= 0"),
            ("aoi_fraction", lambda v: 0 < v <= 1, "a number in (0, 1]"),
            ("aoi_bias", lambda v: 0 <= v <= 1, "a number in [0, 1]"),
            ("aoi_outside_weight", lambda v: 0 <= v and finite(v), "a finite number >= 0"),
            ("kernel", lambda v: v in KERNELS, f"one of {sorted(KERNELS)}"),
            ("length_scale", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("prior_variance", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("measurement_noise_std", lambda v: 0 <= v and finite(v), "a finite number >= 0"),
            ("gp_noise_variance", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("interest_beta", lambda v: 0 <= v and finite(v), "a finite number >= 0"),
            ("interest_threshold", lambda v: finite(v), "a finite number"),
            ("risk_beta", lambda v: 0 <= v and finite(v), "a finite number >= 0"),
            ("n_nodes", lambda v: v >= 2, "an int >= 2"),
            ("k_neighbors", lambda v: 1 <= v < self.n_nodes,
             f"an int in [1, n_nodes) = [1, {self.n_nodes})"),
            ("node_encoding_dim", lambda v: 0 <= v <= self.n_nodes,
             f"an int in [0, n_nodes] = [0, {self.n_nodes}] (0: no encoding key)"),
            ("sample_spacing", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("risk_mask_threshold", lambda v: finite(v), "a finite number"),
            ("trap_threshold", lambda v: finite(v), "a finite number"),
            ("comm_range", lambda v: v > 0, "a number > 0 (inf for global communication)"),
            ("intent_cov_floor", lambda v: 0 < v and finite(v), "a finite number > 0"),
            ("backtrack_penalty", lambda v: finite(v), "a finite number"),
            ("backtrack_window", lambda v: v >= 0, "an int >= 0"),
            ("collision_penalty", lambda v: finite(v), "a finite number"),
            ("overflow_penalty", lambda v: finite(v), "a finite number"),
            ("risk_penalty_threshold", lambda v: finite(v), "a finite number"),
            ("terminal_scale", lambda v: finite(v), "a finite number"),
            ("dtype", lambda v: v in _DTYPES, f"one of {sorted(_DTYPES)}"),
            ("seed", lambda v: 0 <= v < 2**62, "an int in [0, 2**62)"),
        ]
        for name, ok, allowed in rules:
            value = getattr(self, name)
            if not ok(value):
                _bad(name, value, allowed)


def _bad(name: str, value: Any, allowed: str) -> None:
    raise ValueError(f"MAIPPConfig.{name}={value!r} is invalid: expected {allowed}")


def check_device(device: str | torch.device, what: str = "device") -> torch.device:
    """``device`` as a ``torch.device``; a ``ValueError`` naming ``what`` when it is not a
    CPU or CUDA device, or CUDA is not available here (torch's own errors name neither
    the option nor the remedy)."""
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        dev = None
    if dev is None or dev.type not in ("cpu", "cuda"):
        raise ValueError(f"{what}={device!r} is invalid: expected 'cpu', 'cuda' or 'cuda:N'")
    if dev.type == "cuda":
        # device_count asks NVML and leaves CUDA uninitialised (is_available initialises
        # it), so processes forked later, e.g. eval's workers, can still use CUDA.
        count = torch.cuda.device_count()
        if count == 0:
            raise ValueError(f"{what}={device!r}: CUDA is not available here (torch "
                             f"{torch.__version__}); use 'cpu'")
        if dev.index is not None and dev.index >= count:
            raise ValueError(f"{what}={device!r}: only {count} CUDA device(s) here")
    return dev
