"""Training throughput of ``python -m maipp_bench.train``: where an update's time goes.

Times, for the configured algorithm and env, the three phases of an update, over a few
updates after one warm-up update:

* collection (TorchRL ``Collector`` + ``TeamPolicy``): env frames/s and decisions/s;
* decisions + GAE (:func:`maipp_bench.algos.decisions.decision_batch`);
* learning (``epochs`` passes of minibatches through the loss, backward, Adam): decision
  rows per second through forward + backward.

``--card CARD.json`` instead reports the throughput of a finished run from its checkpoint
card (the wall time of every update is in its curve), or from a run folder or its
``curve.jsonl`` (with an exported snapshot's card, also ``run_continued_to``: the updates
its run made past the snapshot); ``--split U`` also reports updates 1..U and U+1.. apart (e.g. a run
resumed with other code at update U), and ``--split stages`` splits wherever the frames an
update change (train_2h.sh's stage 1 collects half of stage 2's: its last update is found,
not typed).

``--profile`` runs the timed updates under ``cProfile`` and adds the seconds and calls
per update of :data:`PHASES` (collection, teammates' intents and their parts, env steps,
backward passes).

``--launches`` (CUDA) runs one more collection after the timed updates, under
``torch.profiler``, and adds what it asked of the GPU per env step: kernel launches,
``cudaMemcpyAsync`` calls, synchronize calls and the kernels' device time, beside its
wall time under the profiler (which slows the host, not the kernels): a step whose device
time is a small part even of the unprofiled step's wall time (the timed updates'
collection, over the same number of steps) is bound by the host.

``--ratio BASE.json OTHER.json`` prints how much faster OTHER ran than BASE (two
``--out`` files measured side by side), per whole update and per phase.

Usage (Hydra overrides as for training):
    python benchmarks/train_throughput.py algo=ours --updates 3
    python benchmarks/train_throughput.py --card maipp_bench/checkpoints/ours.json --split 70
    python benchmarks/train_throughput.py --card docs/cards/PREFIX_stages12.jsonl --split stages
    python benchmarks/train_throughput.py algo=mappo n_envs=16 device=cuda --out t.json
    python benchmarks/train_throughput.py --ratio float32.json bf16.json
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import time
from pathlib import Path
from typing import Any

import torch
from bench_timing import cuda_counts, profiled_seconds
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from torch.profiler import ProfilerActivity, profile

import maipp_bench.train as train_mod
from maipp_bench.algos import rollouts
from maipp_bench.algos.ppo import build_learner
from maipp_bench.allocator import keep_freed_memory
from maipp_bench.curves import read_curve
from maipp_bench.envs.config import MAIPPConfig
from maipp_bench.hardware import machine_name

# label -> (file suffix, function name): where a timed update goes (--profile)
PHASES = {
    "collection (Collector.next)": ("collectors/_single.py", "next"),
    "  teammates' TI intents (fantasy_rollouts)": ("rollouts.py", "fantasy_rollouts"),
    "    network passes (AttentionPolicyNet.forward)": ("attention.py", "forward"),
    "      encoder (encode)": ("attention.py", "encode"),
    "        last layer's row attention (attend_rows)": ("attention.py", "attend_rows"),
    "  GP updates, the intents' fantasy ones and the env's (GPBelief.add)": ("belief.py",
                                                                             "add"),
    "  env steps (MAIPPEnv._step)": ("maipp_env.py", "_step"),
    "learning's backward passes (torch.autograd.backward)": ("torch/autograd/__init__.py",
                                                             "backward"),
}


def card_segment(curve: list[dict], start: int, stop: int) -> dict:
    """Throughput of updates ``start + 1 .. stop`` of a card's curve (cumulative counters)."""
    before = curve[start - 1] if start else {"frames": 0, "wall_s": 0.0}
    rows = curve[start:stop]
    frames, wall = rows[-1]["frames"] - before["frames"], rows[-1]["wall_s"] - before["wall_s"]
    decisions = sum(r["decisions"] for r in rows)
    return {"updates": f"{start + 1}-{stop}", "frames": frames, "decisions": decisions,
            "wall_s": wall, "frames_per_s": frames / wall,
            "decisions_per_s": decisions / wall}


