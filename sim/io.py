"""Atomic file writes: write to a temporary file beside the target, then rename it into place,
so an interrupted run never leaves a half-written result, figure or checkpoint."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_save", "atomic_write_text", "atomic_write_bytes"]

_UMASK = os.umask(0)
os.umask(_UMASK)


def atomic_save(save: Callable[[str], object], path: str | os.PathLike[str]) -> Path:
    """Write a file through ``save(tmp_path)``, then rename it to ``path``.

    Parameters
    ----------
    save : callable
        Called with a temporary path in the target directory; must write the file there.
    path : str or Path
        Final destination; its parent directories are created.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        save(tmp)
        with open(tmp, "rb+") as fh:  # the bytes reach the disk before the rename
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp creates 0600; give the usual file mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    return atomic_save(lambda p: Path(p).write_text(text, encoding="utf-8"), path)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    return atomic_save(lambda p: Path(p).write_bytes(data), path)
