"""Atomic file writes: write to a temporary file beside the target, then rename it into place,
so an interrupted run never leaves a half-written result, figure or checkpoint.

The temporary file is ``.<name>.<pid>.<random>.tmp`` in the target's folder: recognisable, and
tied to the process that writes it. A process killed mid-write cannot remove its temporary;
the next write to the same target (or :func:`clean_stale_temporaries` on the folder) removes
every temporary whose process is gone. After the rename the folder itself is fsynced, so the
new name survives a power cut as well.
"""

from __future__ import annotations

import os
import re
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_save", "atomic_write_text", "atomic_write_bytes", "clean_stale_temporaries"]

_UMASK = os.umask(0)
os.umask(_UMASK)

_TMP = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.[A-Za-z0-9_]+\.tmp$")
_STALE_AGE_S = 24 * 3600  # where a process cannot be looked up (Windows): stale after a day


def _is_stale(entry: os.DirEntry[str], pid: int) -> bool:
    if pid == os.getpid():
        return False
    if os.name != "posix":  # os.kill(pid, 0) would terminate the process on Windows
        return time.time() - entry.stat(follow_symlinks=False).st_mtime > _STALE_AGE_S
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # it exists, owned by someone else, or no way to tell: leave it
        return False
    return False


def clean_stale_temporaries(folder: str | os.PathLike[str], name: str | None = None) -> list[Path]:
    """Remove the temporaries that interrupted :func:`atomic_save` calls left in ``folder``.

    A temporary is stale when the process that wrote it no longer runs on this machine (on
    Windows: when it is older than a day); temporaries of live processes (another writer at
    work) are kept.

    Parameters
    ----------
    folder : path-like
        The folder to clean (missing: nothing to do).
    name : str, optional
        Only the temporaries of this target file name.

    Returns
    -------
    list of Path
        The files removed.
    """
    folder = Path(folder)
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for entry in entries:
        m = _TMP.match(entry.name)
        if m is None or (name is not None and m["name"] != name):
            continue
        if not entry.is_file(follow_symlinks=False) or not _is_stale(entry, int(m["pid"])):
            continue
        try:
            os.unlink(entry.path)
        except FileNotFoundError:  # removed meanwhile by another cleaner
            continue
        removed.append(Path(entry.path))
    return removed


def _fsync_directory(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some file systems do not support fsync on folders
        pass
    finally:
        os.close(fd)


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
    clean_stale_temporaries(path.parent, path.name)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.",
                               suffix=".tmp")
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
    _fsync_directory(path.parent)
    return path


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Atomically write ``text`` (UTF-8) to ``path``."""
    return atomic_save(lambda p: Path(p).write_text(text, encoding="utf-8"), path)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Atomically write ``data`` to ``path``."""
    return atomic_save(lambda p: Path(p).write_bytes(data), path)
