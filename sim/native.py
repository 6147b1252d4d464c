"""Fused CPU kernels for the simulator's step and the IPF reward, built on first use.

The step's claims, collisions, team reward and K-nearest observations, and the IPF reward's
small per-environment solves, are a few dozen tiny tensor operations each in torch; on the
CPU their dispatch and memory traffic cost several times the physics itself. The C sources in
``sim/_native/`` do the same work in one pass per environment, one file per concept beside
its torch reference (``observations.h``: :mod:`sim.observations`; ``physics.h``:
:mod:`sim.physics`; ``tasks.h``: :mod:`sim.tasks`; ``step.c`` the fused step; ``ipf.c``:
:mod:`sim.ipf`; ``spawn.c``: :mod:`sim.scenarios`), compiled as one translation unit
(``kernels.c`` includes them) so that the compiler inlines across them. They are compiled with
the system's C compiler the first time they are needed (about a second) and cached in
``$AGV_CACHE_DIR`` (default ``~/.cache/agv-allocation``), keyed by a hash of the sources, the
flags and the machine. The ctypes signatures are read from the C definitions
(:func:`signatures`), so the table cannot drift from the source.

The torch code stays the definition and runs wherever the kernels cannot: tensors on another
device, no C compiler, or ``AGV_NATIVE=0`` in the environment. Tests check that both paths
agree. Every pointer that reaches C comes from a tensor whose dtype, shape, device and
contiguity were checked, by :func:`pointer` or once where the tensor is made.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import re
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path
from typing import Any

import torch

__all__ = ["available", "cache_dir", "compiler", "disabled_reason", "library", "library_for",
           "load_cached", "parse_signatures", "pointer", "signatures", "sources"]

NATIVE_DIR = Path(__file__).parent / "_native"
SOURCE = NATIVE_DIR / "kernels.c"
FLAGS = ["-O3", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno",
         "-Wno-psabi"]

_lib: ctypes.CDLL | None = None
_tried = False
_reason: str | None = None

_SCALARS = {"int": ctypes.c_int, "int64_t": ctypes.c_int64, "float": ctypes.c_float,
            "double": ctypes.c_double}
_EXPORTED = re.compile(r"^(int|int64_t|void)\s+(agv_\w+)\(([^)]*)\)\s*\{", re.MULTILINE)


def sources() -> list[Path]:
    """The C files of the kernels (``kernels.c`` includes the others: one translation unit)."""
    return sorted(p for p in NATIVE_DIR.iterdir() if p.suffix in (".c", ".h"))


def parse_signatures(text: str) -> dict[str, tuple[Any, list[Any]]]:
    """The ctypes ``(restype, argtypes)`` of every exported ``agv_*`` function defined in C
    source ``text`` (pointers of any type become ``c_void_p``).

    Raises
    ------
    ValueError
        For a return or parameter type the table does not know.
    """
    out: dict[str, tuple[Any, list[Any]]] = {}
    for ret, name, params in _EXPORTED.findall(text):
        argtypes = []
        for param in " ".join(params.split()).split(","):
            if "*" in param:
                argtypes.append(ctypes.c_void_p)
                continue
            words = [w for w in param.split() if w != "const"]
            if len(words) != 2 or words[0] not in _SCALARS:
                raise ValueError(f"{name}: parameter {param.strip()!r} has no ctypes mapping "
                                 f"(known: pointers and {sorted(_SCALARS)})")
            argtypes.append(_SCALARS[words[0]])
        out[name] = (None if ret == "void" else _SCALARS[ret], argtypes)
    return out


def signatures() -> dict[str, tuple[Any, list[Any]]]:
    """The ctypes signature table of the kernels, read from their C definitions."""
    table: dict[str, tuple[Any, list[Any]]] = {}
    for path in sources():
        table.update(parse_signatures(path.read_text()))
    return table


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


def cache_dir() -> Path:
    """Where compiled kernels are cached: ``$AGV_CACHE_DIR``, else
    ``~/.cache/agv-allocation``."""
    root = os.environ.get("AGV_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "agv-allocation"


def compiler() -> str | None:
    """The C compiler the kernels are built with (``$CC``, ``cc``, ``gcc`` or ``clang``, the
    first found), or None."""
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


_cache_dir, _compiler = cache_dir, compiler  # the names older callers import


def load_cached(source: Path, flags: list[str], prefix: str,
                inputs: list[Path] | None = None) -> ctypes.CDLL:
    """Compile ``source`` into a shared library once and load it from the cache.

    The cached file is ``<cache_dir()>/<prefix>_<key>.so``, keyed by the bytes of ``inputs``
    (default ``[source]``: list every file it includes), the compiler, ``flags`` and the
    machine. The build writes a temporary file and renames it, so a concurrent build never
    loads a partial library; a damaged cache entry is built again.

    Raises
    ------
    RuntimeError
        With no C compiler, or when the compiler fails (its message, cut at 2000 characters).
    """
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (tried $CC, cc, gcc, clang)")
    digest = hashlib.sha256()
    for path in inputs if inputs is not None else [source]:
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    digest.update(" ".join([cc, *flags, platform.machine(), platform.system()]).encode())
    target = cache_dir() / f"{prefix}_{digest.hexdigest()[:16]}.so"
    if target.exists():
        try:
            return ctypes.CDLL(str(target))
        except OSError:  # a damaged cache entry: build it again
            pass
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        result = subprocess.run([cc, *flags, str(source), "-o", tmp, "-lm"],
                                capture_output=True, text=True)
        if result.returncode != 0:
            raise RuntimeError(f"{cc} failed: {result.stderr.strip()[:2000]}")
        os.replace(tmp, target)  # atomic: a concurrent build never loads a partial file
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return ctypes.CDLL(str(target))


def _build() -> ctypes.CDLL:
    lib = load_cached(SOURCE, FLAGS, "agv_kernels", inputs=sources())
    for name, (restype, argtypes) in signatures().items():
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
