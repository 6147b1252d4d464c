"""Shielded controllers on a lifelong floor: the shield's liveness rules and lanes, the
learned policies against the dispatchers driven by SafeDriver, over seeds.

    nice python benchmarks/shield_lifelong.py [--floor warehouse-20] [--steps 1000]
        [--seeds 0 1 2] [--weights RUN_DIR_OR_FILE ...] [--variants none off on lanes]
        [--keep-right 0.3 ...] [--baselines path-follower hungarian ...] [--view K]
        [--out FILE]

Rows, every one through :func:`sim.evaluate_lifelong` on the same seeded floors and orders
(one run per seed):

- ``path follower``: :class:`PathFollower`, a scripted controller of the ``obs -> act``
  protocol (each AGV heads for its target, or the nearest visible open pickup when it has
  none, along the floor's shortest path), behind :class:`allocator.SafetyShield` with
  ``liveness=False`` and ``liveness=True``;
- the learned policy of every ``--weights`` entry (a lifelong entity run folder or policy
  file, or a taught family's name such as ``maddpg-dagger``, run at its own view; a file
  sees ``--view`` open pickups and other AGVs, the floor's own 4 by default; none by
  default), ``allocator.make(NAME, scenario=FLOOR, weights=ENTRY,
  shield=True)``, in each ``--variants`` form: without the shield (``none``), with the
  shield's liveness rules ``off`` and ``on``, and on with lanes (``lanes``: the intended
  velocities turned right by each ``--keep-right`` angle, ``SafetyShield.keep_right``) (a run
  folder loads its ``policy.safetensors``, the last policy; pass ``RUN/best.safetensors`` for
  the best);
- for reference, the classical dispatchers driven by :class:`allocator.SafeDriver` (the same
  resolver, QP and braking filter, on planned paths; ``--baselines``, default these four):
  ``hungarian``, ``fifo``, ``auction`` (the decentralized auction with unlimited radio range,
  as the learned policies sense every AGV and order on the floor) and ``auction-3`` (radio
  range 3.0, the scale table's lifelong auction);
- ``hungarian-shield`` (asked for by name): Hungarian's choices, each AGV intending
  ``WaypointDriver``'s command, through :class:`allocator.SafetyShield` with lanes of the first
  ``--keep-right`` angle (:class:`ShieldedIntent`), the action clipped per axis and scaled
  with its direction kept: what a learned policy could reach behind the shield.

Columns: deliveries per 1000 steps (mean over the seeds, 95% t-interval, each seed's),
overlapping AGV pairs summed over the steps and seeds (the simulator's rule), the shield's
interventions per movable AGV-step (``any``, and the share the liveness rules changed), the
resolver's yields, the mean of the actions the controller gave the shield (over all
AGV-steps: a policy that pushes every AGV one way shows there), wall-clock seconds; then each
shielded row's throughput as a multiple of the SafeDriver dispatchers'. Writes a markdown
table with the command, date, commit and seeds to ``--out``.
"""

from __future__ import annotations

import argparse
import datetime
import math
import platform
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from provenance import recorded_command
from scipy import stats
from torch import Tensor

import allocator
import sim
from allocator.distances import FloorDistances
from allocator.learned import TAUGHT_NAMES, scenario_to_run
from sim.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "scale" / "lifelong" / "shield_liveness.md"