def stage_cuts(curve: list[dict]) -> list[int]:
    """The updates after which the frames an update change (a card's cumulative counter):
    the last update of each stage but the last."""
    frames = [0, *(r["frames"] for r in curve)]
    per_update = [b - a for a, b in zip(frames, frames[1:])]
    return [i for i in range(1, len(per_update)) if per_update[i] != per_update[i - 1]]


def split_points(spec: list[str], curve: list[dict]) -> list[int]:
    """``--split``'s update numbers, or with ``stages`` :func:`stage_cuts`; a bad
    ``spec`` is a :class:`ValueError` that names it."""
    if spec == ["stages"]:
        return stage_cuts(curve)
    try:
        cuts = [int(u) for u in spec]
    except ValueError:
        raise ValueError(f"--split takes update numbers or 'stages', got {spec}") from None
    if cuts != sorted(set(cuts)) or any(not 0 < u < len(curve) for u in cuts):
        raise ValueError(f"--split needs increasing updates in 1..{len(curve) - 1}, "
                         f"got {cuts}")
    return cuts


# speed fields of an --out file; seconds_per_update is a time, the others rates
SPEEDS = ("seconds_per_update", "collect_frames_per_s", "learn_rows_per_s")


def speedups(base: dict, other: dict) -> dict[str, float]:
    """How many times faster ``other`` ran than ``base`` in each of :data:`SPEEDS`."""
    return {k: base[k] / other[k] if k == "seconds_per_update" else other[k] / base[k]
            for k in SPEEDS}


