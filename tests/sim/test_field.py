"""sim.ipf_field and sim.render_field tried as a new user would: every bad input is a
ValueError that names it, and the documented results hold."""

from __future__ import annotations

import numpy as np
import pytest

import sim
from sim.ipf import AGENT_VALUE, ipf_field
from sim.render import plot_field

AGENTS = np.array([[-0.5, 0.0], [0.5, 0.1]])
TASKS = np.array([[0.0, 0.5], [0.3, -0.6]])
SHELF = sim.World(obstacles=np.array([[0.1, 0.1, 0.4, 0.4]]))


# ---------------------------------------------------------------------- no tasks
def test_ipf_field_without_any_source_is_refused_instead_of_an_all_zero_field() -> None:
    with pytest.raises(ValueError, match="no source.*zero everywhere"):
        ipf_field(np.array([[0.0, 0.0]]), np.zeros((0, 2)))
    with pytest.raises(ValueError, match="no source.*zero everywhere"):
        ipf_field(np.array([[0.0, 0.0]]), TASKS, claimed=[True, True])


def test_ipf_field_without_open_tasks_is_the_other_agvs_repulsion() -> None:
    field = ipf_field(AGENTS, [], agent=0)
    assert field.values.max() <= 0.0 and field.values.min() == pytest.approx(AGENT_VALUE)
    assert field.value_at_agent < 0.0


# ---------------------------------------------------------------------- the agent index
@pytest.mark.parametrize("agent", [-1, 2, 1.0, True, "0", None])
def test_ipf_field_refuses_an_agent_that_is_not_an_index_of_agents(agent) -> None:
    with pytest.raises(ValueError, match=r"agent must be an index in \[0, 2\)"):
        ipf_field(AGENTS, TASKS, agent=agent)


def test_ipf_field_accepts_a_numpy_integer_agent() -> None:
    assert ipf_field(AGENTS, TASKS, agent=np.int64(1)).agent == 1


# ---------------------------------------------------------------------- positions
def test_ipf_field_refuses_nan_positions_naming_them() -> None:
    with pytest.raises(ValueError, match=r"agents contain NaN or infinite values at rows \[1\]"):
        ipf_field(np.array([[0.0, 0.0], [np.nan, 0.2]]), TASKS)
    with pytest.raises(ValueError, match=r"tasks contain NaN"):
        ipf_field(AGENTS, np.array([[0.0, np.inf]]))


def test_ipf_field_refuses_positions_outside_the_world() -> None:
    with pytest.raises(ValueError, match=r"tasks rows \[1\] lie outside the world bounds"):
        ipf_field(AGENTS, np.array([[0.0, 0.5], [1.5, 0.0]]))
    with pytest.raises(ValueError, match=r"agents rows \[0\] lie outside"):
        ipf_field(np.array([[-3.0, 0.0]]), TASKS)


def test_ipf_field_refuses_an_agent_on_a_shelf() -> None:
    with pytest.raises(ValueError, match=r"agents rows \[1\] lie inside a shelf"):
        ipf_field(np.array([[-0.5, -0.5], [0.2, 0.2]]), np.array([[-0.5, 0.5]]), world=SHELF)


def test_ipf_field_refuses_its_own_agv_on_the_boundary_ring_instead_of_reading_zero() -> None:
    with pytest.raises(ValueError, match=r"AGV 0 \(whose field it is\).*boundary ring"):
        ipf_field(np.array([[0.99, 0.0], [0.0, 0.0]]), TASKS, agent=0)


@pytest.mark.parametrize("points", [[["a", "b"]], [[1 + 2j, 0.0]], [[True, False]]],
                         ids=["strings", "complex", "bools"])
def test_ipf_field_refuses_coordinates_that_are_not_real_numbers(points) -> None:
    with pytest.raises(ValueError, match="agents must hold real coordinates"):
        ipf_field(points, TASKS)


def test_ipf_field_refuses_tasks_of_a_shape_it_used_to_reshape_silently() -> None:
    with pytest.raises(ValueError, match=r"tasks must have shape \(K, 2\), got \(2, 4\)"):
        ipf_field(AGENTS, np.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"tasks must have shape \(K, 2\), got \(2,\)"):
        ipf_field(AGENTS, [0.0, 0.5])


def test_ipf_field_refuses_ragged_positions_naming_them() -> None:
    with pytest.raises(ValueError, match="agents must be an array of shape"):
        ipf_field([[0.0, 0.0], [0.5]], TASKS)


def test_ipf_field_refuses_a_world_that_is_not_a_world() -> None:
    with pytest.raises(ValueError, match="world must be a sim.World or None, got str"):
        ipf_field(AGENTS, TASKS, world="warehouse")


# ---------------------------------------------------------------------- claimed
def test_ipf_field_refuses_claimed_of_the_wrong_length() -> None:
    with pytest.raises(ValueError, match=r"claimed must have shape \(2,\), one flag per task"):
        ipf_field(AGENTS, TASKS, claimed=[True])