class PathFollower:
    """A scripted lifelong controller that reads only its observations.

    Each AGV heads for its own target (a loaded AGV's drop-off, an assigned AGV's pickup), or
    when it has none for the nearest visible open pickup (an idle AGV takes an open order it
    reaches), towards the first corner of the floor's shortest path
    (:meth:`allocator.distances.FloorDistances.next_waypoint`); an AGV with neither stands.
    No coordination and no avoidance: that is the shield's part.

    Parameters
    ----------
    gain : float
        Desired velocity per unit distance to the corner (1/s; > 0).
    max_speed : float
        Cap on the commanded speed (> 0).
    """

    name = "path-follower"

    def __init__(self, gain: float = 4.0, max_speed: float = 1.2) -> None:
        for label, value in (("gain", gain), ("max_speed", max_speed)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value) or value <= 0:
                raise ValueError(f"{label} must be a finite number > 0, got {value!r}")
        self.gain = float(gain)
        self.max_speed = float(max_speed)
        self.distances: FloorDistances | None = None

    def reset(self, env: Any) -> None:
        """Read the env's observation layout, physics and floor (its distance table).

        Raises
        ------
        ValueError
            For an env without a lifelong observation layout.
        """
        from sim.observations import LifelongObsLayout

        if not isinstance(getattr(env, "obs_layout", None), LifelongObsLayout):
            raise ValueError("PathFollower drives lifelong floors (warehouse-N)")
        self.layout = env.obs_layout
        self.physics = env.world.physics
        self.distances = FloorDistances(env.world)

    def act(self, obs: Tensor) -> Tensor:
        """Actions (B, N, 2) in [-1, 1] from lifelong observations (B, N, O)."""
        if self.distances is None:
            raise ValueError("PathFollower.reset(env) must be called before act")
        lay, ph = self.layout, self.physics
        o = obs.detach().cpu().double().numpy()
        pos, vel = o[..., lay.pos], o[..., lay.vel]
        rel = o[..., lay.target_rel]
        go = o[..., lay.target_mask][..., 0] > 0
        if lay.k_pickups:
            seen = o[..., lay.pickup_mask(0)][..., 0] > 0
            rel = np.where(go[..., None], rel, o[..., lay.pickup_rel(0)])
            go = go | seen
        corner = pos.copy()
        if go.any():
            corner[go] = self.distances.next_waypoint(pos[go], pos[go] + rel[go])
        v_cmd = (corner - pos) * self.gain
        speed = np.linalg.norm(v_cmd, axis=-1, keepdims=True)
        v_cmd *= self.max_speed / np.maximum(speed, self.max_speed)
        action = (v_cmd - (1.0 - ph.damping) * vel) / (ph.sensitivity * ph.dt / ph.mass)
        return torch.as_tensor(np.clip(action, -1.0, 1.0), dtype=obs.dtype)


class ShieldedIntent:
    """A dispatcher's driver whose intentions go through :class:`allocator.SafetyShield`.

    Each AGV with a target intends :class:`allocator.WaypointDriver`'s velocity command (the
    first corner of its path, gain 4, 1.2 units/s); the shield (liveness rules, lanes of
    ``keep_right``, QP, braking filter) makes it safe. It answers what a learned lifelong
    policy could reach behind the shield if it made the dispatcher's choices and drove as the
    path follower does. ``keep_direction``: the command's action is scaled into [-1, 1]^2
    (its direction kept) instead of clipped per axis, as ``WaypointDriver`` does.

    Attributes
    ----------
    shield : allocator.SafetyShield
        The shield (``interventions``, ``resolver``), reset with the driver.
    """

    def __init__(self, keep_right: float = 0.0, keep_direction: bool = False) -> None:
        self.waypoints = allocator.WaypointDriver()
        self.max_speed = self.waypoints.max_speed
        self.keep_direction = bool(keep_direction)
        self.env: Any = None
        owner = self

        class _Intent:  # the shield's controller: the driver's own intentions
            def reset(self, env: Any) -> None:
                pass

            def act(self, obs: Tensor) -> Tensor:
                return owner.intent(owner.env)

        self.shield = allocator.SafetyShield(_Intent(), keep_right=keep_right)

    def reset(self, env: Any) -> None:
        """Bind to the env: the waypoint table (which the dispatcher reads) and the shield."""
        self.env = env
        self.waypoints.reset(env)
        self.distances = self.waypoints.distances
        self.shield.reset(env)

    def intent(self, env: Any) -> Tensor:
        """The waypoint commands as actions (B, N, 2), clipped or direction-keeping."""
        if not self.keep_direction:
            return self.waypoints.act(env)
        _, action = self.waypoints.command(env)
        action /= np.maximum(1.0, np.abs(action).max(-1, keepdims=True))
        return torch.as_tensor(action, dtype=torch.float32)

    def act(self, env: Any) -> Tensor:
        """The shielded actions (B, N, 2)."""
        return self.shield.filter(self.intent(env))


def _learned(weights: str, floor: str, liveness: bool | None, keep_right: float = 0.0) -> Any:
    """The learned policy of ``weights`` (a policy file or run folder, or the name of a
    taught family, ``allocator.learned.TAUGHT_NAMES``, with its shipped weights) with
    ``shield=True``, its shield's liveness set (``None``: no shield at all) and its lane
    angle ``keep_right``."""
    from learners.checkpoint import read_metadata

    if weights in TAUGHT_NAMES:
        ctl = allocator.make(weights, scenario=floor, shield=liveness is not None)
    else:
        meta = read_metadata(weights)
        name = f"{meta['algo'].removesuffix('-e')}-{meta['reward']}"
        ctl = allocator.make(name, scenario=floor, weights=weights,
                             shield=liveness is not None)
    if liveness is not None:
        assert ctl.safety.liveness is None  # the default reaches the learned allocator's shield
        ctl.safety.liveness = liveness
        ctl.safety.keep_right = keep_right
    return ctl


