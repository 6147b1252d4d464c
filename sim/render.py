"""Headless pictures with matplotlib: scenes (PNG), episodes (animated GIF) and one AGV's
information potential field (the paper's Figs. 3 and 4; the field itself is :mod:`sim.ipf`);
for lifelong operation (:mod:`sim.lifelong`), a run as an animated GIF
(:func:`render_lifelong`) and its throughput and waits over time (:func:`plot_lifelong`).

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
    "LIFELONG_COLORS", "render_lifelong", "plot_lifelong",
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


# ---------------------------------------------------------------------- lifelong operation
LIFELONG_COLORS: dict[str, str] = {
    "idle": "#b4bec8",
    "to_pickup": "#1f77b4",
    "loaded": "#2ca02c",
    "broken": "#e0201b",
}
"""Face colour of an AGV disc in each :data:`sim.orders.AGENT_STATUS` (``#rrggbb``). In a
:func:`render_lifelong` frame only those discs, the legend and the lines to a pickup (to_pickup)
and to a drop-off (loaded) use them."""

_SHELF, _SHELF_EDGE = "#8f8f8f", "#606060"
_PICKUP_POINT = "#4a4a4a"
_OPEN_ORDER, _OPEN_EDGE = "#ffb000", "#a86f00"
_STATION = "#7b3294"
_DEPOT, _DEPOT_EDGE = "#f2ead9", "#b9a67c"
_GIF_WIDTH_IN, _GIF_DPI = 6.4, 90
_GIF_LAST_FRAME_MS = 1500


class _NoReward:
    """A renderer needs no reward terms (the env then skips computing any)."""

    zeroes_inactive = True

    def __call__(self, state: Any, ctx: Any) -> dict[str, Tensor]:
        return {}


def _lifelong_run(env_or_scenario: Any, steps: int, seed: int, env_index: int,
                  faults: Any) -> tuple[Any, int, Tensor]:
    """The environment to run, the index to draw and its first observations."""
    from sim.lifelong import LifelongEnv, LifelongScenario
    from sim.lifelong_eval import lifelong_runs
    from sim.orders import check_faults
    from sim.scenarios import Scenario, get_scenario

    if isinstance(env_or_scenario, LifelongEnv):
        env = env_or_scenario
        if faults is not None:
            raise ValueError("faults: a LifelongEnv keeps its scenario's breakdowns; pass the "
                             "scenario (or its name) to render_lifelong to add faults")
        if not 0 <= env_index < env.num_envs:
            raise ValueError(f"env_index must lie in [0, {env.num_envs}), got {env_index}")
        return env, env_index, env.observe()
    if getattr(env_or_scenario, "lifelong", False) is not True and hasattr(
            env_or_scenario, "task_pos"):
        raise ValueError(f"env_or_scenario is an episodic {type(env_or_scenario).__name__}; "
                         "render_lifelong draws lifelong runs (use render_episode for episodes)")
    if isinstance(env_or_scenario, str):
        sc = get_scenario(env_or_scenario)
    elif isinstance(env_or_scenario, (LifelongScenario, Scenario)):
        sc = env_or_scenario
    else:
        raise ValueError(f"env_or_scenario must be a LifelongEnv, a LifelongScenario or a "
                         f"lifelong scenario name such as 'warehouse-20', got "
                         f"{type(env_or_scenario).__name__}")
    if not isinstance(sc, LifelongScenario):
        raise ValueError(f"scenario {sc.name!r} is episodic; render_lifelong needs a lifelong "
                         "one ('warehouse-20', 'warehouse-50', 'warehouse-100', ...); use "
                         "render_episode for episodes")
    if env_index != 0:
        raise ValueError(f"env_index must be 0 when a scenario is given (one run is drawn), "
                         f"got {env_index}")
    changes: dict[str, Any] = {"max_steps": steps}
    if faults is not None:
        changes["faults"] = check_faults(faults, sc.num_agents)
    sc = sc.with_options(**changes)
    env = LifelongEnv(sc, num_envs=1, reward=_NoReward(), seed=seed)
    agents, keys = lifelong_runs(sc, 1, seed)
    return env, 0, env.set_state(agents, keys)


def _lifelong_snapshot(env: Any, e: int) -> dict[str, Any]:
    """What one frame shows of environment ``e`` of a LifelongEnv, as numpy arrays."""
    from sim.orders import ASSIGNED, CARRYING, OPEN, TO_PICKUP

    o = env.orders
    status = env.agent_status[e].cpu().numpy()
    pos = env.agent_pos[e].cpu().numpy()
    target = env.targets()[0][e].cpu().numpy()
    order_status = o.status[e].cpu().numpy()
    pickup = o.pickup[e].cpu().numpy()
    loaded = status == CARRYING
    heading = status == TO_PICKUP
    return {
        "step": int(env.steps[e]),
        "pos": pos,
        "status": status,
        "open": pickup[order_status == OPEN],
        "assigned": pickup[order_status == ASSIGNED],
        "to_dropoff": np.stack([pos[loaded], target[loaded]], 1),
        "to_pickup": np.stack([pos[heading], target[heading]], 1),
        "delivered": int(env.delivered[e]),
        "waiting": int((order_status == OPEN).sum() + (order_status == ASSIGNED).sum()),
    }


class _LifelongCanvas:
    """A fixed-size Agg figure of a floor whose moving parts are updated frame by frame."""

    def __init__(self, world: World, label: str, status_names: tuple[str, ...]) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import EllipseCollection, LineCollection
        from matplotlib.figure import Figure
        from matplotlib.lines import Line2D
        from matplotlib.patches import Patch, Rectangle

        self.label = label
        self.colors = np.array([_hex_rgb(LIFELONG_COLORS[name]) for name in status_names])
        xmin, ymin, xmax, ymax = world.bounds
        pad = 0.02 * max(xmax - xmin, ymax - ymin)
        span_x, span_y = xmax - xmin + 2 * pad, ymax - ymin + 2 * pad
        width = _GIF_WIDTH_IN
        ax_w = width - 0.2
        ax_h = ax_w * span_y / span_x
        title_h, legend_h = 0.34, 0.5
        height = ax_h + title_h + legend_h
        # A whole number of pixels high.
        height = round(height * _GIF_DPI) / _GIF_DPI
        self.fig = Figure(figsize=(width, height), dpi=_GIF_DPI, facecolor="white")
        self.canvas = FigureCanvasAgg(self.fig)
        ax = self.fig.add_axes((0.1 / width, legend_h / height, ax_w / width, ax_h / height))
        self.ax = ax
        ax.set_xlim(xmin - pad, xmax + pad)
        ax.set_ylim(ymin - pad, ymax + pad)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_axis_off()
        px_per_unit = self.fig.dpi * ax_w / span_x
        pt = 72.0 / self.fig.dpi  # points per pixel
        ax.add_patch(Rectangle((xmin, ymin), xmax - xmin, ymax - ymin, fill=False, lw=1.5,
                               ec="#333333", zorder=1))
        for x0, y0, x1, y1 in np.asarray(world.depot).reshape(-1, 4):
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fc=_DEPOT, ec=_DEPOT_EDGE,
                                   lw=0.8, zorder=0))
            ax.text((x0 + x1) / 2, (y0 + y1) / 2, "depot", ha="center", va="center",
                    fontsize=8, color=_DEPOT_EDGE, zorder=0.5)
        for x0, y0, x1, y1 in world.obstacles:
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fc=_SHELF, ec=_SHELF_EDGE,
                                   lw=0.6, zorder=1))
        pickups = np.asarray(world.pickups).reshape(-1, 2)
        stations = np.asarray(world.stations).reshape(-1, 2)
        r_px = world.agent_radius * px_per_unit
        if len(pickups):
            ax.scatter(*pickups.T, s=(0.35 * r_px * pt) ** 2 * 4, c=_PICKUP_POINT, lw=0,
                       zorder=2)
        if len(stations):
            ax.scatter(*stations.T, marker="s", s=(2.2 * r_px * pt) ** 2, c=_STATION,
                       ec="white", lw=0.8, zorder=2)
        # The moving parts.
        empty2 = np.zeros((0, 2))
        ring = (1.6 * r_px * pt) ** 2
        self.open = ax.scatter(*empty2.T, s=ring, c=_OPEN_ORDER, ec=_OPEN_EDGE, lw=0.8,
                               zorder=3)
        self.assigned = ax.scatter(*empty2.T, s=ring, facecolors="none", ec=_OPEN_ORDER,
                                   lw=1.6, zorder=3)
        # Lines drawn without antialiasing: crisp in a 64-colour GIF, and far fewer pixels
        # change from frame to frame (a third less GIF).
        self.to_pickup = LineCollection([], colors=LIFELONG_COLORS["to_pickup"], lw=1.0,
                                        linestyles=(0, (2, 2)), antialiaseds=False, zorder=4)
        self.to_dropoff = LineCollection([], colors=LIFELONG_COLORS["loaded"], lw=1.0,
                                         antialiaseds=False, zorder=4)
        ax.add_collection(self.to_pickup)
        ax.add_collection(self.to_dropoff)
        d = 2 * world.agent_radius
        self.agents = EllipseCollection(d, d, 0.0, units="xy", offsets=empty2,
                                        offset_transform=ax.transData, edgecolors="#222222",
                                        linewidths=0.7, zorder=5)
        ax.add_collection(self.agents)
        self.broken = ax.scatter(*empty2.T, marker="x", s=(1.3 * r_px * pt) ** 2, c="black",
                                 lw=1.6, zorder=6)
        self.title = self.fig.text(0.5, 1 - 0.5 * title_h / height, "", ha="center",
                                   va="center", fontsize=10)

        def disc(name: str, text: str) -> Line2D:
            return Line2D([], [], ls="", marker="o", ms=7, mfc=LIFELONG_COLORS[name],
                          mec="#222222", label=text)

        handles = [
            disc("idle", "idle"), disc("to_pickup", "to pickup"), disc("loaded", "loaded"),
            Line2D([], [], ls="", marker="o", ms=7, mfc=LIFELONG_COLORS["broken"],
                   mec="#222222", label="broken"),
            Line2D([], [], ls="", marker="o", ms=8, mfc=_OPEN_ORDER, mec=_OPEN_EDGE,
                   label="open order"),
            Line2D([], [], ls="", marker="o", ms=8, mfc="none", mec=_OPEN_ORDER, mew=1.6,
                   label="order assigned"),
            Line2D([], [], color=LIFELONG_COLORS["loaded"], lw=1.4, label="to drop-off"),
            Line2D([], [], ls="", marker="o", ms=3, mfc=_PICKUP_POINT, mec="none",
                   label="pickup point"),
            Line2D([], [], ls="", marker="s", ms=7, mfc=_STATION, mec="white",
                   label="station"),
            Patch(fc=_SHELF, ec=_SHELF_EDGE, label="shelf"),
        ]
        self.fig.legend(handles=handles, loc="lower center", ncol=5, fontsize=7,
                        frameon=False, handletextpad=0.3, columnspacing=1.0,
                        borderaxespad=0.2)
        self.broken_code = status_names.index("broken")
        self._moving = [self.open, self.assigned, self.to_pickup, self.to_dropoff, self.agents,
                        self.broken, self.title]
        for artist in self._moving:
            artist.set_animated(True)
        self._background: Any = None

    def _snap(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 2) moved to the nearest pixel centre: an AGV that moved less than half
        a pixel draws the same pixels again, which keeps the GIF's frame deltas small."""
        flat = points.reshape(-1, 2)
        if not len(flat):
            return points
        to_px = self.ax.transData
        px = np.floor(to_px.transform(flat)) + 0.5
        return to_px.inverted().transform(px).reshape(points.shape)

    def draw(self, snap: dict[str, Any]) -> np.ndarray:
        """The frame of one snapshot as (H, W, 3) uint8 RGB.

        The floor and the legend are drawn once; each frame restores that background and
        draws only the moving parts on it.
        """
        if self._background is None:
            self.canvas.draw()
            self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        status = snap["status"]
        broken = status == self.broken_code
        pos = self._snap(snap["pos"])
        # Drawn in the order of the status codes, so a loaded or broken AGV that overlaps an
        # idle one stays visible.
        order = np.argsort(status, kind="stable")
        self.agents.set_offsets(pos[order])
        self.agents.set_facecolors(self.colors[status[order]])
        self.broken.set_offsets(pos[broken])
        self.open.set_offsets(snap["open"])
        self.assigned.set_offsets(snap["assigned"])
        self.to_pickup.set_segments(list(self._snap(snap["to_pickup"])))
        self.to_dropoff.set_segments(list(self._snap(snap["to_dropoff"])))
        self.title.set_text(
            f"{self.label}   step {snap['step']}   delivered {snap['delivered']}   "
            f"waiting {snap['waiting']}   broken {int(broken.sum())}/{len(status)}")
        self.canvas.restore_region(self._background)
        for artist in self._moving:
            self.fig.draw_artist(artist)
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()


def _hex_rgb(color: str) -> tuple[float, float, float]:
    return tuple(int(color[k:k + 2], 16) / 255.0 for k in (1, 3, 5))  # type: ignore[return-value]


def _gif_palette(frame: np.ndarray) -> Any:
    """A 64-colour palette from a frame and every state colour (so a colour that first appears
    later, a broken AGV's red say, keeps its own entry)."""
    from PIL import Image

    named = [LIFELONG_COLORS[k] for k in LIFELONG_COLORS] + [
        _OPEN_ORDER, _OPEN_EDGE, _STATION, _SHELF, _SHELF_EDGE, _DEPOT, _PICKUP_POINT]
    swatch = np.repeat(np.array([[int(c[k:k + 2], 16) for k in (1, 3, 5)] for c in named],
                                dtype=np.uint8), 8 * frame.shape[1], axis=0)
    sample = np.concatenate([frame.reshape(-1, 3), swatch]).reshape(-1, frame.shape[1], 3)
    return Image.fromarray(sample).quantize(colors=64, method=Image.Quantize.MEDIANCUT,
                                            dither=Image.Dither.NONE)


class _GifFrames:
    """Frames kept as 64-colour palette images (a byte a pixel), the palette taken from the
    first; :meth:`save` writes them as one animated GIF."""

    def __init__(self) -> None:
        self.images: list[Any] = []
        self.palette: Any = None

    def append(self, frame: np.ndarray) -> None:
        from PIL import Image

        if self.palette is None:
            self.palette = _gif_palette(frame)
        self.images.append(Image.fromarray(frame).quantize(palette=self.palette,
                                                           dither=Image.Dither.NONE))

    def save(self, path: str | os.PathLike[str], fps: float) -> Path:
        images = self.images
        step_ms = max(int(round(1000.0 / fps)), 20)
        durations = [step_ms] * (len(images) - 1) + [max(step_ms, _GIF_LAST_FRAME_MS)]

        def save(tmp: str) -> None:  # the format is named: the temporary ends in .tmp
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                           duration=durations, loop=0, optimize=True)

        return atomic_save(save, path)


