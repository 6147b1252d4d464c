"""The scale table (issue 17): every method from 3 to 100 AGVs, episodic and lifelong.

    python benchmarks/scale_table.py [--sizes 3 6 10 20 50 100] [--episodes 100 100 50 20 10 5]
        [--floors warehouse-20 warehouse-50 warehouse-100] [--lifelong-steps 1000]
        [--seed 0] [--quick] [--out benchmarks/results/scale]
        [--methods hungarian maddpg-ipf ...] [--no-any-n] [--entity POLICY.safetensors ...]
        [--lifelong-weights RUN_DIR_OR_FILE ...] [--dispatchers hungarian fifo ...] [--view KT:KA]
        [--detour [{squares,discs}]]

Episodic rows (``"NvN"``, the paper's open box scaled with N): ``hungarian``, ``greedy``,
``fifo`` and ``auction`` (its radio range equal to the scenario's sensing range, so that the
decentralized peers see as far as each other), and the learned ``maddpg-ipf`` and
``bicnet-ipf`` as shipped (the 3v3 weights at N = 3, the 6v6 weights zero-shot from N = 6;
no such rows at N = 1, 2, 4 or 5, whose scenes cannot fill their fixed input), each
plain and with ``shield=True`` (:class:`allocator.shield.SafetyShield`). Every method runs
through :func:`sim.evaluate` on the same seeded episodes. Columns: task response, average
time (steps until every task is claimed, the step limit where not), that time over
Hungarian's, overlapping AGV pairs summed over an episode's steps (averaged), the shield's
interventions per movable AGV-step, wall-clock seconds.

Any-N rows (issue 17): ``maddpg-ipf`` / ``bicnet-ipf`` with the shipped any-N weights
(``allocator/weights/any``, the entity-token learners of :mod:`learners.entity`) at every N,
where they ship (``--no-any-n`` leaves them out), the taught family ``bicnet-dagger``
(``allocator.learned.TAUGHT``) too, always with the whole scene in view (its own view,
whatever ``--view`` says), and ``--entity FILE`` the policy file of an
entity learner run (e.g. ``runs/.../best.safetensors``), plain and shielded, named
``<algo>-<reward> any-N`` and ``FILE's algo-reward (FILE)``. ``--methods`` keeps only the
named rows (``hungarian`` is always run: the time column is relative to it). ``--detour``
adds a third row for every learned method: shielded, with the shield's detours round parked
AGVs (:mod:`allocator.detour`): a bare ``--detour`` (or ``--detour squares``) with the first
model, squares (``detour="squares"``, what ``detour=True`` meant before 2026-12-07, so that
the commands recorded then still give their tables); ``--detour discs`` with the planner that
sees parked AGVs as discs with the shield's own gaps (``detour="discs"``, ``detour=True``'s
model now).

Lifelong rows (``warehouse-N``, a backlog of 1.5 N orders): the dispatchers ``hungarian``,
``fifo``, ``greedy`` and ``auction`` (range 3.0, as in ``load_curve.py``) with their default
path follower, and ``hungarian`` with :class:`allocator.SafeDriver`, through
:func:`sim.evaluate_lifelong`, with the overlapping pairs counted at every step;
``--dispatchers`` names the rows instead, ``nearest`` among them
(:class:`sim.controllers.NearestTaskController`: every AGV heads straight for the nearest open
pickup, then its drop-off; no dispatcher). **Learned
lifelong rows** (issue 17): the entity learners trained on a lifelong floor
(``agv train --algo maddpg-e --scenario warehouse-20 ...``), plain and shielded, on every
floor: the shipped lifelong weights where they exist (``allocator/weights/<floor>/`` or
``allocator/weights/lifelong/``; the taught ``maddpg-dagger`` at its own view of 16 pickups
and 16 AGVs, ``allocator.learned.TAUGHT_LIFELONG_VIEW``) and every ``--lifelong-weights`` run
folder or policy file.
The paper's (episodic) weights have no lifelong rows: their observations differ.

Writes ``scale.md``, ``scale.json`` and ``scale.png`` (response and time over Hungarian's
against N) to ``--out``, with the command, seed and machine.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from local_information import detour_label
from provenance import recorded_command

import allocator
import sim
from allocator.learned import scenario_to_run
from sim import physics
from sim.io import atomic_write_text

OUT = Path(__file__).parent / "results" / "scale"
CLASSICAL = ("hungarian", "greedy", "fifo", "auction")
LEARNED = ("maddpg-ipf", "bicnet-ipf")
DISPATCHERS = ("hungarian", "fifo", "greedy", "auction", "hungarian+safe", "fifo+safe",
               "auction+safe")
"""Lifelong rows; ``+safe`` drives with :class:`allocator.SafeDriver` (no AGV ever overlaps
another) instead of the default path follower; ``auction`` talks over radio range
:data:`LIFELONG_COMM_RANGE`, ``auction+safe`` over an unlimited range, as the learned lifelong
policies sense the whole floor (their K nearest AGVs and orders, at any distance)."""
BASELINES = (*DISPATCHERS, "nearest")
"""What ``--dispatchers`` may name: the default rows and ``nearest``
(:class:`sim.controllers.NearestTaskController`, no dispatcher)."""
ALL_LEARNED = tuple(f"{a}-{r}" for a in ("maddpg", "bicnet")
                    for r in ("minidist", "greedy", "ipf"))
LIFELONG_COMM_RANGE = 3.0


def episodic_method(name: str, n: int, shield: bool, sensing_range: float,
                    detour: bool | str = False) -> Any:
    """The controller for one episodic row (``detour``: the shield's detours round parked
    AGVs, learned rows with ``shield`` only)."""
    guard = dict(shield=shield, detour=detour)
    if name.endswith(" any-N"):
        return allocator.make(name.split()[0], scenario=f"{n}v{n}", weights="any", **guard)
    if name.startswith("entity:"):
        from learners.checkpoint import read_metadata

        path = name.split(":", 1)[1]
        meta = read_metadata(path)
        family = meta["algo"].removesuffix("-e")
        return allocator.make(f"{family}-{meta['reward']}", scenario=f"{n}v{n}",
                              checkpoint=path, **guard)
    if name in LEARNED:
        weights = "3v3" if n <= 3 else "6v6"
        return allocator.make(name, scenario=weights, **guard)
    if name == "auction":
        return allocator.make("auction", comm_range=sensing_range)
    return allocator.make(name)


def paper_fits(n: int) -> bool:
    """Whether the paper's fixed-size weights can read an NvN scene: the 3v3 ones need 3 tasks
    and 2 other AGVs in view, the 6v6 ones (N > 3) 6 and 5."""
    return n == 3 or n >= 6


class OverlapCounter:
    """Wraps a lifelong controller and counts the overlapping AGV pairs before every step."""

    def __init__(self, controller: Any) -> None:
        self.controller = controller
        self.pairs = 0
        self.env: Any = None

    def reset(self, env: Any) -> None:
        self.env = env
        self.controller.reset(env)

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        env = self.env
        n = env.num_agents
        eye = torch.eye(n, dtype=torch.bool)
        # The simulator's own overlap rule (the step's ``collision_pairs``).
        _, pairs = physics.collisions(physics.pair_distances(env.agent_pos), ~env.done,
                                      env.world.agent_radius, eye, torch.ones_like(eye).triu(1))
        self.pairs += int(pairs.sum())
        return self.controller.act(obs)


def episodic_rows(sizes: list[int], episodes: list[int], seed: int,
                  methods: list[str] | None = None, any_n: bool = False,
                  entity: list[str] | None = None,
                  view: tuple[int, int] | None = None, detour: bool | str = False
                  ) -> list[dict]:
    """The episodic rows; ``view`` (K_t, K_a): the task and AGV slots every row observes
    (capped at M and N - 1), except the paper's weights (``LEARNED``), whose input size is
    fixed; None: the scenarios' own (6 and 5). ``detour``: every learned row also runs
    shielded with the shield's detours round parked AGVs (``"squares"`` or ``"discs"``:
    :class:`allocator.detour.ParkedDetour`'s model; True: its default, discs)."""
    rows = []
    learned = list(LEARNED)
    if any_n:  # the families whose any-N weights ship, the taught ones too
        from allocator.learned import TAUGHT_NAMES, any_n_weights_path

        learned += [f"{m} any-N" for m in LEARNED + TAUGHT_NAMES
                    if any_n_weights_path(*m.split("-", 1)).is_file()]
    learned += [f"entity:{p}" for p in entity or []]
    keep = None if methods is None else set(methods) | {"hungarian"}
    for n, eps in zip(sizes, episodes, strict=True):
        scenario = f"{n}v{n}"
        base = sim.get_scenario(scenario)
        rng = float(base.sensing_range)
        viewed = base if view is None else sim.get_scenario(
            scenario, k_tasks=min(view[0], n), k_agents=min(view[1], n - 1))
        hung_time = None
        guards = [(False, False), (True, False)] + ([(True, detour)] if detour else [])
        variants = [(m, False, False) for m in CLASSICAL] + [(m, s, d) for m in learned
                                                             for s, d in guards]
        if keep is not None:
            variants = [(m, s, d) for m, s, d in variants
                        if m in keep or m.split()[0] in keep and m.endswith("any-N")
                        or m.startswith("entity:")]
        if not paper_fits(n):  # the paper's weights read a fixed observation (3v3's or 6v6's)
            skipped = sorted({m for m, _, _ in variants if m in LEARNED})
            if skipped:
                print(f"{scenario}: no rows for the paper's weights ({', '.join(skipped)}): "
                      "their input is 3v3's or 6v6's, which a scene of 1, 2, 4 or 5 tasks "
                      "cannot fill")
            variants = [v for v in variants if v[0] not in LEARNED]
        for name, shield, det in variants:
            ctl = episodic_method(name, n, shield, rng, det)
            t = time.perf_counter()
            # the paper's weights see the scenario's own slots; a taught family its own view
            # (the whole scene); every other row --view
            scen = base if name in LEARNED else scenario_to_run(ctl, viewed)
            m = sim.evaluate(ctl, scen, episodes=eps, seed=seed, batch_size=eps)
            seconds = time.perf_counter() - t
            safety = getattr(ctl, "safety", None)
            if name == "hungarian":
                hung_time = m.avg_time
            row = dict(kind="episodic", scenario=scenario, n=n, method=name, shield=shield,
                       detour=det, view=f"{scen.k_tasks}:{scen.k_agents}",
                       episodes=eps, response=m.response_rate, avg_time=m.avg_time,
                       time_vs_hungarian=m.avg_time / hung_time if hung_time else math.nan,
                       overlaps=m.collisions,
                       interventions=(safety.intervention_rate() if safety is not None
                                      else None),
                       seconds=seconds)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def policy_file(path: str | Path) -> Path:
    """A policy file, or a run folder's ``best.safetensors`` (else its ``policy.safetensors``)."""
    p = Path(path)
    if p.is_dir():
        best = p / "best.safetensors"
        return best if best.is_file() else p / "policy.safetensors"
    return p