class _Recorder:
    """Sums the controller's own actions: those a shield is given (its ``filter``), or those
    an unshielded controller returns (its ``act``)."""

    def __init__(self, owner: Any, method: str) -> None:
        self.total = np.zeros(2)
        self.count = 0
        inner = getattr(owner, method)

        def wrapped(arg: Any) -> Any:
            out = inner(arg)
            a = arg if method == "filter" else out
            a = np.clip(np.asarray(torch.as_tensor(a).detach().cpu(), dtype=float), -1, 1)
            self.total += a.reshape(-1, 2).sum(0)
            self.count += a.reshape(-1, 2).shape[0]
            return out

        setattr(owner, method, wrapped)

    def mean(self) -> np.ndarray:
        return self.total / max(self.count, 1)


BASELINES = ("path-follower", "hungarian", "fifo", "auction", "auction-3", "hungarian-shield",
             "hungarian-plan", "local-plan", "local-path-plan")
"""The reference rows (``--baselines``): the shielded path follower, the classical
dispatchers driven by SafeDriver (``auction``: unlimited radio range, ``auction-3``: 3.0),
``hungarian-shield``: Hungarian's choices driven by :class:`ShieldedIntent` at the first
``--keep-right`` angle, with the action clipped and direction-keeping (two rows), and
``hungarian-plan``: the lifelong DAgger probe's teacher (``lifelong_dagger.TeacherDriver``:
Hungarian's plan kept to itself, the orders claimed by reaching them, as a decentralized
policy claims them) behind :class:`allocator.SafetyShield` with the same lanes, and
``local-plan``: ``lifelong_dagger.LocalTeacher``, each AGV's share of the assignment among
the 16 open pickups and 16 idle AGVs nearest to it, behind the same shield, and
``local-path-plan``: the same priced by the floor's travel distances (the last four not in
the default set)."""
DEFAULT_BASELINES = BASELINES[:5]


def _baseline(name: str, keep_right: float = 0.0) -> list[tuple[str, str, Any]]:
    """(label, liveness column, controller) of one reference row (two for the follower and
    for ``hungarian-shield``)."""
    if name == "path-follower":
        return [("path follower", "on" if live else "off",
                 allocator.SafetyShield(PathFollower(), liveness=live)) for live in (False, True)]
    if name == "hungarian-shield":
        out = []
        for keep in (False, True):
            driver = ShieldedIntent(keep_right, keep_direction=keep)
            ctl = allocator.HungarianDispatcher(driver=driver)
            ctl.safety = driver.shield  # the counters the rows read
            action = "direction-keeping" if keep else "clipped"
            out.append((f"hungarian's choices, waypoint intent ({action}) + shield",
                        f"on, lanes {keep_right:g} rad", ctl))
        return out
    if name == "hungarian-plan":
        from lifelong_dagger import TeacherDriver

        return [("hungarian's plan, not assigned (the DAgger teacher) + shield",
                 f"on, lanes {keep_right:g} rad",
                 allocator.SafetyShield(TeacherDriver(), keep_right=keep_right))]
    if name in ("local-plan", "local-path-plan"):
        from lifelong_dagger import LOCAL_VIEW, TeacherDriver

        path = name == "local-path-plan"
        priced = ", priced by path" if path else ""
        return [(f"each AGV's local assignment, {LOCAL_VIEW} nearest{priced} (a teacher) + shield",
                 f"on, lanes {keep_right:g} rad",
                 allocator.SafetyShield(TeacherDriver(view=LOCAL_VIEW, path=path),
                                        keep_right=keep_right))]
    if name == "hungarian":
        ctl = allocator.HungarianDispatcher(driver=allocator.SafeDriver())
    elif name == "fifo":
        ctl = allocator.FifoDispatcher(driver=allocator.SafeDriver())
    else:
        comm_range = math.inf if name == "auction" else 3.0
        ctl = allocator.AuctionDispatcher(comm_range, driver=allocator.SafeDriver())
        name = f"auction (range {comm_range:g})"
    return [(f"{name} + SafeDriver", "SafeDriver's", ctl)]