@pytest.mark.parametrize("claimed", [["yes", "no"], [0.5, 0.0], [2, 0], [None, None]])
def test_ipf_field_refuses_claimed_flags_that_are_not_booleans(claimed) -> None:
    with pytest.raises(ValueError, match="claimed must hold booleans"):
        ipf_field(AGENTS, TASKS, claimed=claimed)


def test_ipf_field_accepts_claimed_as_zeros_and_ones() -> None:
    as_int = ipf_field(AGENTS, TASKS, claimed=[0, 1])
    as_bool = ipf_field(AGENTS, TASKS, claimed=[False, True])
    np.testing.assert_array_equal(as_int.values, as_bool.values)


# ---------------------------------------------------------------------- resolution
@pytest.mark.parametrize("resolution", [0, 0.0, -0.05, float("nan"), float("inf")])
def test_ipf_field_refuses_a_resolution_that_is_not_a_positive_number(resolution) -> None:
    with pytest.raises(ValueError, match="resolution must be a positive, finite cell size"):
        ipf_field(AGENTS, TASKS, resolution=resolution)


@pytest.mark.parametrize("resolution", [True, None, "0.05"])
def test_ipf_field_refuses_a_resolution_that_is_a_bool_none_or_a_string(resolution) -> None:
    with pytest.raises(ValueError, match="resolution must be a positive, finite cell size"):
        ipf_field(AGENTS, TASKS, resolution=resolution)


@pytest.mark.parametrize("resolution", [1e300, 1.0])
def test_ipf_field_refuses_a_resolution_too_coarse_for_the_world(resolution) -> None:
    with pytest.raises(ValueError, match=r"at least 3 x 3 cells .* use resolution <= 0.6667"):
        ipf_field(AGENTS, TASKS, resolution=resolution)


@pytest.mark.parametrize("resolution", [1e-300, 1e-4])
def test_ipf_field_refuses_a_resolution_too_fine_before_allocating_the_grid(resolution) -> None:
    with pytest.raises(ValueError, match=r"resolution .* use resolution >= "):
        ipf_field(AGENTS, TASKS, resolution=resolution)


def test_ipf_field_accepts_a_numpy_float_resolution() -> None:
    field = ipf_field(AGENTS, TASKS, resolution=np.float32(0.1))
    assert field.values.shape == (20, 20)


# ---------------------------------------------------------------------- the picture
def test_render_field_draws_and_saves_one_agvs_field(tmp_path) -> None:
    out = tmp_path / "figs" / "field.png"
    fig = sim.render_field(AGENTS, TASKS, agent=1, out=out, claimed=[False, True])
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    expected = ipf_field(AGENTS, TASKS, agent=1, claimed=[False, True]).value_at_agent
    assert fig.axes[0].get_title() == f"IPF of AGV 1 (r_IPF = {expected:.3f})"


def test_render_field_saves_in_the_format_of_the_file_name(tmp_path) -> None:
    out = tmp_path / "field.svg"
    sim.render_field(AGENTS, TASKS, out=out)
    assert out.read_text(encoding="utf-8").lstrip().startswith("<?xml")


def test_render_field_refuses_bad_input_naming_it(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"agent must be an index in \[0, 2\)"):
        sim.render_field(AGENTS, TASKS, agent=5, out=tmp_path / "x.png")
    with pytest.raises(ValueError, match="no source"):
        sim.render_field(AGENTS[:1], [], out=tmp_path / "x.png")
    assert not list(tmp_path.iterdir())


def test_plot_field_refuses_what_is_not_a_field() -> None:
    with pytest.raises(ValueError, match="field must be an IPFField .*got ndarray"):
        plot_field(np.zeros((40, 40)), AGENTS, TASKS)


def test_plot_field_refuses_claimed_of_the_wrong_length_instead_of_an_index_error() -> None:
    field = ipf_field(AGENTS, TASKS)
    with pytest.raises(ValueError, match=r"claimed must have shape \(2,\)"):
        plot_field(field, AGENTS, TASKS, claimed=[True, False, True])


def test_plot_field_refuses_an_agent_to_highlight_that_is_not_an_index() -> None:
    field = ipf_field(AGENTS, TASKS)
    with pytest.raises(ValueError, match=r"agent must be an index in \[0, 2\)"):
        plot_field(field, AGENTS, TASKS, agent=7)


def test_render_episode_writes_a_gif_although_the_atomic_temporary_ends_in_tmp(tmp_path) -> None:
    from sim.controllers import RandomController

    gif = tmp_path / "episode.gif"
    scenario = sim.get_scenario("3v3", max_steps=4)
    sim.render_episode(RandomController(), scenario, seed=0, path=gif, still=tmp_path / "s.png")
    assert gif.read_bytes()[:6] == b"GIF89a"
    assert (tmp_path / "s.png").read_bytes()[:4] == b"\x89PNG"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode.gif", "s.png"]
