"""Training's held-out episodes: the seeds of the worlds that model selection plays, never
the protocol's (a light module: scripts read its constants without importing training)."""

from __future__ import annotations

import argparse

HELDOUT_SEED_BASE = 2**40  # instance seeds of the held-out episodes: never the protocol's
# Set 2's trial seeds: their own range, so that an episode's method key, a hash of
# (trial, instance), is its own (equal trial and instance seeds cancel in that hash).
HELDOUT_TRIAL_BASE = 2**40 + 2**39
# Held-out episode sets. 1: every episode on one roadmap and start node with one trial seed
# (HELDOUT_SEED_BASE) for all: the runs and choices documented up to 2026-11-27. 2: episode
# i has its own trial seed (HELDOUT_TRIAL_BASE + i), so its own roadmap, start and method
# randomness, as each (instance, trial) of the protocol has: the set that ranks like it.
HELDOUT_SETS = (1, 2)


def check_heldout(heldout: int) -> int:
    """``heldout`` if it names a held-out episode set, else a ValueError listing them."""
    if heldout not in HELDOUT_SETS:
        raise ValueError(f"held-out episode set {heldout!r}; valid: {list(HELDOUT_SETS)} "
                         "(1: one shared roadmap, 2: a roadmap per episode)")
    return heldout


def heldout_seeds(first: int, episodes: int, heldout: int) -> tuple[list[int], int | list[int]]:
    """Instance seeds of held-out episodes ``first`` .. ``first + episodes - 1`` of set
    ``heldout``, and their trial seed (set 1: one for all) or seeds (set 2: one each)."""
    instances = [HELDOUT_SEED_BASE + i for i in range(first, first + episodes)]
    if check_heldout(heldout) == 1:
        return instances, HELDOUT_SEED_BASE
    return instances, [HELDOUT_TRIAL_BASE + i for i in range(first, first + episodes)]


def add_heldout_argument(parser: argparse.ArgumentParser) -> None:
    """The scripts' ``--heldout-set`` flag (default: set 2)."""
    parser.add_argument("--heldout-set", type=int, choices=HELDOUT_SETS, default=2,
                        help="training's held-out episode set: 2 draws a roadmap per episode "
                             "as the protocol does; 1 plays them all on one roadmap (the "
                             "choices and figures documented up to 2026-11-27)")