def render_lifelong(
    env_or_scenario: Any,
    controller: Any = None,
    steps: int = 200,
    seed: int = 0,
    path: str | os.PathLike[str] | None = None,
    fps: float = 10,
    env_index: int = 0,
    faults: Any = None,
) -> Path | list[np.ndarray]:
    """Run a controller in lifelong operation and draw every step: an animated GIF.

    Each frame shows the floor (shelves grey, pickup points as small dots, stations as purple
    squares, the depot), the AGVs as discs coloured by state (:data:`LIFELONG_COLORS`: idle,
    to pickup, loaded, broken; a broken AGV also carries a black cross), the open orders'
    pickups (gold: open, gold ring: an AGV is on its way), a dotted line from each AGV going to
    a pickup to it and a solid line from each loaded AGV to its drop-off; the title gives the
    step, the orders delivered so far, the orders waiting for a pickup and the broken AGVs.

    Parameters
    ----------
    env_or_scenario : LifelongEnv, LifelongScenario or str
        A scenario (or its name, ``"warehouse-20"``, ``"warehouse-50"``, ...): the run is run 0
        of :func:`sim.evaluate_lifelong` with the same ``seed``, ``steps`` and ``faults`` (same
        fleet, orders and breakdowns), so the GIF and that evaluation's series describe one
        run. A :class:`sim.lifelong.LifelongEnv`: it is stepped from its current state (all B
        environments; ``seed`` is not used, and a run stops moving at the env's
        ``max_steps``), environment ``env_index`` is drawn.
    controller : Controller or callable, optional
        ``act(obs)`` (or a callable) from (B, N, O) lifelong observations to (B, N, 2)
        actions; ``reset(env)`` is called once first if it has one. Default
        :class:`sim.controllers.NearestTaskController`.
    steps : int
        Steps to run (>= 1); the animation has ``steps + 1`` frames, the start and one after
        each step.
    seed : int
        In [0, 2**63), for a scenario.
    path : str or Path, optional
        Where to write the GIF (atomically; missing folders are made; the name must end in
        ``.gif``). Without it the frames are returned instead. The frames are held in memory
        until the end: about 0.3 MB each for a GIF, 1 MB each returned (a 560 x 580 image).
    fps : float
        Frames per second of the GIF (the last frame is held 1.5 s).
    env_index : int
        Which environment of an env to draw (0 for a scenario).
    faults : sim.Breakdowns, sim.FaultSchedule or list of (step, agent, repair_steps), optional
        Breakdowns for a scenario (replacing its own).

    Returns
    -------
    Path
        ``path``, when given.
    list of np.ndarray
        Otherwise the ``steps + 1`` frames, each (H, W, 3) uint8 RGB.

    Raises
    ------
    ValueError
        For an episodic env or scenario, an unknown name, ``steps`` or ``fps`` not positive, a
        seed outside [0, 2**63), ``env_index`` outside [0, B), ``faults`` with an env or a bad
        fault list, a path not ending in ``.gif``, or actions the env refuses; the message
        names the argument.

    Examples
    --------
    >>> import sim
    >>> frames = sim.render_lifelong("warehouse-20", steps=3)   # doctest: +SKIP
    >>> len(frames), frames[0].dtype                             # doctest: +SKIP
    (4, dtype('uint8'))
    """
    from sim.checks import check_count, check_seed
    from sim.controllers import NearestTaskController
    from sim.evaluate import _as_policy
    from sim.orders import AGENT_STATUS

    steps = check_count("steps", steps)
    seed = check_seed(seed, bits=63)
    if isinstance(fps, (bool, np.bool_)) or not isinstance(fps, (int, float, np.integer,
                                                               np.floating)) \
            or not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a positive number, got {fps!r}")
    if isinstance(env_index, (bool, np.bool_)) or not isinstance(env_index, (int, np.integer)):
        raise ValueError(f"env_index must be an integer, got {env_index!r}")
    env_index = int(env_index)
    if path is not None and Path(path).suffix.lower() != ".gif":
        raise ValueError(f"path {str(path)!r} must end in .gif (the animation is a GIF)")
    env, e, obs = _lifelong_run(env_or_scenario, steps, seed, env_index, faults)
    if controller is None:
        controller = NearestTaskController(env.world.physics)
    act = _as_policy(controller)
    reset = getattr(controller, "reset", None)
    if callable(reset):
        reset(env)
    canvas = _LifelongCanvas(env.world, env.scenario.name, AGENT_STATUS)
    frames: list[np.ndarray] | _GifFrames = [] if path is None else _GifFrames()
    try:
        frames.append(canvas.draw(_lifelong_snapshot(env, e)))
        for _ in range(steps):
            obs, *_ = env.step(act(obs))
            frames.append(canvas.draw(_lifelong_snapshot(env, e)))
    finally:
        canvas.fig.clear()
    if isinstance(frames, _GifFrames):
        return frames.save(path, float(fps))
    return frames


