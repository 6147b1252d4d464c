"""Former home of the environment, now :mod:`sim.env` (physics in :mod:`sim.physics`, task
rules in :mod:`sim.tasks`, observations in :mod:`sim.observations`); kept until every importer
uses :mod:`sim.env`."""

from sim.env import AGVEnv, make_env
from sim.state import SimState, StepContext

__all__ = ["AGVEnv", "SimState", "StepContext", "make_env"]
