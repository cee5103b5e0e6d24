"""Rendering (``maipp_bench.viz``) and the example scripts, on tiny configs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure
from PIL import Image
from torchrl.envs import ActionMask, TransformedEnv

from maipp_bench import viz
from maipp_bench.envs import MAIPPConfig, MAIPPEnv
from maipp_bench.envs.pettingzoo import MAIPPParallelEnv

REPO = Path(__file__).resolve().parent.parent
TINY = dict(n_agents=2, budget=0.5, n_nodes=30, k_neighbors=6, max_steps=8, aoi_enabled=True)


def _env(batch: int = 2, **overrides) -> MAIPPEnv:
    torch.manual_seed(0)
    env = MAIPPEnv(MAIPPConfig(**{**TINY, **overrides}), batch_size=[batch])
    env.set_seed(0)
    return env


def _play(env: MAIPPEnv, steps: int, policy=None):
    td = env.reset()
    for _ in range(steps):
        if bool(td.get("done").all()):
            break
        td = policy(td) if policy is not None else env.rand_action(td)
        td = env.step(td).get("next")
    return td


def test_render_is_an_rgb_picture():
    env = _env()
    _play(env, 2)
    for dpi in (40, 80):
        rgb = viz.render(env, index=1, dpi=dpi)
        assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
        assert rgb.shape[:2] == (round(8.4 * dpi), round(12 * dpi))
        assert rgb.std() > 10  # not uniform
        assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 50


def test_render_follows_the_episode_and_matches_a_full_draw():
    env = _env(batch=1)
    td = _play(env, 0)
    first = viz.render(env, dpi=40)
    td = env.step(env.rand_action(td)).get("next")
    later = viz.render(env, dpi=40)  # cached figure, only the changing parts redrawn
    assert not np.array_equal(first, later)
    fig = viz.draw(env, dpi=40)
    fig.canvas.draw()
    full = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    # Identical but for a few antialiased tick pixels at the panels' edges.
    assert (np.abs(full.astype(int) - later).sum(-1) > 0).mean() < 1e-3


def test_render_accepts_wrappers_and_leaves_pyplot_alone():
    env = _env()
    _play(env, 1)
    masked = TransformedEnv(env, ActionMask(action_key=("agents", "action"),
                                            mask_key=("agents", "action_mask")))
    assert np.array_equal(viz.render(masked, 1, dpi=40), viz.render(env, 1, dpi=40))
    pz = MAIPPParallelEnv(**TINY)
    pz.reset(seed=0)
    assert viz.render(pz, dpi=40).shape == (336, 480, 3)
    fig = viz.draw(env)
    assert isinstance(fig, Figure) and len(fig.axes) == 12  # 6 panels + 6 colour bars
    assert "matplotlib.pyplot" not in sys.modules or not __import__(
        "matplotlib.pyplot").pyplot.get_fignums()
    with pytest.raises(IndexError):
        viz.render(env, index=2)
    with pytest.raises(TypeError):
        viz.render(object())


def _intent_text_visible(fig: Figure) -> bool:
    return any(t.get_text() == "no intents" and t.get_visible()
               for ax in fig.axes for t in ax.texts)


def test_intent_panel():
    env = _env(batch=1)
    td = _play(env, 0)
    assert _intent_text_visible(viz.draw(env))
    td = env.rand_action(td)
    m = env.n_agents
    td.set(("agents", "intent", "mean"), torch.full((1, m, 2), 0.5, dtype=torch.float64))
    td.set(("agents", "intent", "cov"), 0.01 * torch.eye(2, dtype=torch.float64).expand(
        1, m, 2, 2).clone())
    env.step(td)
    assert bool(env.episode.intent_valid.any())
    fig = viz.draw(env)
    assert not _intent_text_visible(fig)
    density = fig.axes[5].images[0].get_array()
    assert float(density.max()) == pytest.approx(1.0)
    assert float(density[15, 15]) > float(density[0, 0])  # peaks at the mean (0.5, 0.5)


def test_save_episode_writes_png_and_gif(tmp_path):
    env = _env(batch=2)
    png, gif = viz.save_episode(env, tmp_path / "sub" / "ep.v1", index=1, dpi=30, png_dpi=40)
    assert png == tmp_path / "sub" / "ep.v1.png" and gif == tmp_path / "sub" / "ep.v1.gif"
    with Image.open(png) as im:
        assert im.format == "PNG" and im.size == (480, 336)
    steps = int(env.episode.steps[1])
    assert steps >= 1
    with Image.open(gif) as im:
        assert im.format == "GIF" and im.is_animated
        assert im.n_frames == steps + 1  # the state after reset, then one frame per step
        im.seek(im.n_frames - 1)
        last = np.asarray(im.convert("RGB"))
    assert last.shape == (252, 360, 3) and last.std() > 10


def test_save_episode_with_policy_and_step_limit(tmp_path):
    env = _env(batch=1, max_steps=50, budget=2.0)
    calls = []

    def policy(td):
        calls.append(1)
        return env.rand_action(td)

    _, gif = viz.save_episode(env, tmp_path / "ep", policy=policy, max_steps=3, dpi=30)
    assert len(calls) == 3
    with Image.open(gif) as im:
        assert im.n_frames == 4


@pytest.mark.parametrize("script", ["random_rollout_torchrl", "pettingzoo_loop",
                                    "render_episode"])
def test_example_runs(script, tmp_path):
    cmd = [sys.executable, str(REPO / "examples" / f"{script}.py"), "--smoke"]
    if script == "render_episode":
        cmd += ["--out", str(tmp_path)]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip()
    if script == "render_episode":
        for name in ("episode.png", "episode.gif"):
            assert (tmp_path / name).stat().st_size > 1000
