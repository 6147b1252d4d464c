"""Skip a test for a missing resource on a developer's machine, fail it on CI.

A test that needs the shipped weights (or another file a fresh clone may lack) should not pass
unnoticed on CI by skipping: with the environment variable ``CI`` set (GitHub Actions, GitLab
and most services set ``CI=true``) the same call fails the test instead.

>>> from allocator.testing import in_ci
>>> in_ci({"CI": "true"}), in_ci({"CI": "0"}), in_ci({})
(True, False, False)
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any, NoReturn

import allocator

__all__ = ["in_ci", "skip_or_fail_in_ci", "make_or_skip"]

_OFF = ("", "0", "false", "no")


def in_ci(environ: Mapping[str, str] | None = None) -> bool:
    """Whether ``CI`` is set to something other than ``""``, ``0``, ``false`` or ``no``.

    Parameters
    ----------
    environ : mapping, optional
        The environment to read (default :data:`os.environ`).
    """
    env = os.environ if environ is None else environ
    return env.get("CI", "").strip().lower() not in _OFF


def skip_or_fail_in_ci(reason: str) -> NoReturn:
    """``pytest.skip(reason)``, or ``pytest.fail`` when running on CI (:func:`in_ci`).

    Parameters
    ----------
    reason : str
        What is missing and how to get it.

    Examples
    --------
    >>> from allocator.learned import weights_path
    >>> from allocator.testing import skip_or_fail_in_ci
    >>> def test_shipped_weights():
    ...     path = weights_path("maddpg", "ipf", "3v3")
    ...     if not path.exists():
    ...         skip_or_fail_in_ci(f"no shipped weights at {path}")
    """
    import pytest

    if in_ci():
        pytest.fail(f"{reason} (CI is set, so a missing resource fails instead of skipping)",
                    pytrace=False)
    pytest.skip(reason)


def make_or_skip(name: str, **options: Any) -> Any:
    """``allocator.make(name, **options)``, skipping (failing on CI) when its files are missing.

    A learned allocator whose weights are not shipped raises
    :class:`~allocator.learned.MissingWeightsError`, a :class:`FileNotFoundError`; that becomes
    :func:`skip_or_fail_in_ci`. Every other error propagates.

    Examples
    --------
    >>> from allocator.testing import make_or_skip
    >>> make_or_skip("maddpg-ipf", scenario="3v3").name
    'maddpg-ipf'
    """
    try:
        return allocator.make(name, **options)
    except FileNotFoundError as err:
        skip_or_fail_in_ci(str(err))