def _lifelong_runs_arg(metrics: Any) -> list[tuple[str | None, Any]]:
    """``metrics`` as (label, LifelongMetrics) pairs; label None for a single unlabelled run."""
    from collections.abc import Mapping

    from sim.lifelong_eval import LifelongMetrics

    if isinstance(metrics, LifelongMetrics):
        return [(None, metrics)]
    if not isinstance(metrics, Mapping):
        raise ValueError(f"metrics must be a sim.LifelongMetrics or a dict label -> "
                         f"LifelongMetrics, got {type(metrics).__name__}")
    if not metrics:
        raise ValueError("metrics is an empty dict; give at least one label -> LifelongMetrics")
    runs = []
    for label, m in metrics.items():
        if not isinstance(label, str) or not label:
            raise ValueError(f"metrics labels must be non-empty strings, got {label!r}")
        if not isinstance(m, LifelongMetrics):
            raise ValueError(f"metrics[{label!r}] must be a sim.LifelongMetrics (from "
                             f"sim.evaluate_lifelong), got {type(m).__name__}")
        runs.append((label, m))
    return runs


def plot_lifelong(
    metrics: Any,
    path: str | os.PathLike[str] | None = None,
    ax: Any = None,
    open_orders: bool = False,
    title: str | None = None,
) -> Figure:
    """Throughput and waits over time of lifelong runs (:func:`sim.evaluate_lifelong`).

    The throughput panel has each run's deliveries per 1000 steps in every window of its
    series (``LifelongMetrics.throughput_series`` at ``time``) and the throughput bound as a
    dashed line (one line when the runs share a bound, else one per run in its colour); the
    wait panel the mean wait (release to pickup, steps) of the orders picked up in each window;
    an optional third panel the orders waiting for a pickup at each window's end.

    Parameters
    ----------
    metrics : LifelongMetrics or dict of str -> LifelongMetrics
        One run, or several to compare (a label each, e.g. the controller's name).
    path : str or Path, optional
        Save the figure there, in the format its suffix names (PNG without one), atomically.
    ax : matplotlib Axes or sequence of Axes, optional
        One Axes: throughput on it and the waits on a twin y-axis (dotted), open orders not
        drawn. A sequence of 2 Axes (3 with ``open_orders``): one panel each. Default a new
        figure with one panel each, sharing the step axis.
    open_orders : bool
        Add the panel of orders waiting for a pickup.
    title : str, optional
        Title of the figure (default the scenario's steps and runs).

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ValueError
        For ``metrics`` that is not a LifelongMetrics or a non-empty dict of them with string
        labels, or ``ax`` that is not an Axes or a sequence of as many Axes as panels.

    Examples
    --------
    >>> import sim
    >>> from sim.controllers import NearestTaskController
    >>> m = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=200)
    >>> fig = sim.plot_lifelong({"nearest": m})                 # doctest: +SKIP
    """
    from matplotlib.axes import Axes
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    runs = _lifelong_runs_arg(metrics)
    if not isinstance(open_orders, (bool, np.bool_)):
        raise ValueError(f"open_orders must be True or False, got {open_orders!r}")
    panels = 3 if open_orders else 2
    twin = False
    if ax is None:
        fig = Figure(figsize=(7.0, 2.1 + 1.6 * panels), layout="constrained")
        FigureCanvasAgg(fig)
        axes = list(fig.subplots(panels, 1, sharex=True))
    elif isinstance(ax, Axes):
        if open_orders:
            raise ValueError("open_orders=True needs a panel of its own: pass ax=None or a "
                             "sequence of 3 Axes")
        axes, twin, fig = [ax, ax.twinx()], True, ax.figure
    else:
        try:
            axes = list(ax)
        except TypeError:
            raise ValueError(f"ax must be a matplotlib Axes or a sequence of {panels} Axes, "
                             f"got {type(ax).__name__}") from None
        if len(axes) != panels or not all(isinstance(a, Axes) for a in axes):
            raise ValueError(f"ax must be a sequence of {panels} matplotlib Axes (throughput, "
                             f"wait{', open orders' if open_orders else ''}), got {len(axes)} "
                             "items")
        fig = axes[0].figure
    colors = [f"C{k % 10}" for k in range(len(runs))]
    top = 0.0
    bounds = np.array([m.throughput_bound for _, m in runs])
    shared_bound = bool(np.allclose(bounds, bounds[0]))
    for (label, m), color in zip(runs, colors, strict=True):
        name = label or "throughput"
        axes[0].plot(m.time, m.throughput_series, "-o", ms=3, lw=1.6, color=color,
                     label=f"{name} (mean {m.throughput:.0f})")
        if not shared_bound:
            axes[0].axhline(m.throughput_bound, ls="--", lw=1.2, color=color,
                            label=f"{name}: bound {m.throughput_bound:.0f}")
        wait_label = f"{label} wait" if (label and twin) else (label or "mean wait")
        axes[1].plot(m.time, m.wait_series, ":" if twin else "-", marker="s", ms=3, lw=1.4,
                     color=color, label=wait_label)
        if open_orders:
            axes[2].plot(m.time, m.open_series, "-", lw=1.4, color=color, label=label)
        top = max(top, float(np.nanmax(m.throughput_series, initial=0.0)), m.throughput_bound)
    if shared_bound:
        axes[0].axhline(bounds[0], ls="--", lw=1.2, color="0.25",
                        label=f"throughput bound ({bounds[0]:.0f})")
    axes[0].set_ylim(0, 1.1 * top if top > 0 else 1.0)
    axes[0].set_ylabel("deliveries / 1000 steps")
    axes[1].set_ylabel("wait to pickup (steps)")
    axes[1].set_ylim(bottom=0)
    if open_orders:
        axes[2].set_ylabel("orders waiting")
        axes[2].set_ylim(bottom=0)
    for a in axes[: 1 if twin else panels]:
        a.grid(True, alpha=0.3)
    axes[0 if twin else -1].set_xlabel("step")
    if twin:
        handles, labels = [], []
        for a in axes:
            h, lab = a.get_legend_handles_labels()
            handles += h
            labels += lab
        axes[0].legend(handles, labels, fontsize=8, loc="best")
    else:
        # One legend: the other panels use the same colour for each run.
        axes[0].legend(fontsize=8, loc="best", ncol=2 if len(runs) > 2 else 1)
    first = runs[0][1]
    if title is None:
        runs_text = "1 run" if first.runs == 1 else f"{first.runs} runs"
        title = f"lifelong operation: {first.steps} steps, {runs_text}"
    if ax is None:
        fig.suptitle(title, fontsize=11)
    else:
        axes[0].set_title(title, fontsize=10)
    if path is not None:  # the temporary file ends in .tmp: take the format from the target
        fmt = Path(path).suffix.lstrip(".").lower() or "png"
        atomic_save(lambda p: fig.savefig(p, dpi=120, format=fmt), path)
    return fig
