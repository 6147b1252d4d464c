"""Scoring a controller in lifelong operation: throughput, waits, lead times, deadlines.

:func:`evaluate_lifelong` runs R independent runs of a lifelong scenario for a number of steps,
``batch_size`` runs at a time, and returns :class:`LifelongMetrics`. Each run's starting fleet
and stream key (its orders and breakdowns, :mod:`sim.streams`) depend only on the seed and the
run's index, so every controller sees the same orders and breakdowns, whatever the batching.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim import streams
from sim.checks import check_count, check_device, check_seed
from sim.lifelong import LifelongEnv, LifelongScenario
from sim.orders import (
    ASSIGNED,
    BROKEN,
    CARRYING,
    LOADED,
    OPEN,
    TO_PICKUP,
    Poisson,
    Trace,
    read_trace,
)
from sim.orders import check_faults as _check_faults
from sim.scenarios import get_scenario
from sim.state import LifelongContext, LifelongState
from sim.world import World

__all__ = ["LifelongMetrics", "evaluate_lifelong", "lifelong_runs"]

_SEED_MIX = 1_000_003


@dataclass(frozen=True)
class LifelongMetrics:
    """What :func:`evaluate_lifelong` measured, over every run.

    Attributes
    ----------
    throughput : float
        Orders delivered per 1000 steps (per run, averaged over the runs).
    throughput_bound : float
        Upper bound for the scenario (:meth:`sim.lifelong.LifelongScenario.throughput_bound`):
        every AGV always on a shortest loaded trip.
    wait_mean, wait_p95 : float
        Release to pickup, steps, over the orders picked up (nan if none). An order a
        controller leaves behind for good is in neither: see ``wait_p95_all`` and
        ``oldest_open``.
    wait_mean_all, wait_p95_all : float
        The same over the orders picked up and the orders still waiting at the end (open or
        assigned, not yet picked up), these counted with their age so far (a lower bound of
        their wait), so that a controller that starves orders cannot look fast (nan if none).
    oldest_open : int
        Age in steps at the end of the oldest order still waiting to be picked up, over every
        run (0 if none).
    lead_mean, lead_p95 : float
        Release to delivery, steps, over the orders delivered (nan if none).
    deadline_miss_rate : float
        Among orders with a deadline that were delivered or are overdue at the end, the
        fraction delivered late or not at all (0 when no order had a deadline).
    collisions_per_1000 : float
        Overlapping AGV pairs summed over the steps, per 1000 steps and run.
    utilization : float
        Fraction of working (not broken) AGV-steps spent on an order (to pickup or loaded).
    reassignments : float
        Times an assigned order went to another AGV, per run.
    lost : int
        Orders released but in no state at the end, over all runs: always 0.
    released, delivered : int
        Over all runs.
    open_at_end : int
        Orders released but not delivered at the end, over all runs.
    runs, steps : int
    seconds : float
        Wall-clock time of the evaluation.
    time : np.ndarray, shape (K,)
        End step of each window of the series.
    throughput_series : np.ndarray, shape (K,)
        Deliveries per 1000 steps in each window, averaged over the runs.
    wait_series : np.ndarray, shape (K,)
        Mean wait of the orders picked up in each window (nan where none).
    open_series : np.ndarray, shape (K,)
        Mean number of orders released and not yet picked up at each window's end.
    """

    throughput: float
    throughput_bound: float
    wait_mean: float
    wait_p95: float
    lead_mean: float
    lead_p95: float
    deadline_miss_rate: float
    collisions_per_1000: float
    utilization: float
    reassignments: float
    lost: int
    released: int
    delivered: int
    open_at_end: int
    wait_mean_all: float
    wait_p95_all: float
    oldest_open: int
    runs: int
    steps: int
    seconds: float
    time: np.ndarray = field(repr=False)
    throughput_series: np.ndarray = field(repr=False)
    wait_series: np.ndarray = field(repr=False)
    open_series: np.ndarray = field(repr=False)

    def summary(self) -> dict[str, float]:
        """The scalar figures as a dict (for tables)."""
        return {k: getattr(self, k) for k in (
            "throughput", "throughput_bound", "wait_mean", "wait_p95", "lead_mean",
            "lead_p95", "deadline_miss_rate", "collisions_per_1000", "utilization",
            "reassignments", "lost", "released", "delivered", "open_at_end",
            "wait_mean_all", "wait_p95_all", "oldest_open", "runs", "steps")}


class _NoReward:
    """Evaluation needs no reward terms."""

    zeroes_inactive = True

    def __call__(self, state: LifelongState, ctx: LifelongContext) -> dict[str, Tensor]:
        return {}


def _scenario(scenario: Any, steps: int, arrival_rate: Any, faults: Any, trace: Any,
              options: dict[str, Any]) -> LifelongScenario:
    if isinstance(scenario, (str, LifelongScenario, World)):
        sc = get_scenario(scenario, **options)
    else:
        raise ValueError(f"scenario must be a lifelong scenario name such as 'warehouse-50', a "
                         f"LifelongScenario or a floor, got {type(scenario).__name__}")
    if not isinstance(sc, LifelongScenario):
        raise ValueError(f"scenario {getattr(sc, 'name', sc)!r} is episodic; evaluate_lifelong "
                         "needs a lifelong one ('warehouse-20', 'warehouse-50', "
                         "'warehouse-100', or a floor with num_agents=); use sim.evaluate for "
                         "episodes")
    given = [name for name, v in (("arrival_rate", arrival_rate), ("trace", trace))
             if v is not None]
    if len(given) > 1:
        raise ValueError("give at most one of arrival_rate and trace")
    changes: dict[str, Any] = {"max_steps": steps}
    if arrival_rate is not None:
        changes["arrivals"] = Poisson(arrival_rate)
    if trace is not None:
        if isinstance(trace, (str, os.PathLike)):
            trace = read_trace(trace, sc.world)
        if not isinstance(trace, Trace):
            raise ValueError(f"trace must be a CSV path or a sim.Trace, got "
                             f"{type(trace).__name__}")
        changes["arrivals"] = trace
    if faults is not None:
        changes["faults"] = _check_faults(faults, sc.num_agents)
    return sc.with_options(**changes)


def lifelong_runs(scenario: LifelongScenario, runs: int, seed: int,
                  device: str | torch.device = "cpu") -> tuple[Tensor, Tensor]:
    """The starting fleets (R, N, 2) and stream keys (R,) of :func:`evaluate_lifelong`'s runs
    for a seed: run r's depend only on the seed and r."""
    runs = check_count("runs", runs)
    seed = check_seed(seed, bits=63)
    dev = check_device(device)
    generator = torch.Generator(device=dev)
    generator.manual_seed(seed * _SEED_MIX % 2**63)
    agents = scenario.spawn(runs, generator, dev)
    keys = streams.derive_key(torch.tensor(seed, dtype=torch.int64, device=dev),
                              torch.arange(runs, device=dev))
    return agents, keys & ((1 << 62) - 1)


