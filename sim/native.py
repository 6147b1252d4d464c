"""Fused CPU kernels for the simulator's step and the IPF reward, built on first use.

The step's claims, collisions, team reward and K-nearest observations, and the IPF reward's
small per-environment solves, are a few dozen tiny tensor operations each in torch; on the
CPU their dispatch and memory traffic cost several times the physics itself. The C source in
``sim/_native/kernels.c`` does the same work in one pass per environment. It is compiled with
the system's C compiler the first time it is needed (about a second) and cached in
``$AGV_CACHE_DIR`` (default ``~/.cache/agv-allocation``), keyed by a hash of the source, the
flags and the machine.

The torch code in :mod:`sim.core` and :mod:`sim.ipf` stays the definition and runs wherever
the kernels cannot: tensors on another device, no C compiler, or ``AGV_NATIVE=0`` in the
environment. Tests check that both paths agree.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import torch

__all__ = ["available", "library", "library_for", "disabled_reason", "pointer"]

SOURCE = Path(__file__).parent / "_native" / "kernels.c"
FLAGS = ["-O3", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno"]

_lib: ctypes.CDLL | None = None
_tried = False
_reason: str | None = None

_P, _I, _F, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_double
_SIGNATURES = {
    "agv_observe": (ctypes.c_int, [_I, _I, _I, _I, _I, _F] + [_P] * 6),
    "agv_post_step": (ctypes.c_int, [_I, _I, _I, _I, _I, _F, _F, _F, _I] + [_P] * 20),
    "agv_prepare": (ctypes.c_int64, [_I, _I] + [_P] * 5),
    "agv_spawn_pick": (None, [_I, _I, _I, _I] + [_P] * 6),
    "agv_ipf": (ctypes.c_int, [_I, _I, _I, _P, _P, _P, _I, _P, _P, _I, _P, _I, _I]
                + [_D] * 6 + [_P] * 6),
}


def pointer(tensor: torch.Tensor, dtype: torch.dtype, shape: tuple[int, ...], name: str) -> int:
    """The address of ``tensor``'s data for a C kernel, after checking that it fits.

    Parameters
    ----------
    tensor : Tensor
        The tensor the kernel reads or writes.
    dtype : torch.dtype
        The element type the C code expects (``torch.float32`` for ``float``, ``torch.int64``
        for ``int64_t``, ``torch.bool`` for ``uint8_t`` flags).
    shape : tuple of int
        The exact shape the C code indexes; ``-1`` matches any size in that place.
    name : str
        The argument's name, for the error message.

    Returns
    -------
    int
        ``tensor.data_ptr()``.

    Raises
    ------
    ValueError
        Naming ``name``, unless ``tensor`` is a C-contiguous CPU tensor of exactly ``dtype``
        and ``shape``.
    """
    if (type(tensor) is torch.Tensor and tensor.dtype is dtype and tensor.is_cpu
            and tensor.shape == shape and tensor.is_contiguous()):
        return tensor.data_ptr()
    _check(tensor, dtype, shape, name)
    return tensor.data_ptr()


def _check(tensor: object, dtype: torch.dtype, shape: tuple[int, ...], name: str) -> None:
    """The slow path of :func:`pointer`: wildcards, subclasses, and the error messages."""
    want = f"a C-contiguous CPU tensor of dtype {dtype} and shape {tuple(shape)}"
    if not isinstance(tensor, torch.Tensor):
        raise ValueError(f"{name} must be {want}, got {type(tensor).__name__}")
    got = f"dtype {tensor.dtype}, shape {tuple(tensor.shape)} on {tensor.device}"
    fits = (len(tensor.shape) == len(shape)
            and all(w == -1 or w == g for w, g in zip(shape, tensor.shape, strict=False)))
    if tensor.dtype != dtype or not fits or not tensor.is_cpu:
        raise ValueError(f"{name} must be {want}, got {got}")
    if not tensor.is_contiguous():
        raise ValueError(f"{name} must be {want}, got a non-contiguous tensor")


def _cache_dir() -> Path:
    root = os.environ.get("AGV_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "agv-allocation"


def _compiler() -> str | None:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def _build() -> ctypes.CDLL:
    cc = _compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (tried $CC, cc, gcc, clang)")
    source = SOURCE.read_bytes()
    key = hashlib.sha256(
        source + " ".join([cc, *FLAGS, platform.machine(), platform.system()]).encode()
    ).hexdigest()[:16]
    target = _cache_dir() / f"agv_kernels_{key}.so"
    if target.exists():
        try:
            lib = ctypes.CDLL(str(target))
        except OSError:  # a damaged cache entry: build it again
            lib = None
    else:
        lib = None
    if lib is None:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
        os.close(fd)
        try:
            result = subprocess.run(
                [cc, *FLAGS, str(SOURCE), "-o", tmp, "-lm"], capture_output=True, text=True
            )
            if result.returncode != 0:
                raise RuntimeError(f"{cc} failed: {result.stderr.strip()[:2000]}")
            os.replace(tmp, target)  # atomic: a concurrent build never loads a partial file
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        lib = ctypes.CDLL(str(target))
    for name, (restype, argtypes) in _SIGNATURES.items():
        fn = getattr(lib, name)
        fn.restype = restype
        fn.argtypes = argtypes
    return lib


def library() -> ctypes.CDLL | None:
    """The loaded kernels, or None where they are unavailable (see :func:`disabled_reason`).

    The first call builds or loads the library; a failed build warns once and the callers use
    their torch path.
    """
    global _lib, _tried, _reason
    if not _tried:
        _tried = True
        if os.environ.get("AGV_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
            _reason = "disabled by AGV_NATIVE=0"
        else:
            try:
                _lib = _build()
            except (OSError, RuntimeError) as err:
                _reason = str(err)
                warnings.warn(
                    f"sim: fused CPU kernels unavailable ({err}); using the slower torch path",
                    stacklevel=2,
                )
    return _lib


def library_for(device: torch.device, wanted: bool | None = None) -> ctypes.CDLL | None:
    """The kernels for tensors on ``device``: None off the CPU, when ``wanted`` is False, or
    where they are unavailable (``wanted=None`` means: when available)."""
    if wanted is False or device.type != "cpu":
        return None
    return library()


def available() -> bool:
    """Whether the fused CPU kernels can be used in this process."""
    return library() is not None


def disabled_reason() -> str | None:
    """Why the kernels are not used (None when they are)."""
    library()
    return _reason
