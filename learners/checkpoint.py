"""Checkpoints: safetensors files with a JSON sidecar, written atomically, validated on load.

A checkpoint is ``NAME.safetensors``: the tensors plus the metadata, stored as JSON in the
safetensors header under ``"agv"``. The file is authoritative and complete on its own: it is
written to a temporary file in the same folder (``sim.io.atomic_save``), flushed, fsynced, moved
into place with ``os.replace`` and the folder fsynced, so a run killed at any moment leaves
either the old or the new file, never half of one.

``NAME.json`` beside it is a derived, optional view of the same metadata (pretty-printed, for
people and tools; strict JSON, with NaN written as ``null``). It is written after the
checkpoint and never read by a loader: a run killed between the two writes leaves a sidecar
that is missing or older (its ``sha256`` names the tensors it describes), which
:func:`write_sidecar` regenerates and ``train(resume=True)`` refreshes.

Every load checks the whole header against a schema before using it (:func:`check_header`:
every field's type and range, known algorithm, reward and scenario names, sizes that agree
with the scenario, a learner configuration whose every field is valid), then the tensors:
their SHA-256 (``sha256``), that every float is finite, and that their shapes are the ones
the header describes. The header itself is covered by ``header_sha256`` (checkpoints written
before that field existed load without it). Every defect is a ValueError naming the field.

No checkpoint is ever read through pickle: safetensors holds raw tensors and a JSON header.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import re
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from learners.algorithms import ALGORITHMS, REWARD_NAMES, make_config, make_learner
from learners.common import check_choice, check_int, check_real
from sim.io import atomic_write_bytes

__all__ = [
    "FORMAT", "FORMAT_VERSION", "KINDS", "save_checkpoint", "load_checkpoint", "read_metadata",
    "resolve_checkpoint_path", "validate_metadata", "check_header", "check_tensors",
    "header_digest", "code_version", "tensor_digest", "write_sidecar", "export_policy",
]

ADDED_CONFIG_FIELDS = ("shield_keep_right", "margin_moving", "parked_token",
                       "shield_penalty", "choice_head", "choice_rounds",
                       "choice_regret", "choice_accumulate", "choice_sinkhorn",
                       "choice_sinkhorn_beta", "waypoint_drive", "idle_token",
                       "drive_sight")
"""Learner config fields added after checkpoints of this format were first written: a header
without them is read with the field's default (which is what those runs did)."""

