"""A random policy that reads the mask from the data, for any wrapper or collector.

The bare env's own random actions respect the live mask because its action spec carries
it; wrappers that copy the spec (``SerialEnv``, ``ParallelEnv``, a ``Collector`` given no
policy) lose it. This module needs nothing but ``("agents", "action_mask")``.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase


class MaskedRandomPolicy(TensorDictModuleBase):
    """Uniform over each agent's allowed slots: writes ``("agents", "action")``.

    Args:
        generator: the ``torch.Generator`` to draw from (default: torch's global one), so a
            seeded collector run reproduces.
    """

    in_keys = [("agents", "action_mask")]
    out_keys = [("agents", "action")]

    def __init__(self, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.generator = generator

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        mask = tensordict.get(("agents", "action_mask"))
        if not bool(mask.any(-1).all()):
            raise ValueError("every agent needs at least one allowed slot in its "
                             "('agents', 'action_mask')")
        g = self.generator  # may live on another device than the data (a CPU generator)
        u = torch.rand(mask.shape, generator=g, device=g.device if g is not None else mask.device)
        u = u.to(mask.device)
        tensordict.set(("agents", "action"), torch.where(mask, u, -1.0).argmax(-1))
        return tensordict
