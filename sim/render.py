"""Headless pictures of scenes (PNG) and episodes (animated GIF) with matplotlib.

matplotlib is imported on first use with the Agg backend, so nothing here needs a screen.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sim.io import atomic_save
from sim.world import World

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from sim.core import AGVEnv

__all__ = ["draw_scene", "render_scene", "render_episode"]

_AGENT_COLORS = "tab:blue"
_TASK_COLOR = "tab:orange"


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def draw_scene(
    ax: Axes,
    world: World,
    agents: np.ndarray,
    tasks: np.ndarray,
    claimed: np.ndarray | None = None,
    agent_task: np.ndarray | None = None,
    trails: np.ndarray | None = None,
    title: str | None = None,
) -> None:
    """Draw one scene on ``ax``.

    Parameters
    ----------
    ax : matplotlib Axes
    world : World
    agents : (N, 2) AGV positions
    tasks : (M, 2) task positions
    claimed : (M,) bool, optional; claimed tasks are drawn filled
    agent_task : (N,) int, optional; a line joins each parked AGV to its task
    trails : (T, N, 2), optional; trajectories so far
    title : str, optional
    """
    from matplotlib.patches import Circle, Rectangle

    agents = np.asarray(agents)
    tasks = np.asarray(tasks)
    claimed = np.zeros(len(tasks), bool) if claimed is None else np.asarray(claimed, bool)
    xmin, ymin, xmax, ymax = world.bounds
    ax.add_patch(Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, fill=False, lw=2, ec="k"))
    for x0, y0, x1, y1 in world.obstacles:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fc="0.55", ec="0.3"))
    for j, (x, y) in enumerate(tasks):
        done = bool(claimed[j])
        ax.add_patch(Circle((x, y), world.capture_radius, fc=_TASK_COLOR if done else "none",
                            ec=_TASK_COLOR, lw=1.5, ls="-" if done else "--", alpha=0.9))
        ax.plot(x, y, marker="x", color=_TASK_COLOR, ms=7, mew=2)
        ax.annotate(f"T{j}", (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8,
                    color="tab:red")
    if trails is not None and len(trails) > 1:
        for i in range(agents.shape[0]):
            ax.plot(trails[:, i, 0], trails[:, i, 1], "-", color=_AGENT_COLORS, alpha=0.35, lw=1)
    for i, (x, y) in enumerate(agents):
        parked = agent_task is not None and agent_task[i] >= 0
        ax.add_patch(Circle((x, y), world.agent_radius, fc="tab:green" if parked else "tab:blue",
                            ec="k", alpha=0.75))
        ax.annotate(f"{i}", (x, y), ha="center", va="center", fontsize=8, color="w")
        if parked:
            tx, ty = tasks[int(agent_task[i])]
            ax.plot([x, tx], [y, ty], ":", color="k", lw=1)
    pad = 0.05 * max(xmax - xmin, ymax - ymin)
    ax.set_xlim(xmin - pad, xmax + pad)
    ax.set_ylim(ymin - pad, ymax + pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:
        ax.set_title(title, fontsize=10)


def render_scene(
    env: AGVEnv,
    env_index: int = 0,
    trails: np.ndarray | None = None,
    path: str | os.PathLike[str] | None = None,
    title: str | None = None,
) -> Figure:
    """A PNG-ready picture of one environment of ``env``: AGVs, tasks, claims, shelves.

    Parameters
    ----------
    env : AGVEnv
    env_index : int
        Which of the B environments.
    trails : (T, N, 2), optional
        Trajectories so far.
    path : str or Path, optional
        Where to save the PNG (written atomically).

    Returns
    -------
    matplotlib Figure
    """
    if not 0 <= env_index < env.num_envs:
        raise ValueError(f"env_index must lie in [0, {env.num_envs}), got {env_index}")
    plt = _plt()
    w, h = env.world.size
    fig, ax = plt.subplots(figsize=(5 * w / max(w, h) + 0.5, 5 * h / max(w, h) + 0.5))
    e = env_index
    draw_scene(
        ax, env.world, env.agent_pos[e].cpu().numpy(), env.task_pos[e].cpu().numpy(),
        env.task_claimed[e].cpu().numpy(), env.agent_task[e].cpu().numpy(),
        trails, title or f"{env.scenario.name}  step {int(env.steps[e])}",
    )
    fig.tight_layout()
    if path is not None:
        atomic_save(lambda p: fig.savefig(p, dpi=110, format="png"), path)
    return fig


def render_episode(
    controller: Any,
    scenario: Any = "3v3",
    seed: int = 0,
    path: str | os.PathLike[str] = "episode.gif",
    fps: int = 8,
    title: str | None = None,
    still: str | os.PathLike[str] | None = None,
) -> Path:
    """Run one episode of ``controller`` and write it as an animated GIF.

    Parameters
    ----------
    controller : Controller or callable
        As accepted by :func:`sim.evaluate`.
    scenario : str or Scenario
    seed : int
        Seed of the episode.
    path : str or Path
        Destination GIF (written atomically).
    fps : int
        Frames per second.
    still : str or Path, optional
        Also save the last frame, with trajectories, as a PNG.

    Returns
    -------
    Path of the GIF.
    """
    from matplotlib.animation import FuncAnimation, PillowWriter

    from sim.core import AGVEnv
    from sim.evaluate import run_episodes
    from sim.scenarios import get_scenario

    scn = get_scenario(scenario)
    env = AGVEnv(scn, num_envs=1, seed=seed)
    rec = run_episodes(env, controller, seed=seed, record=True)
    pos, claimed, agent_task = rec["agent_pos"][:, 0], rec["claimed"][:, 0], rec["agent_task"][:, 0]
    tasks = env.task_pos[0].cpu().numpy()
    plt = _plt()
    w, h = scn.world.size
    fig, ax = plt.subplots(figsize=(5 * w / max(w, h) + 0.5, 5 * h / max(w, h) + 0.5))
    label = title or scn.name

    def frame(t: int) -> None:
        ax.clear()
        draw_scene(ax, scn.world, pos[t], tasks, claimed[t], agent_task[t], pos[: t + 1],
                   f"{label}  step {t}  claimed {int(claimed[t].sum())}/{len(tasks)}")

    anim = FuncAnimation(fig, frame, frames=len(pos), interval=1000 / fps)
    out = atomic_save(lambda p: anim.save(p, writer=PillowWriter(fps=fps)), path)
    if still is not None:
        frame(len(pos) - 1)
        atomic_save(lambda p: fig.savefig(p, dpi=110, format="png"), still)
    plt.close(fig)
    return out