def collection_launches(collector: Any) -> dict[str, float]:
    """What one collection asks of the GPU per env step under ``torch.profiler``
    (:func:`bench_timing.cuda_counts`), and its wall ms per step under the profiler, from
    its first call to the end of its kernels (the profiler's start-up and processing
    left out)."""
    torch.cuda.synchronize()  # the previous update's kernels are neither timed nor counted
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as tp:
        t0 = time.perf_counter()
        batch = collector.next()
        torch.cuda.synchronize()
        wall = time.perf_counter() - t0
    counts = cuda_counts(tp.key_averages()) | {"profiled_wall_ms": 1000 * wall}
    steps = batch.shape[-1]  # env steps of the collection: the batch is [n_envs, steps]
    return {f"{k}_per_step": v / steps for k, v in counts.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*")
    p.add_argument("--updates", type=int, default=3)
    p.add_argument("--out")
    p.add_argument("--card", help="report a finished run's throughput from its card")
    p.add_argument("--every-rollout", action="store_true",
                   help="run the network on every TI rollout, not once per distinct path "
                        "(the reference for benchmarks/ti_distinct_paths.py's speed-up)")
    p.add_argument("--split", nargs="*", default=[],
                   help="with --card: also report the updates between these update numbers "
                        "('stages': where the frames an update change)")
    p.add_argument("--profile", action="store_true",
                   help="cProfile the timed updates: seconds and calls of PHASES (the "
                        "profiler's overhead slows them, so their speeds are not comparable)")
    p.add_argument("--launches", action="store_true",
                   help="CUDA: profile one more collection, after the timed updates, with "
                        "torch.profiler (kernel launches, copies, syncs, device time per "
                        "env step)")
    p.add_argument("--ratio", nargs=2, metavar=("BASE", "OTHER"),
                   help="two --out files: how much faster OTHER ran than BASE")
    args = p.parse_args()
    if args.ratio:
        base, other = (json.loads(Path(f).read_text()) for f in args.ratio)
        print(json.dumps({"base": args.ratio[0], "other": args.ratio[1],
                          "speedup": speedups(base, other)}, indent=1))
        return
    if args.card:
        # A card's own curve (read_curve would shift a fine-tune's frames by its init's,
        # which card_segment must not count), else a run folder or its curve.jsonl.
        card = json.loads(Path(args.card).read_text()) if args.card.endswith(".json") else {}
        curve = card["curve"] if card else read_curve(args.card)
        try:
            split = split_points(args.split, curve) if args.split else []
        except ValueError as err:
            p.error(str(err))  # status 2, as every other bad argument
        cuts = [0, *split, len(curve)]
        report = [card_segment(curve, a, b) for a, b in zip(cuts, cuts[1:])]
        if split:
            report.append(card_segment(curve, 0, len(curve)))
        # seconds to one decimal for reading; callers (draw_section) round the exact figure
        out = {"card": args.card,
               "segments": [seg | {"wall_s": round(seg["wall_s"], 1)} for seg in report]}
        if "run_continued_to" in card:  # an exported snapshot: the updates its run made
            out["run_continued_to"] = card["run_continued_to"]
        print(json.dumps(out, indent=1))
        return
    with initialize_config_module("maipp_bench.conf", version_base=None):
        cfg = compose("train", overrides=args.overrides)
    if args.launches and torch.device(cfg.device).type != "cuda":
        p.error("--launches counts CUDA kernel launches: add device=cuda")
    keep_freed_memory()  # as the train CLI does
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    env_cfg = MAIPPConfig.from_dict(OmegaConf.to_container(cfg.env))
    learner = build_learner(cfg.algo, env_cfg.node_encoding_dim, env_cfg.interest_threshold,
                            cfg.device)
    if cfg.init:  # a fine-tune's throughput: a trained policy samples (and repeats) differently
        train_mod.init_weights(learner, cfg.init, cfg.algo, env_cfg.interest_threshold)
    optim = torch.optim.Adam(learner.parameters(), lr=cfg.algo.lr)
    _, collector, buffer = train_mod.make_collection(cfg, env_cfg, learner)
    times = {"collect": 0.0, "decisions": 0.0, "learn": 0.0}
    frames = decisions = passes = 0
    prof = cProfile.Profile()
    with rollouts.path_merging(not args.every_rollout):
        for update in range(args.updates + 1):
            if update == 1 and args.profile:  # the first update warms up
                prof.enable()
            t0 = time.perf_counter()
            batch = collector.next()
            t1 = time.perf_counter()
            rows = train_mod.collected_decisions(learner, batch, cfg.algo)
            t2 = time.perf_counter()
            train_mod.learn(learner, optim, buffer, rows, cfg.algo)
            passes += cfg.algo.epochs * rows.numel() if update else 0
            t3 = time.perf_counter()
            if update:  # the first update warms up
                times["collect"] += t1 - t0
                times["decisions"] += t2 - t1
                times["learn"] += t3 - t2
                frames += batch.numel()
                decisions += rows.numel()
    prof.disable()
    # One more collection, after the timed updates: its time is not theirs.
    launches = collection_launches(collector) if args.launches else None
    collector.shutdown()
    total = sum(times.values())
    result = {
        "overrides": args.overrides, "updates": args.updates,
        "machine": f"{machine_name()}, {torch.get_num_threads()} torch thread(s), "
                   f"device {cfg.device}",
        "load_avg": os.getloadavg(),
        "seconds_per_update": total / args.updates,
        "share": {k: v / total for k, v in times.items()},
        "frames_per_s": frames / total,
        "decisions_per_s": decisions / total,
        "collect_frames_per_s": frames / times["collect"],
        "learn_rows_per_s": passes / times["learn"],
    }
    if launches is not None:
        result["collection_launches"] = launches
    if args.profile:  # seconds per timed update
        result["profile"] = {label: {"seconds": s / args.updates, "calls": n / args.updates}
                             for label, (s, n) in profiled_seconds(prof, PHASES).items()}
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
