"""Checkpoints: safetensors files with a JSON sidecar, written atomically, validated on load.

A checkpoint is ``NAME.safetensors`` (tensors plus the metadata, stored as JSON in the
safetensors header under ``"agv"``) and ``NAME.json`` (the same metadata, pretty-printed, for
people and tools). The safetensors file alone is authoritative: it is written to a temporary
file in the same folder, flushed, fsynced and moved into place with ``os.replace``, so a run
killed at any moment leaves either the old or the new file, never half of one. The metadata
holds a SHA-256 of the tensors, so a truncated or corrupted file is reported as such.

No checkpoint is ever read through pickle: safetensors holds raw tensors and a JSON header.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from sim.io import atomic_write_bytes

__all__ = [
    "FORMAT", "FORMAT_VERSION", "save_checkpoint", "load_checkpoint", "read_metadata",
    "resolve_checkpoint_path", "validate_metadata", "code_version", "tensor_digest",
    "export_policy",
]

FORMAT = "agv-learner-checkpoint"
FORMAT_VERSION = 1
_META_KEY = "agv"


def code_version() -> dict[str, str]:
    """The package version and, when run from a git checkout, the commit (``+dirty`` if the
    working tree has changes)."""
    from importlib import metadata

    try:
        version = metadata.version("agv-allocation")
    except metadata.PackageNotFoundError:  # pragma: no cover
        version = "unknown"
    out = {"package": version}
    root = Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
            timeout=5, check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--", "learners", "sim"],
            capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()
        out["git"] = commit + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def tensor_digest(tensors: dict[str, Tensor]) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of the tensors, in sorted order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy())
    return h.hexdigest()


def resolve_checkpoint_path(path: str | os.PathLike[str]) -> Path:
    """``X.safetensors`` for ``X.safetensors``, ``X.json`` or ``X`` (if that file exists);
    ``DIR/checkpoint.safetensors`` for a run folder (or a name that is neither)."""
    p = Path(path)
    if p.is_dir() or (p.suffix == "" and not p.with_name(p.name + ".safetensors").exists()):
        return p / "checkpoint.safetensors"
    if p.suffix == ".json":
        return p.with_suffix(".safetensors")
    if p.suffix != ".safetensors":
        return p.with_name(p.name + ".safetensors")
    return p


def save_checkpoint(
    path: str | os.PathLike[str], tensors: dict[str, Tensor], metadata: dict[str, Any]
) -> Path:
    """Write ``path`` (.safetensors) and its ``.json`` sidecar atomically.

    Parameters
    ----------
    path : path-like
        Target file; the suffix ``.safetensors`` is added if missing.
    tensors : dict of str to Tensor
        What to store (made contiguous and moved to the CPU).
    metadata : dict
        JSON-serializable description (algorithm, scenario, config, seed, ...). ``format``,
        ``format_version``, ``sha256`` and ``code_version`` are added.

    Returns
    -------
    Path
        The safetensors file written.
    """
    from safetensors.torch import save

    path = Path(path)
    if path.suffix != ".safetensors":
        path = path.with_name(path.name + ".safetensors")
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, **metadata,
            "code_version": metadata.get("code_version") or code_version(),
            "sha256": tensor_digest(tensors)}
    text = json.dumps(meta, sort_keys=True)
    atomic_write_bytes(path, save(tensors, metadata={_META_KEY: text}))
    sidecar = json.dumps({**meta, "file": path.name}, indent=2, sort_keys=True) + "\n"
    atomic_write_bytes(path.with_suffix(".json"), sidecar.encode())
    return path


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The metadata of a checkpoint, read from its safetensors header (no tensors loaded).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a readable safetensors checkpoint of this library.
    """
    from safetensors import SafetensorError, safe_open

    path = resolve_checkpoint_path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}: expected a .safetensors file written "
                                "by `agv train` (or its .json sidecar, or a run folder)")
    try:
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as err:
        raise ValueError(f"checkpoint {path} is truncated or corrupted (not a readable "
                         f"safetensors file): {err}") from None
    if _META_KEY not in header:
        raise ValueError(f"{path} is a safetensors file but not an agv learner checkpoint "
                         f"(no {_META_KEY!r} metadata)")
    try:
        meta = json.loads(header[_META_KEY])
    except json.JSONDecodeError as err:
        raise ValueError(f"checkpoint {path} has corrupted metadata: {err}") from None
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path} is not an agv learner checkpoint (format "
                         f"{meta.get('format')!r}, expected {FORMAT!r})")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise ValueError(f"checkpoint {path} has format version {meta['format_version']}; this "
                         f"code reads up to {FORMAT_VERSION}: upgrade the package")
    return meta


def validate_metadata(meta: dict[str, Any], path: Path | str, **expected: Any) -> None:
    """Raise a ValueError naming the first field of ``meta`` that differs from ``expected``.

    ``None`` values in ``expected`` are not checked.
    """
    hints = {
        "scenario": "train one for this scenario with `agv train --scenario ...`",
        "obs_dim": "the observation size depends on the scenario's N, M and sensing settings",
        "algo": "load it with the allocator of its own algorithm",
        "kind": "",
    }
    for key, want in expected.items():
        if want is None:
            continue
        have = meta.get(key)
        if have != want:
            raise ValueError(f"checkpoint {path} was made for {key}={have!r}, expected "
                             f"{key}={want!r}" + (f"; {hints[key]}" if hints.get(key) else ""))


def load_checkpoint(
    path: str | os.PathLike[str], **expected: Any
) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Load and check a checkpoint.

    Parameters
    ----------
    path : path-like
        A ``.safetensors`` file, its ``.json`` sidecar, or a run folder.
    **expected
        Metadata fields that must match, e.g. ``algo="maddpg"``, ``scenario="3v3"``,
        ``obs_dim=24`` (``None`` skips a check).

    Returns
    -------
    tensors : dict of str to Tensor
    metadata : dict

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    ValueError
        If the file is truncated or corrupted, is not a checkpoint of this library, or was made
        for another algorithm, scenario or observation size.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = resolve_checkpoint_path(path)
    meta = read_metadata(path)
    validate_metadata(meta, path, **expected)
    try:
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError, RuntimeError) as err:
        raise ValueError(f"checkpoint {path} is truncated or corrupted: {err}") from None
    digest = tensor_digest(tensors)
    if digest != meta.get("sha256"):
        raise ValueError(f"checkpoint {path} is corrupted: its tensors do not match the SHA-256 "
                         "recorded when it was written")
    return tensors, meta


def export_policy(source: str | os.PathLike[str], target: str | os.PathLike[str]) -> Path:
    """Copy a policy checkpoint (checked on the way) to ``target`` with its JSON sidecar, e.g.
    into ``allocator/weights/<scenario>/<algo>-<reward>.safetensors``.

    Returns
    -------
    Path
        The safetensors file written.
    """
    tensors, meta = load_checkpoint(source, kind="policy")
    return save_checkpoint(target, tensors, meta)
