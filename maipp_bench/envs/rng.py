"""Counter-based random numbers: a pure function of (key, counter), batched in tensors.

Every random draw of the world (fields, roadmap, start node, sensor noise) is a hash of
integer keys, so that env ``e`` of a batch gets the same episode whatever the batch size,
on CPU or CUDA, and partial resets never disturb other envs' streams. The mixer is
SplitMix64 (Steele et al., 2014) written with int64 tensor ops (wrapping arithmetic,
logical shifts emulated with masks).
"""

from __future__ import annotations

import functools
import math
import operator

import torch


def _u64(c: int) -> int:
    """A uint64 constant as the int64 with the same bits."""
    return c - (1 << 64) if c >= (1 << 63) else c


_GOLDEN = _u64(0x9E3779B97F4A7C15)
_M1 = _u64(0xBF58476D1CE4E5B9)
_M2 = _u64(0x94D049BB133111EB)


def _shr(x: torch.Tensor, s: int) -> torch.Tensor:
    """Logical right shift of int64 bits."""
    return (x >> s) & ((1 << (64 - s)) - 1)


def mix(x: torch.Tensor) -> torch.Tensor:
    """SplitMix64 finaliser: a bijective scramble of 64-bit integers."""
    z = x + _GOLDEN
    z = (z ^ _shr(z, 30)) * _M1
    z = (z ^ _shr(z, 27)) * _M2
    return z ^ _shr(z, 31)


_MASK64 = (1 << 64) - 1


def mix_int(x: int) -> int:
    """:func:`mix` of one Python integer, as the int64 it gives (the same bits, no tensor:
    a constant tag costs no device work)."""
    if not -(1 << 63) <= x < (1 << 63):
        raise OverflowError(f"RNG tag {x} does not fit in int64")
    z = (x + _GOLDEN) & _MASK64
    z = ((z ^ (z >> 30)) * _M1) & _MASK64
    z = ((z ^ (z >> 27)) * _M2) & _MASK64
    return _u64(z ^ (z >> 31))


def derive(key: torch.Tensor, *tags: int | torch.Tensor) -> torch.Tensor:
    """A child key for each tag sequence (tags broadcast against ``key``)."""
    out = key
    for tag in tags:
        if isinstance(tag, torch.Tensor):
            out = mix(out ^ mix(tag.to(device=key.device, dtype=torch.int64)))
        else:
            out = mix(out ^ mix_int(operator.index(tag)))  # numpy integers too
    return out


def seed_key(seed: int, device: torch.device | str = "cpu") -> torch.Tensor:
    return mix(torch.tensor(seed, dtype=torch.int64, device=device))


@functools.lru_cache(maxsize=64)
def _mixed_counters(n: int, device: torch.device) -> torch.Tensor:
    """``mix(arange(n))``: the same for every draw of n numbers, so made once per device."""
    return mix(torch.arange(n, dtype=torch.int64, device=device))


def _counters(key: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    mixed = _mixed_counters(math.prod(shape), key.device).view(shape)
    return mix(key.view(*key.shape, *([1] * len(shape))) ^ mixed)


def uniform(key: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """float64 uniforms in [0, 1) of shape ``key.shape + shape``."""
    bits = _shr(_counters(key, shape), 11)
    return bits.to(torch.float64) * (2.0**-53)


def normal(key: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """float64 standard normals (Box-Muller) of shape ``key.shape + shape``."""
    u = uniform(key, (*shape, 2))
    u1 = 1.0 - u[..., 0]  # in (0, 1]: log is finite
    return torch.sqrt(-2.0 * torch.log(u1)) * torch.cos(2.0 * math.pi * u[..., 1])


def randint(key: torch.Tensor, low: int, high: int, shape: tuple[int, ...] = ()) -> torch.Tensor:
    """Integers uniform on [low, high] (inclusive), shape ``key.shape + shape``."""
    u = uniform(key, shape)
    return low + torch.floor(u * (high - low + 1)).to(torch.int64).clamp_max(high - low)
