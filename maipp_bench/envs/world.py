"""Ground truth of one MAIPP instance: interest and risk fields, evidence sites, the AOI.

All E worlds are generated at once from per-env integer keys (see :mod:`rng`), so env
``e`` gets the same world whatever the batch size. Fields are mixtures of axis-aligned
Gaussian bumps normalised to a maximum of 1 on the evaluation grid (PROTOCOL, "World").
"""

from __future__ import annotations

import math

import torch
from tensordict import tensorclass

from maipp_bench.envs import rng
from maipp_bench.envs.config import MAIPPConfig

# Sub-stream tags of an instance key: one per random quantity, never reused.
_TAG_N_INTEREST, _TAG_INTEREST_CENTRES, _TAG_INTEREST_STDS = 1, 2, 3
_TAG_N_RISK, _TAG_RISK_CENTRES, _TAG_RISK_STDS = 4, 5, 6
_TAG_AOI = 7
_AOI_LATTICE = 21  # candidate AOI positions per axis


def grid_points(grid_size: int, dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
    """The evaluation grid ``linspace(0, 1, G)^2`` as ``[G*G, 2]`` (x varies fastest)."""
    lin = torch.linspace(0.0, 1.0, grid_size, dtype=dtype, device=device)
    yy, xx = torch.meshgrid(lin, lin, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


@tensorclass
class World:
    """Ground truth of a batch of instances (leading dim: envs).

    ``evidence`` sites are the interest bump centres (PROTOCOL: sparse evidence).
    """

    interest_centres: torch.Tensor  # [E, Ki, 2]
    interest_stds: torch.Tensor  # [E, Ki, 2]
    interest_valid: torch.Tensor  # [E, Ki] bool: bump k exists (K_it <= Ki)
    interest_norm: torch.Tensor  # [E]: max of the raw mixture on the grid
    risk_centres: torch.Tensor  # [E, Kr, 2]
    risk_stds: torch.Tensor  # [E, Kr, 2]
    risk_valid: torch.Tensor  # [E, Kr] bool (all False when risk is off)
    risk_norm: torch.Tensor  # [E]
    aoi_low: torch.Tensor  # [E, 2] lower-left corner of the AOI rectangle
    aoi_high: torch.Tensor  # [E, 2] upper-right corner

    # ---------------------------------------------------------------- fields
    def interest(self, points: torch.Tensor) -> torch.Tensor:
        """True interest y_it at ``points [E, P, 2]`` -> ``[E, P]``."""
        raw = _mixture(points, self.interest_centres, self.interest_stds, self.interest_valid)
        return raw / self.interest_norm.unsqueeze(-1)

    def risk(self, points: torch.Tensor) -> torch.Tensor:
        """True risk y_rk at ``points [E, P, 2]`` -> ``[E, P]`` (zero when risk is off)."""
        raw = _mixture(points, self.risk_centres, self.risk_stds, self.risk_valid)
        return raw / self.risk_norm.unsqueeze(-1)

    def signal(self, points: torch.Tensor, mix_lambda: float) -> torch.Tensor:
        """The interest signal the agents measure: y_mix = y_it (1 - lambda y_rk)."""
        return self.measure(points, mix_lambda)[0]

    def measure(self, points: torch.Tensor, mix_lambda: float
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """What a sensor at ``points [E, P, 2]`` reads, noise-free: the interest signal
        and the risk, ``[E, P]`` each (the risk field evaluated once for both)."""
        risk = self.risk(points)
        return self.interest(points) * (1.0 - mix_lambda * risk), risk

    def grid_signal(self, grid_size: int, mix_lambda: float) -> torch.Tensor:
        """The interest signal on the ``G x G`` evaluation grid -> ``[E, G*G]`` (fast path)."""
        lin = torch.linspace(0.0, 1.0, grid_size, dtype=torch.float64,
                             device=self.interest_norm.device)
        it = _grid_mixture(lin, self.interest_centres, self.interest_stds, self.interest_valid)
        rk = _grid_mixture(lin, self.risk_centres, self.risk_stds, self.risk_valid)
        it = it / self.interest_norm.unsqueeze(-1)
        rk = rk / self.risk_norm.unsqueeze(-1)
        return it * (1.0 - mix_lambda * rk)

    # ---------------------------------------------------------------- AOI and evidence
    @property
    def evidence(self) -> torch.Tensor:
        return self.interest_centres

    def in_aoi(self, points: torch.Tensor) -> torch.Tensor:
        """Whether ``points [E, P, 2]`` lie inside the AOI rectangle -> bool ``[E, P]``."""
        lo, hi = self.aoi_low.unsqueeze(-2), self.aoi_high.unsqueeze(-2)
        return ((points >= lo) & (points <= hi)).all(-1)


def _mixture(points, centres, stds, valid):
    """Sum of axis-aligned Gaussian densities: ``points [E, P, 2]`` -> ``[E, P]``."""
    z = (points.unsqueeze(-2) - centres.unsqueeze(-3)) / stds.unsqueeze(-3)  # [E, P, K, 2]
    dens = torch.exp(-0.5 * (z * z).sum(-1)) / (2.0 * math.pi * stds.prod(-1).unsqueeze(-2))
    return (dens * valid.unsqueeze(-2)).sum(-1)


def _grid_mixture(lin, centres, stds, valid):
    """``_mixture`` on the grid ``lin x lin``, using that axis-aligned bumps are separable:
    O(K G) exponentials instead of O(K G^2)."""
    gx = torch.exp(-0.5 * ((lin - centres[..., 0:1]) / stds[..., 0:1]) ** 2)  # [E, K, G]
    gy = torch.exp(-0.5 * ((lin - centres[..., 1:2]) / stds[..., 1:2]) ** 2)
    w = valid / (2.0 * math.pi * stds.prod(-1))  # [E, K]
    # value[y, x] = sum_k w_k gy[k, y] gx[k, x]  (x varies fastest, as in grid_points)
    return torch.einsum("ek,eky,ekx->eyx", w, gy, gx).reshape(centres.shape[0], -1)


def _bumps(key, n_min, n_max, std_min, std_max, tags):
    tag_n, tag_c, tag_s = tags
    count = rng.randint(rng.derive(key, tag_n), n_min, n_max)  # [E]
    centres = rng.uniform(rng.derive(key, tag_c), (n_max, 2))
    stds = std_min + (std_max - std_min) * rng.uniform(rng.derive(key, tag_s), (n_max, 2))
    valid = torch.arange(n_max, device=key.device) < count.unsqueeze(-1)
    return centres, stds, valid


def generate_world(cfg: MAIPPConfig, instance_key: torch.Tensor) -> World:
    """Generate ``len(instance_key)`` worlds (float64, on the keys' device)."""
    e, device = instance_key.shape[0], instance_key.device
    lin = torch.linspace(0.0, 1.0, cfg.grid_size, dtype=torch.float64, device=device)
    ic, istd, ivalid = _bumps(
        instance_key, cfg.interest_bumps_min, cfg.interest_bumps_max,
        cfg.bump_std_min, cfg.bump_std_max,
        (_TAG_N_INTEREST, _TAG_INTEREST_CENTRES, _TAG_INTEREST_STDS),
    )
    rc, rstd, rvalid = _bumps(
        instance_key, cfg.risk_bumps_min, cfg.risk_bumps_max,
        cfg.bump_std_min, cfg.bump_std_max,
        (_TAG_N_RISK, _TAG_RISK_CENTRES, _TAG_RISK_STDS),
    )
    if not cfg.risk_enabled:
        rvalid = torch.zeros_like(rvalid)
    inorm = _grid_mixture(lin, ic, istd, ivalid).amax(-1)
    rnorm = _grid_mixture(lin, rc, rstd, rvalid).amax(-1)
    rnorm = torch.where(rnorm > 0, rnorm, torch.ones_like(rnorm))
    aoi_low, aoi_high = _place_aoi(cfg, instance_key, ic, ivalid)
    return World(
        interest_centres=ic, interest_stds=istd, interest_valid=ivalid, interest_norm=inorm,
        risk_centres=rc, risk_stds=rstd, risk_valid=rvalid, risk_norm=rnorm,
        aoi_low=aoi_low, aoi_high=aoi_high, batch_size=[e],
    )


def _place_aoi(cfg, key, sites, valid):
    """Square AOI of area ``aoi_fraction`` whose share of evidence outside is closest to
    ``aoi_bias`` (bias 0: the placement containing the most evidence). Ties are broken by
    a keyed random score so the choice is reproducible."""
    e, device = key.shape[0], key.device
    side = math.sqrt(cfg.aoi_fraction)
    if not cfg.aoi_enabled:  # the whole workspace is the AOI
        low = torch.zeros(e, 2, dtype=torch.float64, device=device)
        return low, torch.ones_like(low)
    lin = torch.linspace(0.0, 1.0 - side, _AOI_LATTICE, dtype=torch.float64, device=device)
    cy, cx = torch.meshgrid(lin, lin, indexing="ij")
    corners = torch.stack([cx.reshape(-1), cy.reshape(-1)], -1)  # [C, 2]
    lo = corners.view(1, -1, 1, 2)
    inside = ((sites.unsqueeze(1) >= lo) & (sites.unsqueeze(1) <= lo + side)).all(-1)  # [E,C,K]
    n_in = (inside & valid.unsqueeze(1)).sum(-1).to(torch.float64)
    n_all = valid.sum(-1, keepdim=True).to(torch.float64)
    score = ((n_all - n_in) / n_all - cfg.aoi_bias).abs()
    score = score + 1e-6 * rng.uniform(rng.derive(key, _TAG_AOI), (corners.shape[0],))
    best = corners[score.argmin(-1)]
    return best, best + side