VARIANTS = ("none", "off", "on", "lanes")
"""The learned rows (``--variants``): no shield, the shield with its liveness rules off, on,
and on with lanes (the intended velocities turned right by each ``--keep-right`` angle)."""


def rows(floor: str, steps: int, seeds: list[int], weights: list[str],
         baselines: tuple[str, ...] | list[str] = DEFAULT_BASELINES,
         variants: tuple[str, ...] | list[str] = VARIANTS,
         keep_right: tuple[float, ...] | list[float] = (0.3,),
         view: int | None = None) -> list[dict]:
    """Run every row on every seed; returns one dict per row (also printed as it finishes):
    the mean throughput over the seeds, its 95% t-interval, the per-seed values, the
    overlapping pairs summed over all runs, and the shield's counters averaged over them.
    ``view``: the learned policy files' rows see that many open pickups and other AGVs (None:
    the floor's own; a taught family always sees its own)."""
    viewed = sim.get_scenario(floor) if view is None else \
        sim.get_scenario(floor, k_pickups=view, k_agents=view)
    runs: list[tuple[str, str, Any]] = []
    if "path-follower" in baselines:
        runs += _baseline("path-follower")
    for entry in weights:
        for variant in variants:
            if variant == "lanes":
                runs += [(f"learned ({entry})", f"on, lanes {k:g} rad",
                          _learned(entry, floor, True, k)) for k in keep_right]
            else:
                live = {"none": None, "off": False, "on": True}[variant]
                runs.append((f"learned ({entry})", "no shield" if live is None else variant,
                             _learned(entry, floor, live)))
    for name in baselines:
        if name != "path-follower":
            runs += _baseline(name, keep_right[0])
    out = []
    for label, live, ctl in runs:
        shield = ctl if isinstance(ctl, allocator.SafetyShield) else getattr(ctl, "safety", None)
        recorder = _Recorder(shield, "filter") if shield is not None \
            else _Recorder(ctl, "act") if live == "no shield" else None
        per_seed, overlaps, rates, by_rules, yields = [], 0.0, [], [], 0
        t = time.perf_counter()
        # a taught family: its own view; a policy file: --view; a baseline: the floor's
        scen = scenario_to_run(ctl, viewed if label.startswith("learned") else floor)
        for seed in seeds:
            m = sim.evaluate_lifelong(ctl, scen, steps=steps, seed=seed, runs=1)
            per_seed.append(m.throughput)
            overlaps += m.collisions_per_1000 * steps / 1000.0
            if shield is not None:
                rates.append(shield.intervention_rate())
                by_rules.append(shield.interventions["liveness"] / max(shield.agent_steps, 1))
                yields += shield.resolver.yields if shield.resolver is not None else 0
        seconds = time.perf_counter() - t
        values = np.asarray(per_seed, dtype=float)
        half = float(stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1)
                     / math.sqrt(len(values))) if len(values) > 1 else math.nan
        live_shield = shield is not None and shield.resolver is not None
        row = dict(method=label, liveness=live, throughput=float(values.mean()),
                   throughput_ci95=half, per_seed=per_seed, overlaps=overlaps,
                   interventions=float(np.mean(rates)) if rates else None,
                   by_liveness=float(np.mean(by_rules)) if by_rules else None,
                   yields=yields if live_shield else None,
                   mean_action=None if recorder is None else recorder.mean().round(2).tolist(),
                   seconds=seconds)
        print(row, flush=True)
        out.append(row)
    return out


