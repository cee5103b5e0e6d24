"""The versioned evaluation protocol: suites, settings and the fixed seeds.

A protocol file (``v<N>.json`` beside this module) is never edited in place: its sha256
is pinned below, loading checks it, and every result row records it. Changing suites,
seeds or world laws means a new version.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from maipp_bench.envs.config import MAIPPConfig

PROTOCOL_DIR = Path(__file__).resolve().parent
# sha256 of each released protocol file: an edit in place fails loudly.
PINNED_SHA256 = {
    1: "00124f86b4938d6e94c90182b10706eb9f94075c06a882b8fa41c6f2043da20a",
}


def _value(v: Any) -> Any:
    return math.inf if v == "inf" else v


@dataclass(frozen=True)
class Setting:
    """One point of a suite's grid of axes (e.g. ``budget=2.0``)."""

    suite: str
    values: tuple[tuple[str, Any], ...]

    @property
    def key(self) -> str:
        """Stable text key, e.g. ``comm_range=0.3,budget=2.0``."""
        return ",".join(f"{k}={_fmt(v)}" for k, v in self.values)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.values)


def _fmt(v: Any) -> str:
    if isinstance(v, float) and math.isinf(v):
        return "inf"
    return repr(v) if isinstance(v, float) else str(v)


@dataclass(frozen=True)
class Suite:
    """A named family of settings evaluated on the same instances and trials."""

    name: str
    description: str
    paper_table: str | None
    env: dict[str, Any]
    axes: dict[str, tuple[Any, ...]]
    methods: tuple[str, ...]
    instance_seeds: tuple[int, ...]
    trial_seeds: tuple[int, ...]
    settings: tuple[Setting, ...] = field(default=())

    def env_config(self, setting: Setting, **overrides: Any) -> MAIPPConfig:
        """The task configuration of one setting (suite defaults, then the setting)."""
        values = {**self.env, **setting.as_dict(), **overrides}
        return MAIPPConfig.from_dict(values)

    def setting(self, key: str) -> Setting:
        """The setting with this ``key`` (e.g. ``"budget=2.0"``)."""
        for s in self.settings:
            if s.key == key:
                return s
        raise ValueError(f"unknown setting {key!r} of suite {self.name}; valid settings: "
                         f"{[s.key for s in self.settings]}")

    @property
    def n_episodes(self) -> int:
        return len(self.instance_seeds) * len(self.trial_seeds)


@dataclass(frozen=True)
class Protocol:
    """A loaded, hash-checked protocol version."""

    version: int
    sha256: str
    path: Path
    suites: dict[str, Suite]

    def suite(self, name: str) -> Suite:
        if name not in self.suites:
            raise ValueError(
                f"unknown suite {name!r}; valid suites of protocol v{self.version}: "
                f"{sorted(self.suites)}"
            )
        return self.suites[name]


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_protocol(version: int = 1) -> Protocol:
    """Load protocol ``v<version>.json`` and check it against its pinned sha256."""
    if version not in PINNED_SHA256:
        raise ValueError(f"unknown protocol version {version}; known: {sorted(PINNED_SHA256)}")
    path = PROTOCOL_DIR / f"v{version}.json"
    digest = file_sha256(path)
    if digest != PINNED_SHA256[version]:
        raise RuntimeError(
            f"protocol file {path} has sha256 {digest}, but v{version} is pinned to "
            f"{PINNED_SHA256[version]}: released protocols are never edited in place; "
            "write a new version instead"
        )
    raw = json.loads(path.read_text())
    if raw.get("version") != version:
        raise RuntimeError(f"{path} declares version {raw.get('version')}, expected {version}")
    suites = {}
    for name, spec in raw["suites"].items():
        instances = tuple(raw["instance_seeds"][: spec.get("n_instances")])
        trials = tuple(raw["trial_seeds"][: spec.get("n_trials")])
        axes = {k: tuple(_value(v) for v in vs) for k, vs in spec["axes"].items()}
        env = {k: _value(v) for k, v in spec["env"].items()}
        settings = tuple(
            Setting(name, tuple(zip(axes, combo)))
            for combo in itertools.product(*axes.values())
        )
        suites[name] = Suite(
            name=name, description=spec["description"], paper_table=spec["paper_table"],
            env=env, axes=axes, methods=tuple(spec["methods"]), instance_seeds=instances,
            trial_seeds=trials, settings=settings,
        )
    return Protocol(version=version, sha256=digest, path=path, suites=suites)


def paper_results() -> dict[str, Any]:
    """The paper's Tables 1-3 (Tr(P_f) mean / std), keyed by our method names."""
    return json.loads((PROTOCOL_DIR / "paper_results.json").read_text())