def lifelong_learned(floor: str, weights: list[str]) -> list[tuple[str, dict]]:
    """(row name, ``allocator.make`` keywords) of the learned rows on a floor: shipped
    lifelong weights where they exist (a taught family's too), then every
    ``--lifelong-weights`` entry."""
    from allocator.learned import TAUGHT_NAMES, any_n_weights_path, weights_path
    from learners.checkpoint import read_metadata

    out = []
    for name in ALL_LEARNED + TAUGHT_NAMES:
        algo, reward = name.split("-")
        if weights_path(algo, reward, floor).is_file() or \
                any_n_weights_path(algo, reward, lifelong=True).is_file():
            out.append((f"{name} (shipped)", dict(name=name, weights="auto")))
    for w in weights:
        path = policy_file(w)
        meta = read_metadata(path)
        name = f"{meta['algo'].removesuffix('-e')}-{meta['reward']}"
        out.append((f"{name} ({w})", dict(name=name, checkpoint=str(path))))
    return out


def lifelong_rows(floors: list[str], steps: int, seed: int, weights: list[str] | None = None,
                  dispatchers: list[str] | None = None) -> list[dict]:
    rows = []
    for floor in floors:
        variants: list[tuple[str, bool, Any]] = []
        for name in dispatchers or DISPATCHERS:
            if name == "auction":
                inner = allocator.make("auction", comm_range=LIFELONG_COMM_RANGE)
            elif name == "hungarian+safe":
                inner = allocator.HungarianDispatcher(driver=allocator.SafeDriver())
            elif name == "fifo+safe":
                inner = allocator.FifoDispatcher(driver=allocator.SafeDriver())
            elif name == "auction+safe":
                inner = allocator.AuctionDispatcher(math.inf, driver=allocator.SafeDriver())
            elif name == "nearest":
                from sim.controllers import NearestTaskController

                inner = NearestTaskController()
            else:
                inner = allocator.make(name)
            variants.append((name, False, inner))
        for label, kw in lifelong_learned(floor, weights or []):
            kw = dict(kw)
            name = kw.pop("name")
            for shield in (False, True):
                variants.append((label, shield, allocator.make(name, scenario=floor,
                                                               shield=shield, **kw)))
        for name, shield, inner in variants:
            ctl = OverlapCounter(inner)
            t = time.perf_counter()
            scen = sim.get_scenario(scenario_to_run(inner, floor))  # a taught family: its view
            m = sim.evaluate_lifelong(ctl, scen, steps=steps, seed=seed)
            seconds = time.perf_counter() - t
            safety = getattr(inner, "safety", None)
            row = dict(kind="lifelong", scenario=floor, n=int(floor.split("-")[1]),
                       method=name, shield=shield, view=f"{scen.k_pickups}:{scen.k_agents}",
                       steps=steps, throughput=m.throughput,
                       throughput_bound=m.throughput_bound, wait_p95=m.wait_p95,
                       lost=m.lost, overlaps_per_1000_steps=1000.0 * ctl.pairs / steps,
                       interventions=(safety.intervention_rate() if safety is not None
                                      else None),
                       seconds=seconds)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def _fmt(x: Any, spec: str = ".3f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return format(x, spec)


def write(rows: list[dict], out: Path, command: str, seed: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# Scale table: every method from 3 to 100 AGVs",
        "",
        f"`{command}` on {platform.machine()}, Python {platform.python_version()}, torch "
        f"{torch.__version__}, {stamp}; seed {seed} (the same episodes and orders for every "
        "method). Learned rows: the shipped weights (3v3 at N = 3, 6v6 zero-shot above), "
        "plain and shielded (`shield=True`; `yes + squares detour` / `yes + discs detour`: with "
        "the shield's detours round parked AGVs, `detour=\"squares\"` / `\"discs\"`); `any-N` "
        "rows: the shipped any-N weights "
        "(`allocator/weights/any`; `bicnet-dagger`, taught by DAgger, with the whole scene "
        "in view), `entity:FILE` rows: an entity learner's policy file, "
        "both run zero-shot at every N. Auction: radio range = the scenario's sensing "
        "range (episodic), 3.0 (lifelong `auction`), unlimited (lifelong `auction+safe`, as "
        "the learned lifelong policies sense the whole floor); `+safe`: driven by SafeDriver.",
    ]
    if any(r["kind"] == "episodic" for r in rows):
        lines += [
            "",
            "## Episodic (`NvN`)",
            "",
            "| scenario | method | shield | episodes | response | avg time | time / Hungarian | "
            "overlapping pairs per episode | interventions per AGV-step | s |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
    for r in (r for r in rows if r["kind"] == "episodic"):
        guard = "yes" + detour_label(r.get("detour")) if r["shield"] else "no"
        lines.append(
            f"| {r['scenario']} | {r['method']} | {guard} | "
            f"{r['episodes']} | {_fmt(r['response'])} | {_fmt(r['avg_time'], '.2f')} | "
            f"{_fmt(r['time_vs_hungarian'], '.2f')} | {_fmt(r['overlaps'], '.2f')} | "
            f"{_fmt(r['interventions'])} | {r['seconds']:.0f} |")
    life = [r for r in rows if r["kind"] == "lifelong"]
    if life:
        lines += ["", "## Lifelong (`warehouse-N`, backlog of 1.5 N orders)", "",
                  "| floor | method | shield | steps | deliveries / 1000 steps | bound | "
                  "p95 wait | lost | overlapping pairs / 1000 steps | "
                  "interventions per AGV-step | s |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in life:
            lines.append(
                f"| {r['scenario']} | {r['method']} | {'yes' if r['shield'] else 'no'} | "
                f"{r['steps']} | "
                f"{_fmt(r['throughput'], '.1f')} | {_fmt(r['throughput_bound'], '.0f')} | "
                f"{_fmt(r['wait_p95'], '.0f')} | {r['lost']} | "
                f"{_fmt(r['overlaps_per_1000_steps'], '.1f')} | "
                f"{_fmt(r.get('interventions'))} | {r['seconds']:.0f} |")
    atomic_write_text(out / "scale.md", "\n".join(lines) + "\n")
    meta = dict(command=command, seed=seed, date=stamp, rows=rows)
    atomic_write_text(out / "scale.json", json.dumps(meta, indent=1) + "\n")
    plot(rows, out / "scale.png")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim.io import atomic_save

    ep = [r for r in rows if r["kind"] == "episodic"]
    if not ep:
        return
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    keys = sorted({(r["method"], r["shield"], detour_label(r.get("detour"))) for r in ep},
                  key=lambda k: (k[0] not in CLASSICAL, k))
    for method, shield, detour in keys:
        pts = sorted((r["n"], r["response"], r["time_vs_hungarian"]) for r in ep
                     if r["method"] == method and r["shield"] == shield
                     and detour_label(r.get("detour")) == detour)
        n = [p[0] for p in pts]
        label = method + (" + shield" + detour if shield else "")
        style = ":" if detour else "--" if shield else "-"
        ax1.plot(n, [p[1] for p in pts], style, marker="o", label=label)
        ax2.plot(n, [p[2] for p in pts], style, marker="o", label=label)
    for ax, name in ((ax1, "task response"), (ax2, "avg time / Hungarian's")):
        ax.set_xscale("log")
        ax.set_xlabel("AGVs (N tasks)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    ax1.legend(fontsize=7)
    fig.tight_layout()
    atomic_save(lambda f: fig.savefig(f, format="png", dpi=120), path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="*", default=[3, 6, 10, 20, 50, 100],
                   help="episodic fleet sizes (none: lifelong rows only)")
    p.add_argument("--episodes", type=int, nargs="+", default=None,
                   help="episodes per size (default 100 100 50 20 10 5)")
    p.add_argument("--floors", nargs="*", default=["warehouse-20", "warehouse-50",
                                                   "warehouse-100"])
    p.add_argument("--lifelong-steps", type=int, default=1000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quick", action="store_true", help="3 6 20, few episodes, one floor")
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--methods", nargs="+", default=None,
                   help="episodic rows to run (default all; hungarian is always run)")
    p.add_argument("--any-n", action=argparse.BooleanOptionalAction, default=True,
                   help="the learned rows with the shipped any-N weights, where they ship "
                        "(default on; --no-any-n leaves them out)")
    p.add_argument("--entity", nargs="+", default=[], metavar="FILE",
                   help="add rows for these entity-learner policy files")
    p.add_argument("--view", default=None, metavar="KT:KA",
                   help="episodic rows observe KT task and KA AGV slots (capped at M and "
                        "N - 1; not the paper's weights, whose input is fixed; default the "
                        "scenario's 6:5)")
    p.add_argument("--detour", nargs="?", const="squares", default=False,
                   choices=("squares", "discs"),
                   help="learned episodic rows also run shielded with detours round parked "
                        "AGVs: squares (a bare --detour, as in the commands recorded before "
                        "2026-12-07) or discs (the planner with the shield's own gaps, "
                        "detour=True's model now)")
    p.add_argument("--lifelong-weights", nargs="+", default=[], metavar="RUN_OR_FILE",
                   help="add lifelong rows for these lifelong entity runs or policy files")
    p.add_argument("--dispatchers", nargs="+", default=None, choices=BASELINES,
                   help=f"lifelong baseline rows to run (default {' '.join(DISPATCHERS)})")
    args = p.parse_args(argv)
    if args.quick:
        args.sizes, args.episodes = [3, 6, 20], [20, 20, 4]
        args.floors, args.lifelong_steps = ["warehouse-20"], 200
    default_eps = {3: 100, 6: 100, 10: 50, 20: 20, 50: 10, 100: 5}
    episodes = args.episodes or [default_eps.get(n, 10) for n in args.sizes]
    if len(episodes) != len(args.sizes):
        p.error(f"--episodes needs one count per size ({len(args.sizes)}), got "
                f"{len(episodes)}")
    if any(n < 1 for n in args.sizes) or any(e < 1 for e in episodes):
        p.error("--sizes and --episodes must be positive integers")
    if args.lifelong_steps < 1:
        p.error("--lifelong-steps must be a positive integer")
    view = None
    if args.view is not None:
        try:
            view = tuple(int(x) for x in args.view.split(":"))
        except ValueError:
            view = ()
        if len(view) != 2 or view[0] < 1 or view[1] < 0:
            p.error(f"--view must be KT:KA with KT >= 1 and KA >= 0 (e.g. 10:10), got "
                    f"{args.view!r}")
    torch.set_num_threads(1)
    np.seterr(all="ignore")
    rows = episodic_rows(args.sizes, episodes, args.seed, args.methods, args.any_n,
                         args.entity, view, args.detour)
    for w in args.lifelong_weights:
        if not policy_file(w).is_file():
            p.error(f"--lifelong-weights {w}: no policy file there")
    rows += lifelong_rows(args.floors, args.lifelong_steps, args.seed, args.lifelong_weights,
                          args.dispatchers)
    write(rows, args.out, recorded_command(__file__, argv), args.seed)


if __name__ == "__main__":
    main()
