"""Checkpoints of learned methods: training state for resuming, and shipped policies.

A training checkpoint holds everything a resumed run needs to continue the same curve
(weights, optimiser, schedule, update counter, the curve so far, the full config). A
*policy* file is its slim export (network weights and the configs that define them);
the shipped ones live in ``maipp_bench/checkpoints/<name>.pt`` with a JSON card beside.
Writes are atomic (temporary file + rename), so a run killed mid-write keeps the
previous checkpoint intact.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch

from maipp_bench.algos.modules import AttentionCore

SHIPPED_DIR = Path(__file__).resolve().parent.parent / "checkpoints"
FORMAT = 1


def atomic_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to a temporary file, then rename over ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def resolve(checkpoint: str | Path) -> Path:
    """A path, or the name of a shipped checkpoint (``"ours"`` -> checkpoints/ours.pt)."""
    path = Path(checkpoint)
    if path.suffix != ".pt" and not path.exists():
        path = SHIPPED_DIR / f"{checkpoint}.pt"
    if not path.exists():
        raise FileNotFoundError(
            f"checkpoint {str(checkpoint)!r} not found (looked at {path}); train one with "
            "`python -m maipp_bench.train algo=<name>` or pass --checkpoint METHOD=PATH"
        )
    return path


def _namespace(d: dict[str, Any]) -> SimpleNamespace:
    return SimpleNamespace(**{k: _namespace(v) if isinstance(v, dict) else v
                              for k, v in d.items()})


def load_core(checkpoint: str | Path, device: str | torch.device = "cpu"
              ) -> tuple[AttentionCore, dict[str, Any]]:
    """The policy network of a training checkpoint or policy file, in eval mode."""
    from maipp_bench.algos.ppo import net_config

    payload = torch.load(resolve(checkpoint), map_location=device, weights_only=False)
    if payload.get("format") != FORMAT:
        raise ValueError(f"{checkpoint}: unknown checkpoint format {payload.get('format')!r}")
    algo = _namespace(payload["algo"])
    env = payload["env"]
    core = AttentionCore(algo.feature_set, net_config(algo, env["node_encoding_dim"]),
                         env["interest_threshold"]).to(device)
    core.load_state_dict(payload["core"])
    return core.eval(), payload


# What a policy file keeps of a training checkpoint: the network, the configs that define
# it, and where it came from (no optimiser, schedule or loss state).
POLICY_KEYS = ("format", "algo", "env", "core", "update", "frames", "wall_s", "config",
               "commands")
OPTIONAL_KEYS = ("commit", "init")  # recorded since 2026-11-25


def slim(state: dict[str, Any], *extra: str) -> dict[str, Any]:
    """The policy-file part of a training checkpoint's ``state`` (plus ``extra`` keys)."""
    return {k: state[k] for k in (*POLICY_KEYS, *extra)} | {
        k: state[k] for k in OPTIONAL_KEYS if k in state}


def average_policies(paths: list[Path], weights: list[float] | None = None
                     ) -> dict[str, Any]:
    """The payload of one checkpoint or policy file; of several (snapshots of one run),
    the last one's with its network weights replaced by the uniform average of all of
    theirs, or their sum with ``weights`` (``averaged_updates``: the updates averaged). A
    plain average of weights along one run smooths the update-to-update wander of its
    policy; networks of different shape or inputs are a ValueError."""
    payloads = [torch.load(p, map_location="cpu", weights_only=False) for p in paths]
    if len(payloads) == 1:
        return payloads[0]
    first = payloads[0]

    def network(payload: dict[str, Any]) -> tuple[Any, ...]:
        return (payload["algo"]["feature_set"], payload["env"]["interest_threshold"],
                {k: tuple(v.shape) for k, v in payload["core"].items()})

    for path, payload in zip(paths[1:], payloads[1:], strict=True):
        if network(payload) != network(first):
            raise ValueError(f"cannot average {paths[0]} and {path}: different networks")
    if weights is not None and len(weights) != len(payloads):
        raise ValueError(f"{len(weights)} weights for {len(payloads)} networks")

    def mix(key: str) -> torch.Tensor:
        tensors = [p["core"][key] for p in payloads]
        if weights is None:
            return torch.stack(tensors).mean(0)
        return sum(w * t for w, t in zip(weights, tensors, strict=True))

    core = {k: mix(k) if v.is_floating_point() else v
            for k, v in payloads[-1]["core"].items()}
    return payloads[-1] | {"core": core, "averaged_updates": [p["update"] for p in payloads]}


def export_policy(checkpoint: str | Path, out: str | Path) -> None:
    """Write the slim policy file (weights + configs + curve) of a training checkpoint."""
    payload = torch.load(checkpoint, map_location="cpu", weights_only=False)
    atomic_save(slim(payload, "curve"), out)
