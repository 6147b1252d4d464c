"""The command line a benchmark records beside its results, written so that pasting it at the
repository root repeats the run.

The benchmark scripts import this module by name (``benchmarks/`` is on the import path when
a script runs, and the tests load the scripts the same way).
"""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def recorded_command(script: str, argv: list[str] | None = None, env: str = "") -> str:
    """The command line as it was run, from the repository root.

    Parameters
    ----------
    script : str
        The script's path (its ``__file__``).
    argv : list of str, optional
        Its arguments; ``None``: ``sys.argv[1:]``.
    env : str, optional
        Environment assignments written before ``python`` (e.g. ``"OMP_NUM_THREADS=1"``).

    Returns
    -------
    str
        ``python benchmarks/X.py ARGS`` (shell-quoted). Relative paths in the arguments are
        read from the working directory, so a run started elsewhere (``cd benchmarks &&
        python X.py ...``) is recorded with its ``cd``, and the record repeats the run.
    """
    given = sys.argv[1:] if argv is None else argv
    cwd = Path.cwd().resolve()
    words = ["python", os.path.relpath(Path(script).resolve(), cwd), *map(str, given)]
    line = (f"{env} " if env else "") + shlex.join(words)
    if cwd == ROOT:
        return line
    return f"cd {shlex.quote(os.path.relpath(cwd, ROOT))} && {line}"