FORMAT = "agv-learner-checkpoint"
FORMAT_VERSION = 1
KINDS = ("policy", "training")
"""``policy``: the actor alone (deployment); ``training``: everything needed to resume."""
_META_KEY = "agv"
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def _json_safe(obj: Any) -> Any:
    """``obj`` with every NaN or infinite float replaced by None (strict JSON's null)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _dumps(obj: Any, **kw: Any) -> str:
    return json.dumps(_json_safe(obj), sort_keys=True, allow_nan=False, **kw)


def header_digest(meta: dict[str, Any]) -> str:
    """SHA-256 of the metadata (without ``header_sha256``) in a canonical JSON form (sorted
    keys, no spaces, NaN as null)."""
    body = {k: v for k, v in meta.items() if k != "header_sha256"}
    return hashlib.sha256(_dumps(body, separators=(",", ":")).encode()).hexdigest()


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


@functools.cache
def _scenario_sizes(scenario: str) -> dict[str, int]:
    """N, M, O and S of a named scenario (from a one-environment instance)."""
    import sim

    env = sim.make_env(scenario, num_envs=1, seed=0)
    return {"num_agents": env.num_agents, "num_tasks": env.num_tasks, "obs_dim": env.obs_dim,
            "state_dim": env.state_dim}


def _is_str_dict(value: Any, values: Callable[[Any], bool]) -> bool:
    return isinstance(value, dict) and all(
        isinstance(k, str) and values(v) for k, v in value.items())


def _real_or_null(v: Any) -> bool:
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


_COUNTERS = ("episodes", "env_steps", "updates", "seconds", "best_response_rate", "last_eval")
_REQUIRED = ("format", "format_version", "kind", "algo", "reward", "scenario", "num_agents",
             "num_tasks", "obs_dim", "state_dim", "config", "sha256")
_REQUIRED_FOR_TRAINING = ("seed", "train_config", *_COUNTERS)
_OPTIONAL = ("seed", "train_config", "code_version", "created", "header_sha256", *_COUNTERS)


def check_header(meta: Any, path: Path | str = "<checkpoint>") -> dict[str, Any]:
    """Check a checkpoint's metadata against the schema, before any of it is used.

    Parameters
    ----------
    meta : object
        The parsed ``"agv"`` header (a JSON object).
    path : path-like
        For the messages.

    Returns
    -------
    dict
        ``meta`` with ``last_eval``'s nulls read back as NaN.

    Raises
    ------
    ValueError
        Naming the first field that is missing, unknown, of the wrong type, out of range, not
        a known algorithm / reward / scenario name, in disagreement with the scenario's sizes
        or with another field, or whose ``header_sha256`` does not match.
    """
    def bad(field: str, why: str) -> ValueError:
        return ValueError(f"checkpoint {path} has a bad header: field {field!r} {why}")

    if not isinstance(meta, dict):
        raise ValueError(f"checkpoint {path} has a bad header: its {_META_KEY!r} metadata must "
                         f"be a JSON object, got {type(meta).__name__}")
    if meta.get("format") != FORMAT:
        raise ValueError(f"{path} is not an agv learner checkpoint (field 'format' is "
                         f"{meta.get('format')!r}, expected {FORMAT!r})")
    version = meta.get("format_version")
    if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
        raise ValueError(f"checkpoint {path} has format_version {version}; this code reads up "
                         f"to {FORMAT_VERSION}: upgrade the package")
    kind = meta.get("kind")
    required = _REQUIRED + (_REQUIRED_FOR_TRAINING if kind == "training" else ())
    for field in required:
        if field not in meta:
            raise bad(field, "is missing")
    unknown = sorted(set(meta) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise bad(unknown[0], f"is not a checkpoint field; expected some of "
                              f"{sorted(set(_REQUIRED) | set(_OPTIONAL))}")

    def field_check(field: str, check: Callable[[], Any]) -> Any:
        try:
            return check()
        except ValueError as err:
            raise bad(field, f"is invalid: {err}") from None

    field_check("format_version",
                lambda: check_int("format_version", version, 1, FORMAT_VERSION))
    field_check("kind", lambda: check_choice("kind", kind, KINDS))
    field_check("algo", lambda: check_choice("algo", meta["algo"], sorted(ALGORITHMS)))
    field_check("reward", lambda: check_choice("reward", meta["reward"], REWARD_NAMES))
    scenario = meta["scenario"]
    if not isinstance(scenario, str):
        raise bad("scenario", f"must be a scenario name (a string), got {scenario!r}")
    try:
        sizes = _scenario_sizes(scenario)
    except ValueError as err:
        raise bad("scenario", f"is not a known scenario: {err}") from None
    for field, want in sizes.items():
        have = field_check(field, lambda f=field: check_int(f, meta[f], 1))
        if have != want:
            raise bad(field, f"is {have}, but scenario {scenario!r} has {field}={want}")
    config = meta["config"]
    if not isinstance(config, dict):
        raise bad("config", f"must be a JSON object of the {meta['algo']} hyperparameters, got "
                            f"{config!r}")
    cfg_cls = ALGORITHMS[meta["algo"]][1]
    missing = sorted({f.name for f in dataclasses.fields(cfg_cls)} - set(config)
                     - set(ADDED_CONFIG_FIELDS))
    if missing:
        raise bad("config", f"lacks the {cfg_cls.__name__} field(s) {missing}")
    field_check("config", lambda: make_config(meta["algo"], config))
    if not (isinstance(meta["sha256"], str) and _HEX64.match(meta["sha256"])):
        raise bad("sha256", f"must be 64 lowercase hex digits, got {meta['sha256']!r}")
    if "seed" in meta:
        field_check("seed", lambda: check_int("seed", meta["seed"], 0))
    if "train_config" in meta:
        tc = meta["train_config"]
        if not isinstance(tc, dict):
            raise bad("train_config", f"must be a JSON object, got {tc!r}")
        for key in ("algo", "reward", "scenario", "seed"):
            if key in tc and key in meta and tc[key] != meta[key]:
                raise bad("train_config", f"has {key}={tc[key]!r} but the header has "
                                          f"{key}={meta[key]!r}")
    if "code_version" in meta and not _is_str_dict(meta["code_version"],
                                                   lambda v: isinstance(v, str)):
        raise bad("code_version", f"must be a JSON object of strings, got "
                                  f"{meta['code_version']!r}")
    if "created" in meta and not isinstance(meta["created"], str):
        raise bad("created", f"must be a string, got {meta['created']!r}")
    for field in ("episodes", "env_steps", "updates"):
        if field in meta:
            field_check(field, lambda f=field: check_int(f, meta[f], 0))
    if "seconds" in meta:
        field_check("seconds", lambda: check_real("seconds", meta["seconds"], 0.0))
    if "best_response_rate" in meta:  # -1: no evaluation yet
        field_check("best_response_rate",
                    lambda: check_real("best_response_rate", meta["best_response_rate"],
                                       -1.0, 1.0))
    out = dict(meta)
    if "last_eval" in meta:
        if not _is_str_dict(meta["last_eval"], _real_or_null):
            raise bad("last_eval", f"must be a JSON object of numbers, got {meta['last_eval']!r}")
        out["last_eval"] = {k: math.nan if v is None else v
                            for k, v in meta["last_eval"].items()}
    if "header_sha256" in meta and meta["header_sha256"] != header_digest(meta):
        raise bad("header_sha256", "does not match the header: the metadata was edited after "
                                   "the checkpoint was written")
    return out


def save_checkpoint(
    path: str | os.PathLike[str], tensors: dict[str, Tensor], metadata: dict[str, Any]
) -> Path:
    """Write ``path`` (.safetensors) atomically, then its ``.json`` sidecar.

    Parameters
    ----------
    path : path-like
        Target file; the suffix ``.safetensors`` is added if missing.
    tensors : dict of str to Tensor
        What to store (made contiguous and moved to the CPU).
    metadata : dict
        JSON-serializable description (kind, algo, reward, scenario, the sizes, config, ...;
        see :func:`check_header`). ``format``, ``format_version``, ``code_version``, ``sha256``
        and ``header_sha256`` are added.

    Returns
    -------
    Path
        The safetensors file written.

    Raises
    ------
    ValueError
        If the metadata does not pass :func:`check_header` (nothing is written).
    """
    from safetensors.torch import save

    path = Path(path)
    if path.suffix != ".safetensors":
        path = path.with_name(path.name + ".safetensors")
    tensors = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION,
            **{k: v for k, v in metadata.items() if k != "header_sha256"},
            "code_version": metadata.get("code_version") or code_version(),
            "sha256": tensor_digest(tensors)}
    meta = json.loads(_dumps(meta))  # what a reader will see: NaN as null, tuples as lists
    meta["header_sha256"] = header_digest(meta)
    check_header(meta, path)
    atomic_write_bytes(path, save(tensors, metadata={_META_KEY: _dumps(meta)}))
    _write_sidecar(path, meta)
    return path


def _write_sidecar(path: Path, meta: dict[str, Any]) -> Path:
    sidecar = path.with_suffix(".json")
    text = _dumps({**meta, "file": path.name}, indent=2) + "\n"
    return atomic_write_bytes(sidecar, text.encode())


def write_sidecar(path: str | os.PathLike[str]) -> Path:
    """(Re)write the ``.json`` sidecar of a checkpoint from its header, if it is missing or
    does not describe the checkpoint as it is (e.g. after a kill between the two writes).

    Returns
    -------
    Path
        The sidecar.
    """
    path = resolve_checkpoint_path(path)
    meta = _read_header(path)
    sidecar = path.with_suffix(".json")
    try:
        current = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        current = None
    if current != json.loads(_dumps({**meta, "file": path.name})):
        _write_sidecar(path, meta)
    return sidecar


def _read_header(path: Path) -> dict[str, Any]:
    """The parsed ``"agv"`` header of a safetensors file (no schema check)."""
    from safetensors import SafetensorError, safe_open

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
        return json.loads(header[_META_KEY])
    except json.JSONDecodeError as err:
        raise ValueError(f"checkpoint {path} has corrupted metadata: {err}") from None


def read_metadata(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The metadata of a checkpoint, read from its safetensors header (no tensors loaded) and
    checked by :func:`check_header`.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ValueError
        If it is not a readable safetensors checkpoint of this library, or its header is not
        valid (the message names the field).
    """
    path = resolve_checkpoint_path(path)
    return check_header(_read_header(path), path)


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


