"""A reference-style MAIPP environment: one env, plain Python + numpy/scipy, dense GP refit.

This is the baseline that ``env_throughput.py`` compares ``MAIPPEnv`` against. It follows
the step semantics of ``maipp_bench.envs.MAIPPEnv`` with global communication (one shared
team belief) and does the per-step work the public reference code of this field does
(see /work/shared/REFERENCE_NOTES.md):

* two float64 GPs (interest signal and risk), Matern 3/2, length scale 0.25, noise 1e-4,
  each refit *from scratch* on all measurements so far at every decision event
  (``scipy.linalg.cho_factor`` / ``cho_solve``), then predicted (mean and variance) at all
  1101 query points: the 30x30 grid and the 201 roadmap nodes;
* X_I, Tr(P), the RMSE of the interest map, the node features and the feasibility masks
  are recomputed after every refit;
* Python loops over agents and over motion events, as the reference code has.

It is not bit-identical to ``MAIPPEnv`` (worlds come from numpy's RNG, not the
counter-based keys), but the laws, the rules and the amount of work per step are the same.
Like the reference code (one GP library object per channel) it does not share the
Cholesky factor between the two channels; it also skips the reference code's all-pairs
shortest paths at reset, which ``MAIPPEnv`` does not compute either.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.spatial import cKDTree

EPS = 1e-9  # arrival ties and budget fits, as in maipp_bench.envs.dynamics


def matern32(a: np.ndarray, b: np.ndarray, length_scale: float) -> np.ndarray:
    """Matern nu=3/2 correlation between point sets ``a [P, 2]`` and ``b [Q, 2]``."""
    diff = a[:, None, :] - b[None, :, :]
    s = math.sqrt(3.0) * np.sqrt((diff * diff).sum(-1)) / length_scale
    return (1.0 + s) * np.exp(-s)


class DenseGP:
    """Zero-mean GP with fixed hyperparameters, fitted from scratch on every call."""

    def __init__(self, length_scale: float, variance: float, noise: float) -> None:
        self.length_scale, self.variance, self.noise = length_scale, variance, noise

    def fit_predict(self, x: np.ndarray, y: np.ndarray, query: np.ndarray):
        """Posterior mean and variance at ``query [Q, 2]`` given ``x [n, 2], y [n]``."""
        k = self.variance * matern32(x, x, self.length_scale) + self.noise * np.eye(len(x))
        factor = cho_factor(k, lower=True)
        k_star = self.variance * matern32(x, query, self.length_scale)  # [n, Q]
        mean = k_star.T @ cho_solve(factor, y)
        var = self.variance - np.einsum("nq,nq->q", k_star, cho_solve(factor, k_star))
        return mean, np.maximum(var, 0.0)


def bump_field(rng: np.random.Generator, k_min: int, k_max: int, std_min: float,
               std_max: float, grid: np.ndarray):
    """A mixture of axis-aligned Gaussian bumps normalised to max 1 on the grid."""
    count = rng.integers(k_min, k_max + 1)
    centres = rng.uniform(0.0, 1.0, (count, 2))
    stds = rng.uniform(std_min, std_max, (count, 2))

    def raw(pts: np.ndarray) -> np.ndarray:
        z = (pts[:, None, :] - centres[None]) / stds[None]
        return (np.exp(-0.5 * (z * z).sum(-1)) / (2 * math.pi * stds.prod(-1))).sum(-1)

    norm = raw(grid).max()
    return (lambda pts: raw(pts) / norm), centres


class ReferenceMAIPPEnv:
    """Single-env MAIPP with a shared team belief, refit densely at every decision event.

    Example:
        >>> env = ReferenceMAIPPEnv(budget=1.0)
        >>> obs = env.reset(seed=0)
        >>> obs, reward, done = env.step(env.random_masked_action(np.random.default_rng(0)))
        >>> obs["node_features"].shape, reward.shape
        ((3, 201, 5), (3,))
    """

    def __init__(self, n_agents: int = 3, budget: float = 3.0, n_nodes: int = 200,
                 k_neighbors: int = 20, grid_size: int = 30, length_scale: float = 0.25,
                 noise: float = 1e-4, sample_spacing: float = 0.2, max_steps: int = 1000,
                 risk_enabled: bool = True) -> None:
        self.m, self.k, self.n_nodes = n_agents, k_neighbors, n_nodes
        self.team_budget, self.spacing = n_agents * budget, sample_spacing
        self.max_steps, self.risk_enabled = max_steps, risk_enabled
        self.mix_lambda, self.noise_std, self.detect_radius = 0.5, 0.01, 0.05
        self.beta, self.threshold, self.risk_beta, self.risk_mask = 1.0, 0.4, 1.0, 0.7
        self.risk_penalty, self.trap = 0.7, 0.9
        self.backtrack_window, self.terminal_scale = 2, 1.0 / 900.0
        self.collision_penalty, self.overflow_penalty, self.backtrack_penalty = 0.2, 1.0, 0.1
        lin = np.linspace(0.0, 1.0, grid_size)
        yy, xx = np.meshgrid(lin, lin, indexing="ij")
        self.grid = np.stack([xx.ravel(), yy.ravel()], -1)  # [900, 2]
        self.gp = DenseGP(length_scale, 1.0, noise)

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | None = None) -> dict:
        rng = self.rng = np.random.default_rng(seed)
        m = self.m
        self.interest, self.evidence = bump_field(rng, 8, 12, 0.08, 0.12, self.grid)
        if self.risk_enabled:
            self.risk, _ = bump_field(rng, 4, 6, 0.08, 0.12, self.grid)
        else:
            self.risk = lambda pts: np.zeros(len(pts))
        self.grid_truth = self.signal(self.grid)
        # PRM: node 0 is the shared start; action slots are the k nearest other nodes.
        self.nodes = rng.uniform(0.0, 1.0, (self.n_nodes + 1, 2))
        dist, idx = cKDTree(self.nodes).query(self.nodes, k=self.k + 1)
        self.nbr, self.nbr_len = idx[:, 1:], dist[:, 1:]
        self.node_risk = self.risk(self.nodes)
        self.query = np.concatenate([self.grid, self.nodes])  # 1101 query points
        self.time, self.steps, self.budget_used = 0.0, 0, 0.0
        self.cur, self.tgt = np.zeros(m, dtype=np.int64), np.zeros(m, dtype=np.int64)
        self.edge_len, self.progress, self.since = np.zeros(m), np.zeros(m), np.zeros(m)
        self.trapped = np.zeros(m, dtype=bool)
        self.history = np.full((m, self.backtrack_window), -1)
        self.meas_x, self.meas_y = [], []
        self.found = np.zeros(len(self.evidence), dtype=bool)
        self._measure(np.repeat(self.nodes[:1], m, axis=0))  # everyone measures at start
        self._decision_event()
        return self._observe()

    def signal(self, pts: np.ndarray) -> np.ndarray:
        """The interest signal the agents measure: y_it (1 - lambda y_rk)."""
        return self.interest(pts) * (1.0 - self.mix_lambda * self.risk(pts))

    def step(self, actions: np.ndarray):
        """Apply the deciding agents' actions; advance to the next decision event."""
        m, deciding = self.m, self.deciding.copy()
        actions = np.asarray(actions, dtype=np.int64)
        for a in np.flatnonzero(deciding):
            if not (0 <= actions[a] < self.k and self.mask[a, actions[a]]):
                raise ValueError(f"masked or out-of-range action {actions[a]} for agent {a}")
        penalty, terminated = np.zeros(m), False
        chosen = np.full(m, -1)
        committed = 0.0
        for a in np.flatnonzero(deciding):  # agent order: the lower index wins a clash
            node, length = self.nbr[self.cur[a], actions[a]], self.nbr_len[self.cur[a], actions[a]]
            clash = (chosen[:a] == node).any()
            chosen[a] = node
            if clash:
                penalty[a] += self.collision_penalty  # it waits and decides again
                continue
            committed += length
            if self.budget_used + committed > self.team_budget + EPS:
                penalty[a] += self.overflow_penalty
                terminated = True
                continue
            if (self.history[a] == node).any():
                penalty[a] += self.backtrack_penalty
            self.tgt[a], self.edge_len[a], self.progress[a] = node, length, 0.0
            self.budget_used += length
        before = self.objective
        if not terminated:
            terminated = not self._advance(penalty)
        self.steps += 1
        truncated = self.steps >= self.max_steps and not terminated
        done = terminated or truncated
        if done:
            self.deciding[:] = False
            self.mask[:] = True
        gain = max(0.0, (before - self.objective) / max(before, 1e-12))
        reward = gain - penalty - (self.terminal_scale * self.objective if done else 0.0)
        return self._observe(), reward, done

    def random_masked_action(self, rng: np.random.Generator) -> np.ndarray:
        """Uniform over each deciding agent's feasible slots (0 for the others)."""
        actions = np.zeros(self.m, dtype=np.int64)
        for a in np.flatnonzero(self.deciding):
            actions[a] = rng.choice(np.flatnonzero(self.mask[a]))
        return actions

    # ------------------------------------------------------------------ motion
    def _advance(self, penalty: np.ndarray) -> bool:
        """Advance event by event until some agent decides; False if nobody can move."""
        while True:
            moving = self.edge_len > 0
            if not moving.any():
                return False
            left = np.where(moving, self.edge_len - self.progress, np.inf)
            dt = left.min()
            for a in np.flatnonzero(moving):
                self._travel(a, dt)
            self.time += dt
            for a in np.flatnonzero(moving & (left <= dt + EPS)):
                self._arrive(a, penalty)
            self._decision_event()
            if self.deciding.any():
                return True

    def _travel(self, a: int, dist: float) -> None:
        """Move agent ``a`` by ``dist`` along its edge, measuring every ``spacing``."""
        total = self.since[a] + dist
        count = int(math.floor(total / self.spacing + EPS))
        if count:
            src, dst = self.nodes[self.cur[a]], self.nodes[self.tgt[a]]
            along = self.progress[a] + self.spacing * np.arange(1, count + 1) - self.since[a]
            self._measure(src + (dst - src) * (along / self.edge_len[a])[:, None])
        self.since[a] = max(total - count * self.spacing, 0.0)
        self.progress[a] += dist

    def _arrive(self, a: int, penalty: np.ndarray) -> None:
        self.history[a] = np.concatenate([[self.cur[a]], self.history[a, :-1]])
        self.cur[a], self.edge_len[a], self.progress[a] = self.tgt[a], 0.0, 0.0
        risk = self.node_risk[self.cur[a]]
        if self.risk_enabled:
            penalty[a] += risk if risk > self.risk_penalty else 0.0
            self.trapped[a] |= risk >= self.trap

    def _measure(self, pts: np.ndarray) -> None:
        noise = self.noise_std * self.rng.standard_normal((len(pts), 2))
        self.meas_x.append(pts)
        self.meas_y.append(np.stack([self.signal(pts), self.risk(pts)], -1) + noise)
        d = np.linalg.norm(pts[:, None] - self.evidence[None], axis=-1)
        self.found |= (d <= self.detect_radius).any(0)

    # ------------------------------------------------------------------ belief and masks
    def _decision_event(self) -> None:
        """Refit both GPs from scratch on all measurements; recompute X_I, Tr(P), masks."""
        x, y = np.concatenate(self.meas_x), np.concatenate(self.meas_y)
        mu, var = self.gp.fit_predict(x, y[:, 0], self.query)
        risk_mu, risk_var = self.gp.fit_predict(x, y[:, 1], self.query)
        g = len(self.grid)
        region = mu[:g] + self.beta * np.sqrt(var[:g]) >= self.threshold
        self.objective = self.trace = var[:g][region].sum()
        self.rmse = np.sqrt(((mu[:g] - self.grid_truth) ** 2).mean())
        self.node_mu, self.node_sd = mu[g:], np.sqrt(var[g:])
        self.node_ucb = risk_mu[g:] + self.risk_beta * np.sqrt(risk_var[g:])
        self.deciding = np.zeros(self.m, dtype=bool)
        self.mask = np.ones((self.m, self.k), dtype=bool)
        for a in range(self.m):
            nbr = self.nbr[self.cur[a]]
            ok = self.nbr_len[self.cur[a]] <= self.team_budget - self.budget_used + EPS
            ok &= ~np.isin(nbr, np.delete(self.tgt, a))  # node collision
            if self.risk_enabled:
                ok &= risk_mu[g + nbr] <= self.risk_mask
            self.deciding[a] = self.edge_len[a] == 0 and not self.trapped[a] and ok.any()
            if self.deciding[a]:
                self.mask[a] = ok

    def _observe(self) -> dict:
        n = len(self.nodes)
        ucb = self.node_ucb if self.risk_enabled else np.zeros(n)
        feats = np.stack([self.nodes[:, 0], self.nodes[:, 1], self.node_mu, self.node_sd, ucb], -1)
        return {
            "node_features": np.repeat(feats[None], self.m, axis=0),  # [m, N, 5]
            "current_node": self.cur.copy(),
            "budget": max(0.0, 1.0 - self.budget_used / self.team_budget),
            "neighbors": self.nbr[self.cur],
            "neighbor_dist": self.nbr_len[self.cur],
            "action_mask": self.mask.copy(),
            "deciding": self.deciding.copy(),
            "metrics": {"trace": self.trace, "rmse": self.rmse, "time": self.time,
                        "distance": self.budget_used, "evidence": int(self.found.sum()),
                        "traps": int(self.trapped.sum()),
                        "measurements": sum(len(p) for p in self.meas_x)},
        }
