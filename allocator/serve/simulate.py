"""``agv serve --simulate``: the lifelong simulator stands in for the fleet.

The simulator's AGVs (``sim-00``, ``sim-01``, ...) move with the simulator's physics
(:func:`sim.make_env` on the service's floor, with no orders of its own) and are driven along
the service's plan by :class:`allocator.dispatch.WaypointDriver`. After every step they report
what a real fleet would, through the same rules as the HTTP API: their positions and status,
``picked_up`` on reaching the pickup of the order they were given, ``delivered`` on reaching
its drop-off, and ``fault`` / ``repaired`` when the simulator's breakdowns
(``--sim-faults RATE:REPAIR``) strike and end.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import numpy as np

from allocator.serve.fleet import Conflict, Fleet, NotFound

__all__ = ["SimulatedFleet"]

log = logging.getLogger("agv.serve")

_BROKEN = 3  # sim.orders.BROKEN
_NEVER = 2**60


class _DriverView:
    """What :class:`WaypointDriver` reads of an env, with the service's plan as targets."""

    def __init__(self, env: Any) -> None:
        self.env = env
        self.world = env.world
        self.target = np.zeros((1, env.num_agents, 2), dtype=np.float32)
        self.has = np.zeros((1, env.num_agents), dtype=bool)

    @property
    def agent_pos(self) -> Any:
        return self.env.agent_pos

    @property
    def agent_vel(self) -> Any:
        return self.env.agent_vel

    def targets(self) -> tuple[Any, Any]:
        import torch

        return torch.as_tensor(self.target), torch.as_tensor(self.has)


class SimulatedFleet:
    """A simulated fleet on the service's floor, stepping in the background.

    Parameters
    ----------
    fleet : Fleet
    scenario : str
        A lifelong scenario (``warehouse-20``): its fleet size; its floor when the service
        has none of its own (the service's floor is used otherwise).
    rate : float
        Steps per second (10 is real time at the simulator's dt of 0.1 s).
    faults : str, optional
        ``"RATE:REPAIR"``: breakdowns per AGV-step and repair steps.
    seed : int
    """

    def __init__(self, fleet: Fleet, scenario: str, rate: float = 10.0,
                 faults: str | None = None, seed: int = 0) -> None:
        import sim
        from allocator.dispatch import WaypointDriver

        if not (isinstance(rate, (int, float)) and 0 < rate <= 1000):
            raise ValueError(f"--sim-rate must be in (0, 1000] steps per second, got {rate!r}")
        scen = sim.get_scenario(scenario)
        n = getattr(scen, "num_agents", None)
        if n is None or not getattr(scen, "lifelong", True) or \
                not hasattr(scen, "throughput_bound"):
            raise ValueError(f"--simulate {scenario}: not a lifelong scenario (e.g. "
                             "warehouse-20)")
        world = fleet.world
        options: dict[str, Any] = {}
        if faults:
            try:
                r, rep = faults.split(":")
                options["faults"] = sim.Breakdowns(float(r), repair_steps=int(rep))
            except ValueError as err:
                raise ValueError(f"--sim-faults must be RATE:REPAIR (e.g. 0.0005:60): {err}"
                                 ) from None
        # The service's orders come from its clients: none arrive in the simulator itself.
        self.env = sim.make_env(world, num_agents=n, seed=seed, arrivals=sim.Backlog(0),
                                max_steps=_NEVER, **options)
        self.fleet = fleet
        self.rate = float(rate)
        width = max(2, len(str(n - 1)))
        self.ids = [f"sim-{i:0{width}d}" for i in range(n)]
        self.view = _DriverView(self.env)
        self.driver = WaypointDriver()
        self.driver.reset(self.view)
        self.radius = float(world.capture_radius)
        self.steps = 0
        self._restore()
        self._report(persist=True)

    def _restore(self) -> None:
        """Start the simulated AGVs where the database last saw them, if it did."""
        known = [self.fleet.agents.get(i) for i in self.ids]
        if not all(a is not None for a in known):
            return
        pos = np.array([[[a.x, a.y] for a in known]], dtype=np.float32)
        try:
            self.env.set_state(pos)
        except ValueError as err:  # e.g. positions too close for the simulator
            log.warning("simulated AGVs start afresh: %s", err)

    def _report(self, persist: bool) -> bool:
        """Positions, statuses and events of the last step into the fleet; True if anything
        the plan depends on changed."""
        fleet = self.fleet
        pos = self.env.agent_pos[0].double().numpy()
        broken = (self.env.fleet.status[0] == _BROKEN).numpy()
        changed = False
        for i, aid in enumerate(self.ids):
            a = fleet.agents.get(aid)
            p = (float(pos[i, 0]), float(pos[i, 1]))
            try:
                if a is None:
                    fleet.put_agent(aid, p, "broken" if broken[i] else "idle")
                    changed = True
                    continue
                if broken[i] and a.status != "broken":
                    fleet.event(aid, "fault", None)
                    changed = True
                elif not broken[i] and a.status == "broken":
                    fleet.event(aid, "repaired", None)
                    changed = True
                if a.order is not None and a.status != "broken":
                    o = fleet.orders.get(a.order)
                    if o is not None:
                        goal = o.dropoff if a.loaded else o.pickup
                        if np.hypot(p[0] - goal[0], p[1] - goal[1]) <= self.radius:
                            fleet.event(aid, "delivered" if a.loaded else "picked_up", o.id)
                            changed = True
                status = a.status if a.status in ("broken", "charging") else \
                    ("busy" if a.order is not None else "idle")
                before = fleet.epoch
                fleet.put_agent(aid, p, status, persist=persist)
                changed |= fleet.epoch != before
            except (Conflict, NotFound) as err:  # e.g. an order withdrawn meanwhile
                log.info("simulated %s: %s", aid, err)
        return changed

    def _targets(self) -> None:
        fleet = self.fleet
        self.view.has[:] = False
        for i, aid in enumerate(self.ids):
            a = fleet.agents.get(aid)
            if a is None or a.order is None or a.status == "broken":
                continue
            o = fleet.orders.get(a.order)
            if o is None:
                continue
            self.view.target[0, i] = o.dropoff if a.loaded else o.pickup
            self.view.has[0, i] = True

    def step(self) -> None:
        """One simulator step along the current plan (no reporting)."""
        actions = self.driver.act(self.view)
        self.env.step(actions)
        self.steps += 1

    async def run(self, app: Any) -> None:
        """Step at ``rate`` Hz and report after every step, until cancelled."""
        period = 1.0 / self.rate
        every = max(1, int(round(self.rate)))  # positions stored about once a second
        dispatch = app.state.dispatch
        nxt = time.perf_counter()
        while True:
            self._targets()
            await asyncio.to_thread(self.step)
            if self._report(persist=self.steps % every == 0):
                dispatch.touched(structural=True)
            elif self.steps % 2 == 0:  # moving AGVs on the event stream at ~5 Hz
                dispatch.publish()
            nxt += period
            delay = nxt - time.perf_counter()
            if delay < -1.0:  # fell far behind (a slow machine): do not try to catch up
                nxt = time.perf_counter()
            await asyncio.sleep(max(0.0, delay))
