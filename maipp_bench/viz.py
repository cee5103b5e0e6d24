"""Pictures of MAIPP episodes: the panels of the paper's Figure 3, as images and GIFs.

Headless and free of global state: figures are plain :class:`matplotlib.figure.Figure`
objects drawn by the Agg renderer (:class:`~matplotlib.backends.backend_agg.FigureCanvasAgg`),
never registered with ``pyplot``, so importing or calling this module changes no backend
and leaks no figures, whatever backend the caller uses::

    from maipp_bench import viz

    env = MAIPPEnv(MAIPPConfig(n_agents=3, budget=2.0), batch_size=[4])
    td = env.reset()
    rgb = viz.render(env, index=0)          # [H, W, 3] uint8: the env.render() of this task
    fig = viz.draw(env, index=0)            # the Figure, e.g. fig.savefig("step0.pdf")
    viz.save_episode(env, "out/episode")    # out/episode.png (final state), .gif (each step)

Panels, for env ``index`` at the current step (team belief = the last belief, all
measurements; the grid is the 30 x 30 evaluation grid):

(a) predicted interest mean, every agent's trajectory (its visited nodes, then the edge in
    progress) and measurement points in the agent's colour;
(b) ground-truth interest signal (what the agents measure: y_mix with risk on);
(c) risk prediction (team risk mean) with trap nodes (true risk >= ``trap_threshold``, x);
(d) GP standard deviation sqrt(sigma^2);
(e) the high-interest region X_I = {mu + beta sigma >= threshold} (``interest_beta``,
    ``interest_threshold``) whose variance is Tr(P);
(f) the intent distribution: the sum of the Gaussian densities of every intent the agents
    have broadcast (their latest), or "no intents" when none was.

Overlays: the AOI outline (``aoi_enabled``), evidence sites (filled: found, hollow: not
yet), current agent positions (numbered; a trapped agent is crossed out).

``draw``, ``render`` and ``save_episode`` accept a :class:`~maipp_bench.envs.MAIPPEnv`,
a TorchRL ``TransformedEnv`` around one, or a
:class:`~maipp_bench.envs.pettingzoo.MAIPPParallelEnv` (``draw``/``render`` only).
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from matplotlib import patheffects
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import ListedColormap, to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle
from tensordict import TensorDictBase

from maipp_bench.envs.maipp_env import MAIPPEnv

__all__ = ["draw", "render", "save_episode", "AGENT_COLOURS"]

# Agent colours: tab10 without its red (red marks evidence); cycled beyond 9 agents.
AGENT_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                 "#17becf", "#bcbd22", "#7f7f7f")
_EVIDENCE = "#e41a1c"
_REGION_CMAP = ListedColormap(["#d9d9d9", "#fdae61"])
_INTENT_RES = 30  # intent densities: on a grid like the evaluation grid
_FIGSIZE = (12.0, 8.4)
_PAINTERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # render()'s figures
_TITLES = (
    "(a) interest mean (team belief)",
    "(b) ground-truth interest signal",
    "(c) risk mean (team belief)",
    "(d) interest std (team belief)",
    "(e) high-interest region $X_I$",
    "(f) intents (sum of densities)",
)


def _unwrap(env: Any) -> MAIPPEnv:
    """The :class:`MAIPPEnv` under ``env`` (itself, a TransformedEnv's base, a PettingZoo
    view's ``env``)."""
    seen = 0
    while not isinstance(env, MAIPPEnv):
        inner = getattr(env, "base_env", None)
        if inner is None:
            inner = getattr(env, "env", None)
        if inner is None or seen > 8:
            raise TypeError(f"maipp_bench.viz: expected a MAIPPEnv (or a wrapper of one), "
                            f"got {type(env).__name__}")
        env, seen = inner, seen + 1
    return env


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


class _Snapshot:
    """Everything one picture needs, of env ``index``, as numpy arrays (float64)."""

    def __init__(self, base: MAIPPEnv, index: int) -> None:
        st = base.episode
        if not 0 <= index < base.n_envs:
            raise IndexError(f"maipp_bench.viz: index must be in [0, {base.n_envs}), "
                             f"got {index}")
        cfg, i, g = base.config, index, base.config.grid_size
        g2 = cfg.n_grid
        team = st.belief[i, -1]
        self.mu = _np(team.mu[:g2, 0]).reshape(g, g)  # row = y, column = x
        self.var = _np(team.sigma2[:g2]).clip(min=0.0).reshape(g, g)
        self.risk = _np(team.mu[:g2, 1]).reshape(g, g)
        self.truth = _np(st.grid_truth[i]).reshape(g, g)
        self.region = self.mu + cfg.interest_beta * np.sqrt(self.var) >= cfg.interest_threshold
        nodes = _np(st.roadmap.nodes[i])
        pos = _np(base.agent_positions()[i])
        moving = (st.edge_len[i] > 0).tolist()
        self.paths = []
        for a in range(base.n_agents):
            path = nodes[st.traj[i, a, : int(st.traj_len[i, a])].cpu().numpy()]
            if moving[a]:
                path = np.concatenate([path, pos[a : a + 1]])
            self.paths.append(path)
        self.pos = pos
        self.trapped = st.trapped[i].cpu().numpy()
        n = int(st.meas_count[i])
        self.meas = _np(st.meas_x[i, :n])
        self.meas_agent = st.meas_agent[i, :n].cpu().numpy()
        valid = st.world.interest_valid[i]
        self.evidence = _np(st.world.evidence[i][valid])
        self.found = st.evidence_found[i][valid].cpu().numpy()
        trap = (st.node_risk[i] >= cfg.trap_threshold) & st.roadmap.node_valid[i]
        self.traps = nodes[trap.cpu().numpy()] if cfg.risk_enabled else nodes[:0]
        self.aoi = (_np(st.world.aoi_low[i]), _np(st.world.aoi_high[i]))
        self.intent_mean = _np(st.intent_mean[i])
        self.intent_cov = _np(st.intent_cov[i])
        self.intent_valid = st.intent_valid[i].cpu().numpy()
        self.trace = float(st.trace[i])
        self.rmse = float(np.sqrt(((self.mu - self.truth) ** 2).mean()))
        self.step = int(st.steps[i])
        self.time = float(st.time[i])
        self.used = float(st.budget_used[i])
        self.pool = float(st.team_budget[i])


def _intent_density(snap: _Snapshot) -> np.ndarray | None:
    """Sum of the valid intent Gaussians' densities on a ``_INTENT_RES^2`` grid, or None."""
    if not snap.intent_valid.any():
        return None
    lin = np.linspace(0.0, 1.0, _INTENT_RES)
    xx, yy = np.meshgrid(lin, lin)  # row = y
    total = np.zeros_like(xx)
    for mean, cov in zip(snap.intent_mean[snap.intent_valid],
                         snap.intent_cov[snap.intent_valid]):
        a, b, c = cov[0, 0], cov[0, 1], cov[1, 1]
        det = max(a * c - b * b, np.finfo(float).tiny)
        dx, dy = xx - mean[0], yy - mean[1]
        quad = (c * dx * dx - 2 * b * dx * dy + a * dy * dy) / det
        total += np.exp(-0.5 * quad) / (2 * math.pi * math.sqrt(det))
    return total


class _Painter:
    """One figure whose artists are built once and updated per frame (fast animations)."""

    def __init__(self, base: MAIPPEnv, dpi: float, blit: bool = False) -> None:
        cfg = base.config
        self.blit, self._background = blit, None
        self.cfg, self.m = cfg, base.n_agents
        fig = Figure(figsize=_FIGSIZE, dpi=dpi)
        FigureCanvasAgg(fig)
        self.fig = fig
        fig.subplots_adjust(left=0.03, right=0.96, bottom=0.09, top=0.9, wspace=0.28,
                            hspace=0.22)
        axes = fig.subplots(2, 3).ravel()
        self.axes = axes
        h = 0.5 / (cfg.grid_size - 1)  # grid values sit at the pixel centres
        extent = (-h, 1 + h, -h, 1 + h)
        zero = np.zeros((cfg.grid_size, cfg.grid_size))
        sd_max = math.sqrt(cfg.prior_variance)
        specs = [  # (cmap, vmin, vmax, colourbar label)
            ("viridis", 0.0, 1.0, "mean"),
            ("viridis", 0.0, 1.0, "signal"),
            ("Reds", 0.0, 1.0, "risk mean"),
            ("magma", 0.0, sd_max, "std"),
            (_REGION_CMAP, 0.0, 1.0, ""),
            ("Purples", 0.0, 1.0, "density / max"),
        ]
        self.images = []
        for ax, title, (cmap, lo, hi, label) in zip(axes, _TITLES, specs):
            data = zero if ax is not axes[5] else np.zeros((_INTENT_RES, _INTENT_RES))
            im = ax.imshow(data, origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi,
                           interpolation="nearest")
            self.images.append(im)
            ax.set_title(title, fontsize=10)
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7, length=2)
            cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
            cb.ax.tick_params(labelsize=7, length=2)
            cb.set_label(label, fontsize=7)
            if cmap is _REGION_CMAP:
                cb.set_ticks([0.25, 0.75], labels=["out", "in"])
        axes[4].set_title(
            f"(e) $X_I$: $\\mu + {cfg.interest_beta:g}\\sigma \\geq {cfg.interest_threshold:g}$",
            fontsize=10)
        self.region_text = axes[4].text(0.02, 0.02, "", transform=axes[4].transAxes, fontsize=8,
                                        va="bottom", bbox=dict(fc="white", alpha=0.8, lw=0))
        self.intent_text = axes[5].text(0.5, 0.5, "no intents", transform=axes[5].transAxes,
                                        ha="center", va="center", fontsize=11, color="0.3")
        if not cfg.risk_enabled:
            axes[2].text(0.5, 0.5, "risk off", transform=axes[2].transAxes, ha="center",
                         va="center", fontsize=11, color="0.3")
        colours = [AGENT_COLOURS[a % len(AGENT_COLOURS)] for a in range(self.m)]
        self.colours = np.array(colours)
        halo = [patheffects.Stroke(linewidth=3.5, foreground="white"), patheffects.Normal()]
        # (a): trajectories and measurements
        self.paths = [axes[0].plot([], [], "-", color=c, lw=1.8, path_effects=halo, zorder=3)[0]
                      for c in colours]
        self.meas = [ax.scatter(np.empty(0), np.empty(0), s=9, c="w", edgecolors="k",
                                linewidths=0.3, zorder=4) for ax in (axes[0], axes[3])]
        # Evidence on (a), (b), (e): filled when found, hollow when not.
        self.evidence = [ax.scatter(np.empty(0), np.empty(0), s=90, marker="*",
                                    linewidths=1.0, zorder=5) for ax in (axes[0], axes[1],
                                                                         axes[4])]
        self.traps = axes[2].scatter(np.empty(0), np.empty(0), s=22, marker="x", c="k",
                                     linewidths=1.0, zorder=4)
        # Agents on every panel but the ground truth.
        self.agents, self.crosses = [], []
        for ax in (axes[0], axes[2], axes[3], axes[4], axes[5]):
            self.agents.append(ax.scatter(np.empty(0), np.empty(0), s=70, edgecolors="k",
                                          linewidths=1.0, zorder=6))
            self.crosses.append(ax.scatter(np.empty(0), np.empty(0), s=110, marker="X",
                                           c="k", zorder=7))
        self.labels = [axes[0].text(0, 0, str(a), fontsize=6, ha="center", va="center",
                                    color="white", zorder=8, fontweight="bold")
                       for a in range(self.m)]
        self.intent_means = axes[5].scatter(np.empty(0), np.empty(0), s=60, marker="P",
                                            edgecolors="k", linewidths=0.6, zorder=5)
        if cfg.aoi_enabled:
            for ax, colour in ((axes[0], "w"), (axes[1], "w"), (axes[4], "k")):
                ax.add_patch(Rectangle((0, 0), 1, 1, fill=False, ec=colour, lw=1.4, ls="--",
                                       zorder=4, gid="aoi"))
        self.aoi = [p for ax in axes for p in ax.patches if p.get_gid() == "aoi"]
        handles = [Line2D([], [], color=c, lw=2, marker="o", mec="k", label=f"agent {a}")
                   for a, c in enumerate(colours)]
        handles += [
            Line2D([], [], ls="", marker="o", mfc="w", mec="k", ms=4, label="measurement"),
            Line2D([], [], ls="", marker="*", mfc=_EVIDENCE, mec=_EVIDENCE, ms=10,
                   label="evidence found"),
            Line2D([], [], ls="", marker="*", mfc="none", mec=_EVIDENCE, ms=10,
                   label="evidence not found"),
        ]
        if cfg.risk_enabled:
            handles.append(Line2D([], [], ls="", marker="x", color="k", label="trap node"))
        if cfg.aoi_enabled:
            handles.append(Line2D([], [], ls="--", color="k", label="AOI"))
        fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 9), fontsize=8,
                   frameon=False, handlelength=1.6, columnspacing=1.2)
        self.suptitle = fig.suptitle("", fontsize=11)
        # What changes from frame to frame, in drawing order. With ``blit`` the rest (axes,
        # ticks, colour bars, legend) is drawn once and restored, the bulk of the cost.
        dynamic = [*self.images, *self.aoi, *self.paths, *self.meas, *self.evidence,
                   self.traps, self.intent_means, *self.agents, *self.crosses, *self.labels,
                   self.region_text, self.intent_text]
        # Spines are static but drawn over the images, as a full draw does.
        spines = [sp for ax in axes for sp in ax.spines.values()]
        if blit:
            for artist in [*dynamic, *spines, self.suptitle]:
                artist.set_animated(True)
        self.dynamic = sorted(dynamic + spines, key=lambda a: a.get_zorder()) + [self.suptitle]

    def update(self, snap: _Snapshot) -> Figure:
        self.images[0].set_data(snap.mu)
        self.images[1].set_data(snap.truth)
        self.images[2].set_data(snap.risk)
        self.images[3].set_data(np.sqrt(snap.var))
        self.images[4].set_data(snap.region.astype(float))
        density = _intent_density(snap)
        self.images[5].set_data(np.zeros((_INTENT_RES, _INTENT_RES)) if density is None
                                else density / density.max())
        self.intent_text.set_visible(density is None)
        self.intent_means.set_offsets(snap.intent_mean[snap.intent_valid])
        self.intent_means.set_facecolors(self.colours[snap.intent_valid])
        self.region_text.set_text(f"{int(snap.region.sum())} / {snap.region.size} cells")
        for line, path in zip(self.paths, snap.paths):
            line.set_data(path[:, 0], path[:, 1])
        face = self.colours[snap.meas_agent % len(self.colours)] if len(snap.meas) else "w"
        for sc in self.meas:
            sc.set_offsets(snap.meas)
            sc.set_facecolors(face)
        face = np.array([_EVIDENCE if f else "none" for f in snap.found])
        for sc in self.evidence:
            sc.set_offsets(snap.evidence)
            sc.set_facecolors(face)
            sc.set_edgecolors(_EVIDENCE)
        self.traps.set_offsets(snap.traps)
        for sc in self.agents:
            sc.set_offsets(snap.pos)
            sc.set_facecolors(self.colours)
        for sc in self.crosses:
            sc.set_offsets(snap.pos[snap.trapped])
        for text, p in zip(self.labels, snap.pos):
            text.set_position(p)
        lo, hi = snap.aoi
        for patch in self.aoi:
            patch.set_bounds(lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1])
        found, total = int(snap.found.sum()), len(snap.found)
        self.suptitle.set_text(
            f"step {snap.step}   time {snap.time:.2f}   budget used {snap.used:.2f} / "
            f"{snap.pool:g}   Tr(P) {snap.trace:.1f}   RMSE {snap.rmse:.3f}   "
            f"evidence {found} / {total}   trapped {int(snap.trapped.sum())}")
        return self.fig

    def palette(self) -> np.ndarray:
        """``[C, 3]`` uint8 (C < 256): the colours a frame is made of, for GIF frames:
        samples of each colour map, the agents' colours, evidence red and a grey ramp."""
        ramps = [im.get_cmap()(np.linspace(0, 1, n))[:, :3]
                 for im, n in zip(self.images, (32, 0, 24, 32, 2, 16))]
        named = np.array([to_rgb(c) for c in (*self.colours, _EVIDENCE)])
        pale = 0.5 * named + 0.5  # their blends with white (halos, antialiasing)
        grey = np.linspace(0, 1, 24)[:, None].repeat(3, 1)
        rgb = np.concatenate([*ramps, named, pale, grey])
        return np.unique((rgb * 255).round().astype(np.uint8), axis=0)

    def rgb(self) -> np.ndarray:
        canvas = self.fig.canvas
        if not self.blit:
            canvas.draw()
        else:
            if self._background is None:
                canvas.draw()  # animated artists are left out: this is the background
                self._background = canvas.copy_from_bbox(self.fig.bbox)
            canvas.restore_region(self._background)
            for artist in self.dynamic:
                if artist.get_visible():
                    self.fig.draw_artist(artist)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()