def check_tensors(tensors: dict[str, Tensor], meta: dict[str, Any],
                  path: Path | str = "<checkpoint>") -> None:
    """Check the tensors of a checkpoint against its (checked) header.

    Every floating-point tensor must be finite, and the networks' tensors (``actor.*`` for a
    policy; the actor, critic and their targets for a training checkpoint) must have exactly
    the names, shapes and dtypes of the learner the header describes.

    Raises
    ------
    ValueError
        Naming the tensor, and the header fields that set its shape.
    """
    for name, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise ValueError(f"checkpoint {path}: tensor {name!r} holds NaN or infinite values")
    learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"], meta["num_agents"],
                           dict(meta["config"]))
    want = learner.policy_tensors() if meta["kind"] == "policy" else {
        k: v for k, v in learner.training_tensors().items()
        if k.split(".", 1)[0] in ("actor", "critic", "target_actor", "target_critic")}
    prefixes = tuple({k.split(".", 1)[0] + "." for k in want})
    have = {k: v for k, v in tensors.items() if k.startswith(prefixes)}
    fields = (f"algo={meta['algo']!r}, obs_dim={meta['obs_dim']}, "
              f"state_dim={meta['state_dim']}, num_agents={meta['num_agents']}, config")
    if set(have) != set(want):
        extra, lacking = sorted(set(have) - set(want)), sorted(set(want) - set(have))
        raise ValueError(f"checkpoint {path}: its network tensors are not those its header "
                         f"({fields}) describes: unexpected {extra}, missing {lacking}")
    for name, w in want.items():
        t = have[name]
        if tuple(t.shape) != tuple(w.shape) or t.dtype != w.dtype:
            raise ValueError(f"checkpoint {path}: tensor {name!r} is {t.dtype} of shape "
                             f"{tuple(t.shape)}, but the header ({fields}) needs {w.dtype} of "
                             f"shape {tuple(w.shape)}")


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
        If the file is truncated or corrupted, is not a checkpoint of this library, has a bad
        header (:func:`check_header`) or tensors (:func:`check_tensors`), or was made for
        another algorithm, scenario or observation size.
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
    if digest != meta["sha256"]:
        raise ValueError(f"checkpoint {path} is corrupted: its tensors do not match the SHA-256 "
                         "recorded when it was written")
    check_tensors(tensors, meta, path)
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
