"""Headless pictures with matplotlib: scenes (PNG), episodes (animated GIF) and one AGV's
information potential field (the paper's Figs. 3 and 4; the field itself is :mod:`sim.ipf`).

matplotlib is imported on first use with the Agg backend, so nothing here needs a screen.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from torch import Tensor

from sim.io import atomic_save
from sim.ipf import (
    AGENT_VALUE,
    DEFAULT_RESOLUTION,
    TASK_VALUE,
    IPFField,
    check_scene,
    ipf_field,
)
from sim.world import World

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "SceneSource", "draw_scene", "render_scene", "render_episode", "plot_field", "render_field",
]


class SceneSource(Protocol):
    """What :func:`render_scene` reads of an environment (``sim.AGVEnv`` has all of it)."""

    num_envs: int
    world: World
    scenario: Any
    agent_pos: Tensor  # (B, N, 2)
    task_pos: Tensor  # (B, M, 2)
    task_claimed: Tensor  # (B, M) bool
    agent_task: Tensor  # (B, N) int64
    steps: Tensor  # (B,) int64

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
    env: SceneSource,
    env_index: int = 0,
    trails: np.ndarray | None = None,
    path: str | os.PathLike[str] | None = None,
    title: str | None = None,
) -> Figure:
    """A PNG-ready picture of one environment of ``env``: AGVs, tasks, claims, shelves.

    Parameters
    ----------
    env : AGVEnv, or any object with the attributes of :class:`SceneSource`
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

    from sim import make_env
    from sim.evaluate import run_episodes
    from sim.scenarios import get_scenario

    scn = get_scenario(scenario)
    env = make_env(scn, num_envs=1, seed=seed)
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

    def save_gif(tmp: str) -> None:
        # Pillow picks the format from the name, and the temporary ends in .tmp.
        with tempfile.TemporaryDirectory() as scratch:
            gif = os.path.join(scratch, "episode.gif")
            anim.save(gif, writer=PillowWriter(fps=fps))
            shutil.copyfile(gif, tmp)

    out = atomic_save(save_gif, path)
    if still is not None:
        frame(len(pos) - 1)
        atomic_save(lambda p: fig.savefig(p, dpi=110, format="png"), still)
    plt.close(fig)
    return out


def plot_field(
    field: IPFField,
    agents: np.ndarray,
    tasks: np.ndarray,
    agent: int | None = None,
    ax: Any = None,
    path: str | os.PathLike[str] | None = None,
    claimed: np.ndarray | None = None,
) -> Figure:
    """A heatmap of one AGV's field with the tasks and AGVs marked (the paper's Figs. 3, 4).

    Parameters
    ----------
    field : IPFField
        From :func:`sim.ipf.ipf_field`.
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
    agent : int, optional
        The AGV whose field it is (default ``field.agent``), drawn highlighted.
    ax : matplotlib Axes, optional
        Draw into it; a new figure otherwise.
    path : str or Path, optional
        Save the figure there, in the format its suffix names (PNG without one), atomically.
    claimed : array-like of bool, shape (M,), optional
        Claimed tasks, drawn hollow.

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        For a ``field`` that is not an :class:`sim.ipf.IPFField`, and for the inputs
        :func:`sim.ipf.check_scene` refuses (in the field's world); the message names them.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    if not isinstance(field, IPFField):
        raise ValueError(f"field must be an IPFField (from sim.ipf_field), got "
                         f"{type(field).__name__}")
    world, agents, tasks, agent, claimed = check_scene(
        agents, tasks, field.agent if agent is None else agent, field.world, claimed)
    if ax is None:  # a bare Agg figure: no pyplot, no global backend switch
        fig = Figure(figsize=(5.0, 5.0 * world.size[1] / world.size[0] + 0.4))
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
    else:
        fig = ax.figure
    xmin, ymin, xmax, ymax = world.bounds
    image = ax.imshow(
        field.values, origin="lower", extent=(xmin, xmax, ymin, ymax), cmap="RdBu_r",
        norm=TwoSlopeNorm(vcenter=0.0, vmin=AGENT_VALUE, vmax=TASK_VALUE), interpolation="nearest",
    )
    ax.contour(field.x, field.y, field.values, levels=[-2, -1, -0.25, 0.25, 0.5, 1, 2, 3, 4],
               colors="k", linewidths=0.4, alpha=0.5)
    for x0, y0, x1, y1 in world.obstacles:
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.35", zorder=2))
    r = world.agent_radius
    for i, (px, py) in enumerate(agents):
        me = i == agent
        ax.add_patch(Circle((px, py), r, fill=me, facecolor="gold" if me else "none",
                            edgecolor="k", linewidth=1.5 if me else 1.0, zorder=3))
        ax.annotate(str(i), (px, py), ha="center", va="center", fontsize=8, zorder=4)
    if len(tasks):
        ax.scatter(*tasks[~claimed].T, marker="*", s=140, c="yellow", edgecolors="k", zorder=4,
                   label="task (+5)")
        if claimed.any():
            ax.scatter(*tasks[claimed].T, marker="*", s=140, facecolors="none", edgecolors="k",
                       zorder=4, label="claimed task")
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_title(f"IPF of AGV {agent} (r_IPF = {field.value_at_agent:.3f})")
    fig.colorbar(image, ax=ax, shrink=0.8, label="potential")
    if path is not None:  # the temporary file ends in .tmp: take the format from the target
        fmt = Path(path).suffix.lstrip(".").lower() or "png"
        atomic_save(lambda p: fig.savefig(p, dpi=120, bbox_inches="tight", format=fmt), path)
    return fig


def render_field(
    agents: np.ndarray,
    tasks: np.ndarray,
    agent: int = 0,
    world: World | None = None,
    out: str | os.PathLike[str] | None = None,
    resolution: float = DEFAULT_RESOLUTION,
    claimed: np.ndarray | None = None,
) -> Figure:
    """A picture of AGV ``agent``'s information potential field in one scene.

    :func:`sim.ipf.ipf_field` then :func:`plot_field`, in one call.

    Parameters
    ----------
    agents : array-like, shape (N, 2)
        AGV positions in world units.
    tasks : array-like, shape (M, 2)
        Task positions.
    agent : int
        Whose field (drawn highlighted).
    world : World, optional
        Default ``sim.World()`` (the box ``[-1, 1]^2``).
    out : str or Path, optional
        Save the figure there, in the format its suffix names (PNG without one), atomically;
        missing folders are created.
    resolution : float
        Cell size of the field's grid in world units (default 0.05).
    claimed : array-like of bool, shape (M,), optional
        Claimed tasks: not sources, drawn hollow.

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        For any input :func:`sim.ipf.ipf_field` refuses; the message names it.

    Examples
    --------
    >>> import numpy as np, sim
    >>> fig = sim.render_field(np.array([[-0.5, 0.0], [0.5, 0.0]]), np.array([[0.0, 0.5]]))
    >>> fig.axes[0].get_title()
    'IPF of AGV 0 (r_IPF = 0.308)'
    """
    field = ipf_field(agents, tasks, agent=agent, world=world, resolution=resolution,
                      claimed=claimed)
    return plot_field(field, agents, tasks, agent=field.agent, path=out, claimed=claimed)
