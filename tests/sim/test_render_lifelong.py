"""Pictures of lifelong operation: ``sim.render.render_lifelong`` (an animated GIF of a run) and
``sim.render.plot_lifelong`` (throughput and waits over time)."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

import sim
from sim.controllers import NearestTaskController
from sim.lifelong import LifelongEnv
from sim.render import LIFELONG_COLORS, plot_lifelong, render_lifelong

SCENARIO = "warehouse-20"


def _rgb(color: str) -> np.ndarray:
    return np.array([int(color[k:k + 2], 16) for k in (1, 3, 5)], dtype=np.uint8)


def _pixels_of(frame: np.ndarray, color: str, tol: int = 0) -> int:
    """Pixels of ``frame`` (H, W, 3) within ``tol`` of ``color`` in every channel."""
    diff = np.abs(frame.astype(int) - _rgb(color).astype(int))
    return int((diff <= tol).all(-1).sum())


@pytest.fixture(scope="module")
def metrics() -> sim.LifelongMetrics:
    return sim.evaluate_lifelong(NearestTaskController(), SCENARIO, steps=60, seed=0,
                                 window=20)


@pytest.fixture(scope="module")
def broken_frames() -> list[np.ndarray]:
    """AGV 0 breaks down in step 1 (and stays broken for 50 steps)."""
    return render_lifelong(SCENARIO, steps=3, seed=0, faults=[(1, 0, 50)])


# ---------------------------------------------------------------------- render_lifelong
def test_gif_has_a_frame_per_step_and_the_frames_size(tmp_path) -> None:
    frames = render_lifelong(SCENARIO, steps=4, seed=1)
    assert len(frames) == 5
    assert all(f.dtype == np.uint8 and f.shape == frames[0].shape for f in frames)
    height, width, channels = frames[0].shape
    assert channels == 3 and width > 300 and height > 300
    out = render_lifelong(SCENARIO, steps=4, seed=1, path=tmp_path / "sub" / "run.gif",
                          fps=5)
    assert out == tmp_path / "sub" / "run.gif"
    with Image.open(out) as gif:
        assert gif.format == "GIF"
        assert gif.n_frames == 5
        assert gif.size == (width, height)
        assert gif.info["duration"] == 200  # 5 frames per second
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["run.gif"]  # no temporary left


def test_same_seed_same_frames_other_seed_other_frames() -> None:
    a = render_lifelong(SCENARIO, steps=2, seed=3)
    b = render_lifelong(SCENARIO, steps=2, seed=3)
    c = render_lifelong(SCENARIO, steps=2, seed=4)
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], c[0])


def test_a_broken_agv_is_drawn_in_the_broken_colour(broken_frames) -> None:
    red = LIFELONG_COLORS["broken"]
    assert len(set(LIFELONG_COLORS.values())) == 4  # every state has its own colour
    before, after = broken_frames[0], broken_frames[1]
    legend = _pixels_of(before, red)  # the legend's "broken" disc, in every frame
    assert 0 < legend < 100
    # One more disc, of radius 0.15 at about 75 pixels per unit (~11 px), less its cross.
    assert 30 < _pixels_of(after, red) - legend < 450
    assert _pixels_of(broken_frames[3], red) == _pixels_of(after, red)  # still broken
    idle = LIFELONG_COLORS["idle"]
    assert _pixels_of(after, idle) < _pixels_of(before, idle)  # that disc is no longer idle
    healthy = render_lifelong(SCENARIO, steps=1, seed=0)
    assert _pixels_of(healthy[1], red) == legend


def test_the_broken_colour_survives_in_the_gif(tmp_path) -> None:
    out = render_lifelong(SCENARIO, steps=2, seed=0, faults=[(1, 0, 50)],
                          path=tmp_path / "broken.gif")
    with Image.open(out) as gif:
        gif.seek(0)
        first = np.asarray(gif.convert("RGB"))
        gif.seek(2)
        last = np.asarray(gif.convert("RGB"))
    red = LIFELONG_COLORS["broken"]
    assert _pixels_of(last, red, tol=12) - _pixels_of(first, red, tol=12) > 30


def test_an_env_is_stepped_from_its_state_and_env_index_is_drawn() -> None:
    env = sim.make_env(SCENARIO, num_envs=2, seed=5)
    assert isinstance(env, LifelongEnv)
    env.step(np.zeros((2, env.num_agents, 2), np.float32))
    first = render_lifelong(env, NearestTaskController(), steps=2, env_index=1)
    assert len(first) == 3
    assert env.steps.tolist() == [3, 3]
    other = render_lifelong(env, steps=1, env_index=0)
    assert not np.array_equal(first[-1], other[0])


def test_a_callable_controller_is_accepted() -> None:
    calls = []

    def stand_still(obs):
        calls.append(obs.shape)
        return np.zeros((*obs.shape[:2], 2), np.float32)

    frames = render_lifelong(SCENARIO, stand_still, steps=2)
    assert len(frames) == 3 and len(calls) == 2


@pytest.mark.parametrize(("kwargs", "fragment"), [
    ({"steps": 0}, "steps"),
    ({"steps": -3}, "steps"),
    ({"steps": 2.5}, "steps"),
    ({"seed": -1}, "seed"),
    ({"fps": 0}, "fps"),
    ({"fps": float("nan")}, "fps"),
    ({"env_index": 1}, "env_index"),
    ({"env_index": True}, "env_index"),
    ({"path": "run.png"}, ".gif"),
    ({"faults": [(1, 99, 5)]}, "fault row 0"),
])
def test_bad_arguments_are_value_errors(tmp_path, monkeypatch, kwargs, fragment) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=fragment):
        render_lifelong(SCENARIO, **{"steps": 1, **kwargs})
    assert not list(tmp_path.iterdir())


def test_episodic_scenarios_envs_and_other_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="episodic"):
        render_lifelong("3v3", steps=1)
    with pytest.raises(ValueError, match="episodic"):
        render_lifelong(sim.get_scenario("6v6"), steps=1)
    with pytest.raises(ValueError, match="episodic"):
        render_lifelong(sim.make_env("3v3", num_envs=1), steps=1)
    with pytest.raises(ValueError, match="env_or_scenario"):
        render_lifelong(42, steps=1)
    with pytest.raises(ValueError):
        render_lifelong("no-such-floor", steps=1)
    env = sim.make_env(SCENARIO, num_envs=2, seed=0)
    with pytest.raises(ValueError, match=r"env_index must lie in \[0, 2\)"):
        render_lifelong(env, steps=1, env_index=2)
    with pytest.raises(ValueError, match="faults"):
        render_lifelong(env, steps=1, faults=sim.Breakdowns(0.1, 5))
    assert env.steps.tolist() == [0, 0]  # nothing ran


def test_controller_errors_surface_as_value_errors() -> None:
    with pytest.raises(ValueError, match="controller"):
        render_lifelong(SCENARIO, controller=object(), steps=1)
    with pytest.raises(ValueError, match="actions"):
        render_lifelong(SCENARIO, controller=lambda obs: np.zeros((1, 3, 2)), steps=1)


# ---------------------------------------------------------------------- plot_lifelong
def _dashed_at(ax: Axes, y: float) -> list:
    return [line for line in ax.get_lines() if line.get_linestyle() == "--"
            and np.allclose(line.get_ydata(), y)]


def test_plot_has_throughput_wait_and_the_bound(metrics, tmp_path) -> None:
    fig = plot_lifelong(metrics, path=tmp_path / "plot.png")
    assert isinstance(fig, Figure)
    top, bottom = fig.axes[:2]
    assert len(fig.axes) == 2
    assert len(_dashed_at(top, metrics.throughput_bound)) == 1
    curve = [ln for ln in top.get_lines() if ln.get_linestyle() == "-"]
    assert len(curve) == 1
    np.testing.assert_allclose(curve[0].get_xdata(), metrics.time)
    np.testing.assert_allclose(curve[0].get_ydata(), metrics.throughput_series)
    wait = bottom.get_lines()
    assert len(wait) == 1
    np.testing.assert_allclose(wait[0].get_ydata(), metrics.wait_series)
    assert top.get_ylim()[1] > metrics.throughput_bound
    with Image.open(tmp_path / "plot.png") as png:
        assert png.format == "PNG"


def test_plot_compares_labelled_runs_and_adds_open_orders(metrics) -> None:
    faulty = sim.evaluate_lifelong(NearestTaskController(), SCENARIO, steps=60, seed=0,
                                   window=20, faults=sim.Breakdowns(0.05, 10))
    fig = plot_lifelong({"nearest": metrics, "breakdowns": faulty}, open_orders=True)
    assert len(fig.axes) == 3
    top = fig.axes[0]
    assert len(_dashed_at(top, metrics.throughput_bound)) == 1  # one shared bound
    labels = [t.get_text() for t in top.get_legend().get_texts()]
    assert any(lab.startswith("nearest") for lab in labels)
    assert any(lab.startswith("breakdowns") for lab in labels)
    np.testing.assert_allclose(fig.axes[2].get_lines()[1].get_ydata(), faulty.open_series)


def test_plot_into_given_axes(metrics) -> None:
    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    assert plot_lifelong({"nearest": metrics}, ax=ax) is fig
    assert len(fig.axes) == 2  # the waits on a twin y-axis
    assert len(_dashed_at(ax, metrics.throughput_bound)) == 1
    fig2 = Figure()
    panels = fig2.subplots(2, 1)
    assert plot_lifelong(metrics, ax=panels) is fig2
    assert len(_dashed_at(panels[0], metrics.throughput_bound)) == 1


def test_plot_refuses_bad_arguments(metrics) -> None:
    for bad in (None, [metrics], {}, {"a": 1}, {3: metrics}, {"": metrics}):
        with pytest.raises(ValueError, match="metrics"):
            plot_lifelong(bad)
    fig = Figure()
    with pytest.raises(ValueError, match="ax"):
        plot_lifelong(metrics, ax=fig.subplots(3, 1))
    with pytest.raises(ValueError, match="ax"):
        plot_lifelong(metrics, ax="axes")
    with pytest.raises(ValueError, match="open_orders"):
        plot_lifelong(metrics, ax=fig.subplots(2, 1)[0], open_orders=True)
    with pytest.raises(ValueError, match="open_orders"):
        plot_lifelong(metrics, open_orders="yes")
