"""MKL's CPU-independent kernels for protocol runs, so that boards reproduce on other CPUs.

MKL, torch's BLAS on x86, picks the fastest code path for the CPU at hand, and the paths
round float products differently. The TI methods score their rollouts on float32 fantasy
beliefs, where such a last-bit difference can flip a decision (a cell sitting at the
interest threshold) and change the episode from there on: an Intel Xeon with MKL's default
kernels played one episode of 240 of the ``risk_aware`` TI rows' first trial, and one
``agents10`` spot check, differently from the AMD EPYC boxes that computed the boards.
MKL's conditional numerical reproducibility mode ``COMPATIBLE`` runs one code path on every
x86 CPU; under it that Intel Xeon plays those episodes as the AMD EPYC boards do
(docs/protocol.md, "Another CPU"). ``python -m maipp_bench.eval`` pins it, and every board
records the mode its rows ran under (``machine.mkl_kernels``).

MKL fixes its code path at its first call, and importing tensordict already makes one: pin
before importing it (this module imports only torch, and only inside its functions).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

# mkl_service.h: the MKL_CBWR_BRANCH setting and two of its values.
_CBWR_BRANCH = 1
_CBWR_BRANCH_OFF = 1  # nothing set: MKL's default, the CPU's fastest path
_CBWR_COMPATIBLE = 3
ENV = "MKL_CBWR"
PINNED = ("COMPATIBLE", "unavailable")  # the modes a protocol run may compute rows under


def _mkl() -> ctypes.CDLL | None:
    """torch's (statically linked) MKL service functions, or None for a build without MKL."""
    import torch

    lib = Path(torch.__file__).parent / "lib" / "libtorch_cpu.so"
    if not torch.backends.mkl.is_available() or not lib.is_file():
        return None
    try:
        handle = ctypes.CDLL(str(lib))
        if not (hasattr(handle, "mkl_serv_cbwr_get") and hasattr(handle, "mkl_serv_cbwr_set")):
            return None
    except OSError:
        return None
    return handle


def kernel_mode() -> str:
    """This process's MKL code path: ``"COMPATIBLE"`` (CPU-independent), ``"default"`` (the
    CPU's fastest), ``"branch <n>"`` (another ``MKL_CBWR`` value), or ``"unavailable"``
    (torch without MKL: there is no MKL path to pin)."""
    mkl = _mkl()
    if mkl is None:
        return "unavailable"
    branch = mkl.mkl_serv_cbwr_get(_CBWR_BRANCH)
    return {_CBWR_COMPATIBLE: "COMPATIBLE", _CBWR_BRANCH_OFF: "default"}.get(
        branch, f"branch {branch}")


def pin_cpu_kernels() -> str:
    """Ask for MKL's CPU-independent kernels in this process and the processes it starts
    (forked ones inherit the setting, spawned ones read ``MKL_CBWR``). Takes effect only
    before MKL's first call; returns :func:`kernel_mode` after trying."""
    os.environ[ENV] = "COMPATIBLE"
    mkl = _mkl()
    if mkl is not None and mkl.mkl_serv_cbwr_get(_CBWR_BRANCH) != _CBWR_COMPATIBLE:
        mkl.mkl_serv_cbwr_set(_CBWR_COMPATIBLE)  # fails (-8) once MKL has run: checked below
    return kernel_mode()


def require_pinned_kernels() -> str:
    """:func:`pin_cpu_kernels`, raising RuntimeError with what to do when MKL already runs
    another code path in this process (rows computed so could differ on another CPU)."""
    mode = pin_cpu_kernels()
    if mode not in PINNED:
        raise RuntimeError(
            f"MKL already runs its {mode} kernels in this process, and protocol rows "
            "computed so can differ on another CPU (docs/protocol.md, 'Another CPU'): set "
            f"{ENV}=COMPATIBLE in the environment, or call "
            "maipp_bench.kernels.pin_cpu_kernels() before importing tensordict or torchrl")
    return mode
