"""The shared, batched AGV simulator: physics, scenarios, rewards, metrics, rendering.

Heavy or optional pieces (PettingZoo, matplotlib) are imported on first use.
"""

from __future__ import annotations

from typing import Any

from sim.env import AGVEnv, make_env
from sim.evaluate import Metrics, evaluate
from sim.lifelong import LifelongEnv, LifelongScenario
from sim.lifelong_eval import LifelongMetrics, evaluate_lifelong
from sim.observations import LifelongObsLayout, ObsLayout
from sim.orders import Backlog, Breakdowns, FaultSchedule, Poisson, Trace, read_trace
from sim.rewards import REWARDS, make_reward
from sim.scenarios import SCENARIOS, Scenario, get_scenario, scenario_names
from sim.state import SimState, StepContext
from sim.world import Physics, World

__all__ = [
    "AGVEnv", "SimState", "StepContext", "make_env", "REWARDS", "make_reward", "SCENARIOS",
    "Scenario", "get_scenario", "scenario_names", "Physics", "World", "ObsLayout",
    "evaluate", "Metrics", "pettingzoo_env", "ipf_field", "render_scene", "render_episode",
    "render_field", "LifelongEnv", "LifelongScenario", "LifelongMetrics", "evaluate_lifelong",
    "LifelongObsLayout", "Poisson", "Backlog", "Trace", "read_trace", "Breakdowns",
    "FaultSchedule", "load_floor", "warehouse_floor", "save_floor_json", "check_reachable",
    "render_lifelong", "plot_lifelong",
]

_LAZY = {
    "pettingzoo_env": "sim.parallel_env",
    "ipf_field": "sim.ipf",
    "render_scene": "sim.render",
    "render_episode": "sim.render",
    "render_field": "sim.render",
    "load_floor": "sim.floors",
    "warehouse_floor": "sim.floors",
    "save_floor_json": "sim.floors",
    "check_reachable": "sim.floors",
    "render_lifelong": "sim.render",
    "plot_lifelong": "sim.render",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
