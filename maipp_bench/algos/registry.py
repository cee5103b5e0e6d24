"""One registry of methods: a policy class registered by name + one YAML per method.

``maipp_bench/conf/method/<method>.yaml`` names the policy class, whether the method
models risk (risk-unaware methods get the pruned roadmap, as in the paper) and its
parameters. Adding a method is one module (the policy, decorated with
:func:`register_policy`) and one YAML.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

METHOD_CONF_DIR = Path(__file__).resolve().parent.parent / "conf" / "method"
POLICIES: dict[str, Callable[..., Any]] = {}


def register_policy(name: str) -> Callable[[type], type]:
    """Class decorator: make a policy class available to method YAMLs as ``policy: name``."""

    def wrap(cls: type) -> type:
        if name in POLICIES:
            raise ValueError(f"policy {name!r} registered twice")
        POLICIES[name] = cls
        return cls

    return wrap


@dataclass(frozen=True)
class MethodSpec:
    """A named, configured method as the evaluation protocol runs it."""

    name: str
    policy: str
    models_risk: bool
    learned: bool = False
    params: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    prune_roadmap: bool | None = None  # None: prune exactly when the method ignores risk

    @property
    def prunes_roadmap(self) -> bool:
        """Whether the method runs on the roadmap without nodes of true risk > 0.7: by
        default the risk-unaware ones (paper); a YAML may say otherwise, e.g. to measure the
        traps a risk-unaware policy falls into on the full roadmap."""
        return (not self.models_risk) if self.prune_roadmap is None else self.prune_roadmap

    def checkpoint(self, override: str | None = None) -> Path | None:
        """The checkpoint file a learned method runs (``override`` or its YAML's), resolved;
        None for planners. Raises FileNotFoundError with what to do when it is missing."""
        if not self.learned:
            return None
        from maipp_bench.algos.checkpoint import resolve

        return resolve(override or self.params.get("checkpoint", self.name))

    def fingerprint(self) -> str:
        """sha256 of what decides this method's actions: policy, its ``version`` (bumped
        whenever the algorithm changes), params and risk handling. Stored with every
        result row, so rows of an older algorithm are never reused or reported."""
        version = getattr(POLICIES[self.policy], "version", 1)
        spec = {"policy": self.policy, "version": version, "params": self.params,
                "models_risk": self.models_risk}
        if self.prune_roadmap is not None:
            spec["prune_roadmap"] = self.prune_roadmap
        return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()

    def build(self, env: Any, seeds: Any, **extra: Any) -> Any:
        """Instantiate the policy for a batched env and per-episode method seeds."""
        return POLICIES[self.policy](env, seeds, **{**self.params, **extra})


def _load(path: Path) -> MethodSpec:
    raw = yaml.safe_load(path.read_text()) or {}
    known = {"policy", "models_risk", "learned", "params", "description", "prune_roadmap"}
    unknown = set(raw) - known
    if unknown:
        raise ValueError(f"{path}: unknown keys {sorted(unknown)}; allowed: {sorted(known)}")
    return MethodSpec(name=path.stem, policy=raw["policy"], models_risk=bool(raw["models_risk"]),
                      learned=bool(raw.get("learned", False)), params=dict(raw.get("params") or {}),
                      description=str(raw.get("description", "")),
                      prune_roadmap=None if raw.get("prune_roadmap") is None
                      else bool(raw["prune_roadmap"]))


def method_names() -> list[str]:
    """Every method with a YAML whose policy class is registered."""
    return sorted(p.stem for p in METHOD_CONF_DIR.glob("*.yaml") if _load(p).policy in POLICIES)


def get_method(name: str) -> MethodSpec:
    """The method called ``name``; unknown names get an error listing the valid ones."""
    path = METHOD_CONF_DIR / f"{name}.yaml"
    valid = method_names()
    if not path.exists():
        raise ValueError(f"unknown method {name!r}; valid methods: {valid}")
    spec = _load(path)
    if spec.policy not in POLICIES:
        raise ValueError(
            f"method {name!r} needs policy {spec.policy!r}, which is not registered; "
            f"valid methods: {valid}"
        )
    return spec