def evaluate_lifelong(
    controller: Any,
    scenario: str | LifelongScenario | World = "warehouse-20",
    steps: int = 2000,
    seed: int = 0,
    arrival_rate: float | None = None,
    faults: Any = None,
    trace: Any = None,
    runs: int = 1,
    batch_size: int = 64,
    device: str | torch.device = "cpu",
    window: int = 100,
    progress: bool = False,
    **scenario_options: Any,
) -> LifelongMetrics:
    """Run a controller in lifelong operation and measure throughput, waits and lead times.

    Parameters
    ----------
    controller : Controller or callable
        ``act(obs)`` (or a callable) mapping (B, N, O) lifelong observations to (B, N, 2)
        actions; an optional ``reset(env)`` is called once per batch of runs, after the fleets
        are placed. A centralized dispatcher keeps the env and calls ``env.assign(...)``.
    scenario : str, LifelongScenario or World
        ``"warehouse-20"``, ``"warehouse-50"``, ``"warehouse-100"``, any ``"warehouse-N"``,
        a lifelong scenario, or a floor (then ``num_agents=`` is needed).
    steps : int
        Steps of every run.
    seed : int
        In [0, 2**63): the same seed gives the same fleets, orders and breakdowns for every
        controller and every ``batch_size``.
    arrival_rate : float, optional
        Poisson arrivals at this rate (orders per step) instead of the scenario's.
    faults : sim.Breakdowns or list of (step, agent, repair_steps), optional
    trace : str, path or sim.Trace, optional
        Replay a CSV order log instead of generated orders.
    runs : int
        Independent runs R.
    batch_size : int
        Runs simulated at once.
    device : str or torch.device
    window : int
        Steps per point of the time series.
    progress : bool
        Show a progress bar (tqdm).
    **scenario_options
        Other scenario fields (``service_steps=2``, ``num_agents=20`` for a floor, ...).

    Returns
    -------
    LifelongMetrics

    Raises
    ------
    ValueError
        Naming the argument: an episodic or unknown scenario, counts that are not positive
        integers, a seed outside [0, 2**63), a rate that is not positive and finite, a bad
        trace or fault schedule, a controller whose actions are not finite (B, N, 2) numbers.

    Examples
    --------
    >>> import sim
    >>> from sim.controllers import NearestTaskController
    >>> m = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=50, seed=0)
    >>> m.lost
    0
    """
    from sim.evaluate import _as_policy

    act = _as_policy(controller)
    steps = check_count("steps", steps)
    runs = check_count("runs", runs)
    batch_size = check_count("batch_size", batch_size)
    window = check_count("window", window)
    seed = check_seed(seed, bits=63)
    dev = check_device(device)
    sc = _scenario(scenario, steps, arrival_rate, faults, trace, scenario_options)
    start = time.perf_counter()
    agents, keys = lifelong_runs(sc, runs, seed, dev)
    K = -(-steps // window)
    delivered_series = np.zeros((runs, K))
    open_series = np.zeros((runs, K))
    wait_sum = np.zeros(K)
    wait_count = np.zeros(K)
    waits: list[np.ndarray] = []
    ages: list[np.ndarray] = []  # orders still waiting at the end of each batch of runs
    leads: list[np.ndarray] = []
    late = due = 0
    collisions = 0.0
    busy = working = 0.0
    reassign = lost = released = delivered = open_end = 0
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=runs * steps, desc=f"lifelong {sc.name}", unit="step")
    for first in range(0, runs, batch_size):
        rows = slice(first, min(first + batch_size, runs))
        b = rows.stop - first
        env = LifelongEnv(sc, num_envs=b, reward=_NoReward(), seed=seed, device=dev)
        obs = env.set_state(agents[rows], keys[rows])
        reset = getattr(controller, "reset", None)
        if callable(reset):
            reset(env)
        for t in range(steps):
            obs, _, _, info = env.step(act(obs))
            k = t // window
            ev = env.events
            o = env.orders
            n_del = ev.delivered.sum(1)
            delivered_series[rows, k] += n_del.cpu().numpy()
            if (t + 1) % window == 0 or t == steps - 1:
                open_series[rows, k] = (o.count(OPEN) + o.count(ASSIGNED)).cpu().numpy()
            if bool(ev.picked_up.any()):
                w = (o.picked - o.release)[ev.picked_up].cpu().numpy()
                waits.append(w)
                wait_sum[k] += w.sum()
                wait_count[k] += len(w)
            if bool(n_del.any()):
                d = ev.delivered
                leads.append((o.finished - o.release)[d].cpu().numpy())
                dl = o.deadline[d]
                has = dl >= 0
                due += int(has.sum())
                late += int((has & (o.finished[d] > dl)).sum())
            collisions += float(info["collision_pairs"].sum())
            st = env.agent_status
            busy += float(((st == TO_PICKUP) | (st == CARRYING)).sum())
            working += float((st != BROKEN).sum())
            if bar is not None:
                bar.update(b)
        o = env.orders
        overdue = (o.deadline >= 0) & (o.deadline < env.steps.unsqueeze(1)) & (
            (o.status == OPEN) | (o.status == ASSIGNED) | (o.status == LOADED))
        due += int(overdue.sum())
        late += int(overdue.sum())
        waiting = (o.status == OPEN) | (o.status == ASSIGNED)
        ages.append((env.steps.unsqueeze(1) - o.release)[waiting].cpu().numpy())
        reassign += int(env.reassignments.sum())
        lost += int(env.order_balance().abs().sum())
        released += int(env.released.sum())
        delivered += int(env.delivered.sum())
        open_end += int((o.count(OPEN) + o.count(ASSIGNED) + o.count(LOADED)).sum())
    if bar is not None:
        bar.close()
    wait = np.concatenate(waits) if waits else np.zeros(0)
    lead = np.concatenate(leads) if leads else np.zeros(0)
    age = np.concatenate(ages) if ages else np.zeros(0)
    wait_all = np.concatenate([wait, age])
    ends = np.minimum(np.arange(1, K + 1) * window, steps)
    widths = ends - np.arange(K) * window

    def stat(values: np.ndarray, q: float | None) -> float:
        if not len(values):
            return float("nan")
        return float(np.mean(values) if q is None else np.percentile(values, q))

    with np.errstate(invalid="ignore", divide="ignore"):
        wait_series = np.where(wait_count > 0, wait_sum / np.maximum(wait_count, 1), np.nan)
    return LifelongMetrics(
        throughput=1000.0 * delivered / (runs * steps),
        throughput_bound=sc.throughput_bound(steps),
        wait_mean=stat(wait, None), wait_p95=stat(wait, 95),
        lead_mean=stat(lead, None), lead_p95=stat(lead, 95),
        deadline_miss_rate=late / due if due else 0.0,
        collisions_per_1000=1000.0 * collisions / (runs * steps),
        utilization=busy / working if working else 0.0,
        reassignments=reassign / runs,
        lost=lost, released=released, delivered=delivered, open_at_end=open_end,
        wait_mean_all=stat(wait_all, None), wait_p95_all=stat(wait_all, 95),
        oldest_open=int(age.max()) if len(age) else 0, runs=runs, steps=steps,
        seconds=time.perf_counter() - start,
        time=ends, throughput_series=1000.0 * delivered_series.mean(0) / widths,
        wait_series=wait_series, open_series=open_series.mean(0),
    )
