"""MKL's CPU-independent kernels for protocol runs, so that boards reproduce on other CPUs.

MKL, torch's BLAS on x86, picks the fastest code path for the CPU at hand, and the paths
round float products differently. The TI methods score their rollouts on float32 fantasy
beliefs, where such a last-bit difference can flip a decision (a cell sitting at the
interest threshold) and change the episode from there on: an Intel Xeon with MKL's default
kernels played one episode of 240 of the ``risk_aware`` TI rows' first trial, and one
``agents10`` spot check, differently from the AMD EPYC boxes that computed the boards.
MKL's conditional numerical reproducibility mode ``COMPATIBLE`` runs one code path on every
x86 CPU; under it that Intel Xeon plays those TI episodes as the AMD EPYC boards do (a few
planner episodes still differ there, under every MKL code path: something else rounds
differently; docs/protocol.md, "Another CPU"). ``python -m maipp_bench.eval`` pins it unless
``MKL_CBWR`` asks for other kernels, and every board and stored episode records the mode
(``mkl_kernels``).

Not pinned: torch's own vectorised kernels (softmax, attention), whose width follows the
CPU (:func:`aten_capability`; AVX512 on the first two boxes measured, AVX2 on an AMD EPYC
without AVX512); boards record it too.

MKL fixes its code path at its first call, and importing tensordict already makes one: pin
before importing it (this module imports only torch, and only inside its functions).
"""

from __future__ import annotations

import ctypes
import functools
import os
import warnings
from pathlib import Path

# mkl_service.h: the MKL_CBWR_BRANCH setting and two of its values.
_CBWR_BRANCH = 1
_CBWR_BRANCH_OFF = 1  # nothing set: MKL's default, the CPU's fastest path
_CBWR_COMPATIBLE = 3
ENV = "MKL_CBWR"
PINNED = ("COMPATIBLE", "unavailable")  # the modes a protocol run may compute rows under
# torch links MKL statically into its CPU library, whose name follows the platform.
_TORCH_CPU_LIBS = ("libtorch_cpu.so", "libtorch_cpu.dylib", "torch_cpu.dll")


@functools.cache  # loaded once: eval's workers ask for the mode at every chunk
def _mkl() -> ctypes.CDLL | None:
    """torch's MKL service functions, or None where they cannot be reached."""
    import torch

    for name in _TORCH_CPU_LIBS:
        lib = Path(torch.__file__).parent / "lib" / name
        if not lib.is_file():
            continue
        try:
            handle = ctypes.CDLL(str(lib))
            get, set_ = handle.mkl_serv_cbwr_get, handle.mkl_serv_cbwr_set
        except (OSError, AttributeError):
            return None
        for fn in (get, set_):
            fn.argtypes, fn.restype = [ctypes.c_int], ctypes.c_int
        return handle
    return None


def kernel_mode() -> str:
    """This process's MKL code path: ``"COMPATIBLE"`` (CPU-independent), ``"default"`` (the
    CPU's fastest), ``"branch <n>"`` (another ``MKL_CBWR`` value), ``"unavailable"`` (torch
    without MKL: nothing to pin) or ``"unknown"`` (MKL present but its settings out of
    reach, e.g. a build linking it dynamically)."""
    import torch

    mkl = _mkl()
    if mkl is None:
        return "unknown" if torch.backends.mkl.is_available() else "unavailable"
    branch = mkl.mkl_serv_cbwr_get(_CBWR_BRANCH)
    return {_CBWR_COMPATIBLE: "COMPATIBLE", _CBWR_BRANCH_OFF: "default"}.get(
        branch, f"branch {branch}")


def aten_capability() -> str:
    """The vector width of torch's own CPU kernels here (``"AVX512"``, ``"AVX2"``, ...):
    float32 softmax and attention round differently at another width."""
    import torch

    return torch.backends.cpu.get_cpu_capability()


def chosen_elsewhere() -> str | None:
    """An ``MKL_CBWR`` the user set to other kernels than the CPU-independent ones (e.g.
    ``AUTO``: MKL's usual speed, rows that may differ on another CPU), else None."""
    asked = os.environ.get(ENV, "")
    return asked if asked and "COMPATIBLE" not in asked.upper() else None


def pin_cpu_kernels() -> str:
    """Ask for MKL's CPU-independent kernels in this process and the processes it starts
    (forked ones inherit the setting, spawned ones read ``MKL_CBWR``, set only when this
    process runs them too), unless the user chose others (:func:`chosen_elsewhere`). Takes
    effect only before MKL's first call; returns :func:`kernel_mode` after trying."""
    if chosen_elsewhere():
        return kernel_mode()
    mkl = _mkl()
    if mkl is not None and mkl.mkl_serv_cbwr_get(_CBWR_BRANCH) != _CBWR_COMPATIBLE:
        mkl.mkl_serv_cbwr_set(_CBWR_COMPATIBLE)  # after MKL's first call: refused, kept as is
    mode = kernel_mode()
    if mode in ("COMPATIBLE", "unknown"):  # unknown: the variable is all there is to set
        os.environ[ENV] = "COMPATIBLE"
    return mode


def require_pinned_kernels() -> str:
    """:func:`pin_cpu_kernels`, raising RuntimeError with what to do when MKL already runs
    another code path in this process (rows computed so could differ on another CPU);
    warning when the user chose other kernels with ``MKL_CBWR``, or when MKL's settings are
    out of reach (then ``MKL_CBWR`` is all that asks)."""
    mode = pin_cpu_kernels()
    if (asked := chosen_elsewhere()) and mode not in PINNED:
        warnings.warn(f"{ENV}={asked}: rows computed under MKL's {mode} kernels may differ on "
                      "another CPU; the board records the kernels (machine.mkl_kernels) and "
                      "stored episodes of other kernels are not mixed in (docs/protocol.md, "
                      "'Another CPU')", stacklevel=2)
    elif mode == "unknown":
        warnings.warn(f"cannot read MKL's kernel setting in this torch build; {ENV}="
                      "COMPATIBLE asks for its CPU-independent kernels only if it was set "
                      "before MKL's first call (docs/protocol.md, 'Another CPU')", stacklevel=2)
    elif mode not in PINNED:
        raise RuntimeError(
            f"MKL already runs its {mode} kernels in this process (mkl_cbwr_set refuses a "
            "change after MKL's first call), and protocol rows computed so can differ on "
            f"another CPU (docs/protocol.md, 'Another CPU'): set {ENV}=COMPATIBLE in the "
            "environment, or call maipp_bench.kernels.pin_cpu_kernels() before importing "
            "tensordict or torchrl")
    return mode
