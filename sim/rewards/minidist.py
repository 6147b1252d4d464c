"""The paper's global MiniDist reward: every AGV receives the team reward R_t."""

from __future__ import annotations

from torch import Tensor

from sim.state import SimState, StepContext

__all__ = ["MiniDist"]


class MiniDist:
    """The paper's global MiniDist reward: every AGV receives the team reward R_t.

    Terms, each (B, N) and equal across the AGVs of an environment:
    ``distance`` = -(sum over all M tasks of the distance to the nearest AGV, after the step)
    and ``collision`` = -(number of AGV pairs whose discs overlap).
    """

    zeroes_inactive = True

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]:
        # The environment splits R_t per AGV already (0 where it was not running).
        return {"distance": ctx.team_distance, "collision": ctx.team_collision}
