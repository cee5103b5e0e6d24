"""Rendering speed: ``maipp_bench.viz.render`` per frame and ``save_episode`` for a
60-step episode (docs/interop.md). Usage::

    python benchmarks/render_speed.py
"""

from __future__ import annotations

import platform
import tempfile
import time

import torch

from maipp_bench import viz
from maipp_bench.envs import MAIPPConfig, MAIPPEnv


def main() -> None:
    torch.set_num_threads(1)
    env = MAIPPEnv(MAIPPConfig(n_agents=3, budget=2.0), batch_size=[1])
    torch.manual_seed(0)
    td = env.reset()
    t0 = time.perf_counter()
    viz.render(env)
    first = time.perf_counter() - t0
    frames, t0 = 0, time.perf_counter()
    for _ in range(20):
        td = env.step(env.rand_action(td))["next"]
        viz.render(env)
        frames += 1
    per_frame = (time.perf_counter() - t0) / frames
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        viz.save_episode(env, f"{tmp}/episode", max_steps=60)
        episode = time.perf_counter() - t0
    print(f"# {platform.machine()}, torch {torch.__version__}, one thread")
    print("| what | seconds |")
    print("|---|---:|")
    print(f"| first render | {first:.2f} |")
    print(f"| later render (step + frame) | {per_frame:.3f} |")
    print(f"| save_episode, 60 steps (PNG + GIF) | {episode:.2f} |")


if __name__ == "__main__":
    main()