def _fmt(x: Any, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def _mean(xy: list[float] | None) -> str:
    return "n/a" if xy is None else f"({xy[0]:+.2f}, {xy[1]:+.2f})"


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _ratios(table: list[dict]) -> list[str]:
    """Lines giving each row's mean throughput as a multiple of the SafeDriver dispatchers'."""
    refs = {r["method"]: r["throughput"] for r in table if r["method"].endswith("SafeDriver")}
    lines = []
    for r in table:
        if r["method"].endswith("SafeDriver") or r["liveness"] == "no shield":
            continue
        parts = [f"{r['throughput'] / v:.2f}x {name.removesuffix(' + SafeDriver')}"
                 for name, v in refs.items() if v > 0]
        if parts:
            lines.append(f"- {r['method']}, liveness {r['liveness']}: {', '.join(parts)}")
    return lines


def write(table: list[dict], out: Path, command: str, floor: str, steps: int,
          seeds: list[int]) -> None:
    """The markdown table of ``table`` with the command, date, commit and seeds."""
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        f"# Shielded lifelong controllers on {floor}",
        "",
        f"`{command}` on {platform.machine()}, Python {platform.python_version()}, torch "
        f"{torch.__version__}, {date}, commit {_commit()}; seeds {' '.join(map(str, seeds))}, "
        f"{steps} steps, one run per seed (the same floor and orders for every row). "
        "Deliveries: mean over the seeds and its 95% t-interval. Overlapping pairs: summed "
        "over the steps and seeds (the simulator's rule). Interventions: share of movable "
        "AGV-steps whose action the shield changed (any stage); by liveness: the share the "
        "resolver changed (both averaged over the seeds); yields: the resolver's, summed; mean "
        "action: the controller's own actions (before the shield) averaged over all AGV-steps.",
        "",
        "| controller | shield liveness | deliveries / 1000 steps | per seed | overlapping "
        "pairs | interventions per AGV-step | by liveness | yields | mean action (x, y) | s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table:
        ci = "" if not math.isfinite(r["throughput_ci95"]) else f" ± {r['throughput_ci95']:.1f}"
        lines.append(f"| {r['method']} | {r['liveness']} | {r['throughput']:.1f}{ci} | "
                     f"{' / '.join(f'{v:.0f}' for v in r['per_seed'])} | "
                     f"{r['overlaps']:.0f} | {_fmt(r['interventions'], '.3f')} | "
                     f"{_fmt(r['by_liveness'], '.3f')} | {_fmt(r['yields'], 'd')} | "
                     f"{_mean(r['mean_action'])} | {r['seconds']:.0f} |")
    ratios = _ratios(table)
    if ratios:
        lines += ["", "Mean throughput against the dispatchers with SafeDriver:", "", *ratios]
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--floor", default="warehouse-20", help="a lifelong floor (warehouse-N)")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0], metavar="SEED",
                   help="seeds of the floor and orders, one run each (default 0)")
    p.add_argument("--weights", nargs="*", default=[], metavar="RUN_DIR_OR_FILE",
                   help="lifelong entity run folders or policy files, or a taught family's "
                        f"name ({', '.join(TAUGHT_NAMES)}: its shipped weights at its own "
                        "view) (none: no learned rows)")
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS,
                   metavar="V", help=f"learned rows, any of {' '.join(VARIANTS)} (default all)")
    p.add_argument("--keep-right", type=float, nargs="+", default=[0.3], metavar="RAD",
                   help="lane angles of the 'lanes' rows, in [0, pi/2) (default 0.3)")
    p.add_argument("--baselines", nargs="*", default=list(DEFAULT_BASELINES),
                   choices=BASELINES, metavar="NAME",
                   help=f"reference rows, any of {' '.join(BASELINES)} (default "
                        f"{' '.join(DEFAULT_BASELINES)})")
    p.add_argument("--view", type=int, default=None, metavar="K",
                   help="the policy files' rows see K open pickups and K other AGVs (default: "
                        "the floor's own 4; a taught family always sees its own)")
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    if args.view is not None and args.view < 1:
        p.error(f"--view must be >= 1, got {args.view}")
    if args.steps < 1:
        p.error("--steps must be a positive integer")
    if min(args.seeds) < 0:
        p.error("--seeds must be >= 0")
    if not all(0 <= k < math.pi / 2 for k in args.keep_right):
        p.error("--keep-right angles must be in [0, pi/2)")
    try:
        scenario = sim.get_scenario(args.floor)
    except (KeyError, ValueError) as err:
        p.error(f"--floor {args.floor}: {err}")
    if not getattr(scenario, "lifelong", False):
        p.error(f"--floor {args.floor} is not a lifelong floor")
    if args.view is not None and args.view > scenario.num_agents:
        p.error(f"--view must be at most the floor's fleet ({scenario.num_agents} on "
                f"{args.floor}), got {args.view}")
    for entry in args.weights:
        if entry not in TAUGHT_NAMES and not Path(entry).exists():
            p.error(f"--weights {entry}: no such file or folder (nor a taught family: "
                    f"{', '.join(TAUGHT_NAMES)})")
    table = rows(args.floor, args.steps, args.seeds, args.weights, args.baselines,
                 args.variants, args.keep_right, args.view)
    command = recorded_command(__file__, argv)
    write(table, args.out, command.strip(), args.floor, args.steps, args.seeds)
    return table


if __name__ == "__main__":
    main()