# ====================================================================== public API
def draw(env: Any, index: int = 0, dpi: float = 100) -> Figure:
    """The Figure-3 panels of env ``index`` at its current step, as a new ``Figure``
    (Agg canvas attached: ``fig.savefig(...)`` works headless; nothing touches pyplot)."""
    base = _unwrap(env)
    return _Painter(base, dpi).update(_Snapshot(base, index))


def render(env: Any, index: int = 0, dpi: float = 80) -> np.ndarray:
    """RGB picture of env ``index`` now, ``[H, W, 3]`` uint8: this task's ``env.render()``
    (``H, W = 8.4 dpi, 12 dpi``; 672 x 960 at the default ``dpi=80``).

    The figure of each (env, dpi) is kept (weakly, it goes with the env) and only its
    changing parts are redrawn, so rendering every step of an episode is cheap."""
    base = _unwrap(env)
    painters = _PAINTERS.setdefault(base, {})
    painter = painters.get(dpi)
    if painter is None:
        painter = painters[dpi] = _Painter(base, dpi, blit=True)
    painter.update(_Snapshot(base, index))
    return painter.rgb()


def save_episode(
    env: Any,
    path_prefix: str | Path,
    index: int = 0,
    policy: Callable[[TensorDictBase], TensorDictBase] | None = None,
    max_steps: int | None = None,
    fps: float = 6.0,
    dpi: float = 50,
    png_dpi: float = 100,
    tensordict: TensorDictBase | None = None,
) -> tuple[Path, Path]:
    """Play env ``index``'s episode and write ``<prefix>.png`` and ``<prefix>.gif``.

    Args:
        env: a :class:`MAIPPEnv` or a TorchRL ``TransformedEnv`` around one; every env of
            the batch steps, the pictures show env ``index``.
        path_prefix: output path without suffix (``.png`` and ``.gif`` are appended; parent
            folders are created).
        policy: ``policy(td) -> td`` writing ``("agents", "action")`` (e.g. a
            :class:`~maipp_bench.algos.base.PlannerPolicy`, or a TorchRL module); default
            random masked actions (``env.rand_action``).
        max_steps: at most this many steps (default: until env ``index`` is done; the
            episode is truncated at ``config.max_steps`` anyway).
        fps: GIF frame rate (the final frame is held for 2 s).
        dpi: GIF frame resolution (50: 600 x 420 pixels).
        png_dpi: resolution of the final-state PNG.
        tensordict: continue from this root tensordict (the last ``td["next"]``) instead of
            resetting.

    Returns:
        ``(png_path, gif_path)``. One frame per step, plus the first (after reset).
    """
    from PIL import Image

    base = _unwrap(env)
    prefix = Path(path_prefix)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    td = env.reset() if tensordict is None else tensordict
    limit = base.config.max_steps if max_steps is None else int(max_steps)
    painter = _Painter(base, dpi, blit=True)
    painter.update(_Snapshot(base, index))
    frames = [painter.rgb()]
    for _ in range(limit):
        if bool(td.get("done")[index].any()):
            break
        td = policy(td) if policy is not None else env.rand_action(td)
        td = env.step(td).get("next")
        painter.update(_Snapshot(base, index))
        frames.append(painter.rgb())
    png_path, gif_path = (prefix.parent / f"{prefix.name}.{ext}" for ext in ("png", "gif"))
    draw(base, index, dpi=png_dpi).savefig(png_path)
    # One fixed palette for every frame, no dithering, unchanged pixels transparent
    # (optimize=True): only what a step changed is stored, so GIFs stay small.
    pal = Image.new("P", (1, 1))
    pal.putpalette(painter.palette().ravel().tolist())
    images = [Image.fromarray(f).quantize(palette=pal, dither=Image.Dither.NONE)
              for f in frames]
    durations = [round(1000 / fps)] * (len(images) - 1) + [2000]
    images[0].save(gif_path, save_all=True, append_images=images[1:], duration=durations,
                   loop=0, optimize=True)
    return png_path, gif_path
