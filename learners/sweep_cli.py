"""``agv sweep``: training and evaluation sweeps on Ray Tune (see ``docs/sweeps.md``).

``allocator/cli.py`` registers it with ``add_sweep_parser(sub, make_controller=allocator.make)``
(the controller factory is passed in: ``learners`` does not import ``allocator``). It also runs
alone, without evaluation sweeps::

    python -m learners.sweep_cli benchmarks/sweeps/tiny.toml --results runs/sweeps/tiny --cpus 2
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from learners.cli import output_dir, positive_int

__all__ = ["add_sweep_arguments", "add_sweep_parser", "run_sweep", "main"]

_DESCRIPTION = ("Run a training sweep (a grid or random search over algorithm x reward x "
                "scenario x seed x any training or learner setting) or, with --evaluate, the "
                "benchmark matrix (allocator x scenario x seed), in parallel on Ray Tune: on "
                "this machine by default, on a Ray cluster with --address. Writes one CSV row "
                "per trial (trials.csv) and the mean and 95% interval over the seeds per "
                "configuration (summary.csv) to the results folder.")


def add_sweep_arguments(parser: argparse.ArgumentParser,
                        make_controller: Callable[..., Any] | None = None) -> None:
    """Add the ``agv sweep`` arguments to ``parser`` and set ``func`` to :func:`run_sweep`.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    make_controller : callable, optional
        ``make_controller(name, **options)`` building an allocator by name (``allocator.make``),
        needed by ``--evaluate``.
    """
    parser.add_argument("spec", metavar="SPEC",
                        help="the sweep spec, a TOML file (e.g. benchmarks/sweeps/tiny.toml)")
    parser.add_argument("--results", metavar="DIR", type=output_dir, default=None,
                        help="results folder: trials/, trials.csv, summary.csv (default "
                             "runs/sweeps/<name>); on a cluster, a folder every machine "
                             "sees at the same path")
    parser.add_argument("--resume", action="store_true",
                        help="continue the sweep in --results: finished trials are kept, "
                             "unfinished ones continue from their checkpoints")
    parser.add_argument("--address", metavar="ADDR", default=None,
                        help="join a running Ray cluster (ray start --head prints its "
                             "address, e.g. 10.0.0.5:6379); default: Ray on this machine, "
                             "on 127.0.0.1 only")
    parser.add_argument("--cpus", metavar="N", type=positive_int, default=None,
                        help="CPUs of the local Ray (default: all of this machine's)")
    parser.add_argument("--evaluate", action="store_true",
                        help="the spec is an evaluation matrix ([evaluate] allocators, "
                             "scenarios, episodes)")
    parser.add_argument("--quiet", action="store_true", help="no Tune status table")
    parser.set_defaults(func=run_sweep, make_controller=make_controller)


def add_sweep_parser(subparsers: argparse._SubParsersAction,
                     make_controller: Callable[..., Any] | None = None
                     ) -> argparse.ArgumentParser:
    """Register ``sweep`` on the ``agv`` subcommands.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        From ``parser.add_subparsers()``.
    make_controller : callable, optional
        ``allocator.make``, for ``--evaluate``.

    Returns
    -------
    argparse.ArgumentParser
        The ``sweep`` parser.
    """
    parser = subparsers.add_parser("sweep", help="training and evaluation sweeps on Ray",
                                   description=_DESCRIPTION)
    add_sweep_arguments(parser, make_controller)
    return parser


def run_sweep(args: argparse.Namespace) -> int:
    """Run ``agv sweep``.

    Returns
    -------
    int
        0 every trial finished, 1 some trials failed after their retries, 2 bad input or Ray
        not installed (with a one-line message on standard error).
    """
    from learners import sweep

    if not sweep.ray_available():
        print(sweep.RAY_INSTALL_HINT, file=sys.stderr)
        return 2
    try:
        spec = sweep.load_spec(args.spec, mode="evaluate" if args.evaluate else "train")
        results = args.results or str(Path("runs") / "sweeps" / spec.name)
        print(f"sweep {spec.name}: {len(spec.trials)} trials -> {results}", flush=True)
        outcome = sweep.run_sweep(spec, results, resume=args.resume, address=args.address,
                                  cpus=args.cpus,
                                  make_controller=getattr(args, "make_controller", None),
                                  verbose=0 if getattr(args, "quiet", False) else 1)
    except (ValueError, FileNotFoundError, ImportError) as err:
        print(f"agv sweep: error: {err}", file=sys.stderr)
        return 2
    skipped = len(spec.trials) - len(outcome.ran)
    print(f"sweep {spec.name}: {outcome.finished}/{len(spec.trials)} trials finished "
          f"({len(outcome.ran)} run now, {skipped} already done) in {outcome.seconds:.0f} s; "
          f"tables {outcome.trials_csv} and {outcome.summary_csv}")
    if outcome.failed:
        print(f"agv sweep: {len(outcome.failed)} trial(s) failed after their retries: "
              f"{', '.join(outcome.failed)}; see {outcome.results}/trials/<trial>/ and "
              "rerun with --resume", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m learners.sweep_cli SPEC ...`` (training sweeps; ``--evaluate`` needs the
    ``agv`` command, which knows the allocators)."""
    parser = argparse.ArgumentParser(prog="agv sweep", description=_DESCRIPTION)
    add_sweep_arguments(parser)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
