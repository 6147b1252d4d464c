"""The information potential field: oracle, discrete-harmonic properties, metamorphic checks,
the batched reward path, bad input and the picture."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import sim
from sim import native
from sim.ipf import (
    AGENT_VALUE,
    TASK_VALUE,
    IPFGrid,
    ipf_field,
    ipf_grid,
    jacobi_field,
)
from sim.render import plot_field

COARSE = 0.1  # 20 x 20 cells on the MPE box: fast Jacobi for the oracle tests
SHELVES = sim.World(obstacles=np.array([[-0.6, -0.2, -0.1, 0.2], [0.2, -0.7, 0.5, 0.6]]))


def _scene(world: sim.World, n: int, m: int, seed: int, gap: float = 0.25):
    """n AGVs and m tasks on the free floor, pairwise ``gap`` apart."""
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = world.bounds
    points: list[np.ndarray] = []
    while len(points) < n + m:
        p = rng.uniform((xmin, ymin), (xmax, ymax))
        if world.is_free(p[None], clearance=0.15)[0] and all(
            np.linalg.norm(p - q) >= gap for q in points
        ):
            points.append(p)
    arr = np.array(points)
    return arr[:n], arr[n:]


def _sources(grid: IPFGrid, agents: np.ndarray, tasks: np.ndarray, agent: int):
    others = np.delete(agents, agent, axis=0)
    cells = grid.cell_of(np.concatenate([others, tasks])).numpy()
    values = np.r_[np.full(len(others), AGENT_VALUE), np.full(len(tasks), TASK_VALUE)]
    return cells, values


# ---------------------------------------------------------------------- the grid
def test_default_grid_has_agv_spanning_several_cells() -> None:
    grid = ipf_grid()
    assert grid.shape == (40, 40)
    assert 2 * sim.World().agent_radius / grid.dx >= 5
    np.testing.assert_allclose(grid.x[[0, -1]], [-0.975, 0.975])
    assert grid.fixed[0].all() and grid.fixed[:, -1].all() and not grid.fixed[1:-1, 1:-1].any()


def test_grid_is_cached_per_world_and_resolution() -> None:
    assert ipf_grid(sim.World(), COARSE) is ipf_grid(sim.World(agent_radius=0.1), COARSE)
    assert ipf_grid(sim.World(), COARSE) is not ipf_grid(SHELVES, COARSE)
    assert ipf_grid(sim.World(), COARSE) is not ipf_grid(sim.World(), 0.2)


def test_graph_is_the_4_neighbour_grid_with_fixed_flags() -> None:
    grid = ipf_grid(SHELVES, COARSE)
    g = grid.graph
    H, W = grid.shape
    assert g.number_of_nodes() == H * W
    assert g.number_of_edges() == H * (W - 1) + W * (H - 1)
    assert all(g.degree(n) == 4 for n in g.nodes if not g.nodes[n]["fixed"])
    assert sum(g.nodes[n]["fixed"] for n in g.nodes) == H * W - grid.num_free


def test_green_function_inverts_the_dirichlet_laplacian() -> None:
    grid = ipf_grid(SHELVES, COARSE)
    lap = grid.laplacian().toarray()
    np.testing.assert_allclose(lap @ grid.green, np.eye(grid.num_free), atol=1e-10)


# ---------------------------------------------------------------------- the oracle
@pytest.mark.parametrize("world", [sim.World(), SHELVES], ids=["box", "shelves"])
@pytest.mark.parametrize("n", [1, 3, 8])
def test_fast_solver_matches_jacobi(world: sim.World, n: int) -> None:
    grid = ipf_grid(world, COARSE)
    agents, tasks = _scene(world, n, n, seed=n)
    for agent in {0, n - 1}:
        cells, values = _sources(grid, agents, tasks, agent)
        reference = jacobi_field(grid, cells, values, tol=1e-9)
        fast = grid.fields(torch.from_numpy(cells)[None], torch.from_numpy(values)[None])[0]
        np.testing.assert_allclose(fast.numpy(), reference, atol=1e-8, rtol=0)


@pytest.mark.parametrize("world", [sim.World(), SHELVES], ids=["box", "shelves"])
def test_reward_path_matches_jacobi_at_every_agent(world: sim.World) -> None:
    grid = ipf_grid(world, COARSE)
    agents, tasks = _scene(world, 4, 3, seed=7)
    pot = grid.agent_potentials(torch.from_numpy(agents)[None], torch.from_numpy(tasks)[None])
    for i in range(4):
        cells, values = _sources(grid, agents, tasks, i)
        reference = jacobi_field(grid, cells, values, tol=1e-9)
        own = int(grid.cell_of(agents[i]))
        assert abs(float(pot[0, i]) - reference.ravel()[own]) < 1e-8


def test_ipf_field_methods_agree_at_default_resolution() -> None:
    agents = np.array([[-0.5, 0.0], [0.5, 0.1], [0.0, -0.6]])
    tasks = np.array([[0.1, 0.5], [0.6, 0.6], [-0.7, -0.7]])
    fast = ipf_field(agents, tasks, agent=1)
    jacobi = ipf_field(agents, tasks, agent=1, method="jacobi")
    np.testing.assert_allclose(fast.values, jacobi.values, atol=1e-8, rtol=0)
    assert fast.value_at_agent == pytest.approx(jacobi.value_at_agent, abs=1e-8)


# ---------------------------------------------------------------------- harmonic properties
@pytest.fixture(scope="module")
def shelf_field() -> tuple[sim.ipf.IPFField, np.ndarray, np.ndarray]:
    agents, tasks = _scene(SHELVES, 5, 5, seed=11)
    return ipf_field(agents, tasks, agent=2, world=SHELVES), agents, tasks


def test_discrete_maximum_principle(shelf_field) -> None:
    field, _, _ = shelf_field
    assert field.values.min() >= AGENT_VALUE - 1e-12
    assert field.values.max() <= TASK_VALUE + 1e-12


def test_mean_value_property_at_free_nodes(shelf_field) -> None:
    field, agents, tasks = shelf_field
    grid = ipf_grid(SHELVES)
    phi = field.values
    cells, _ = _sources(grid, agents, tasks, field.agent)
    harmonic = ~grid.fixed.copy()
    harmonic.ravel()[cells] = False
    mean = 0.25 * (np.roll(phi, 1, 0) + np.roll(phi, -1, 0) + np.roll(phi, 1, 1)
                   + np.roll(phi, -1, 1))
    np.testing.assert_allclose(phi[harmonic], mean[harmonic], atol=1e-10, rtol=0)


def test_sources_keep_their_values_and_fixed_nodes_are_zero(shelf_field) -> None:
    field, agents, tasks = shelf_field
    grid = ipf_grid(SHELVES)
    flat = field.values.ravel()
    others = np.delete(agents, field.agent, axis=0)
    np.testing.assert_allclose(flat[grid.cell_of(others).numpy()], AGENT_VALUE, atol=1e-10)
    np.testing.assert_allclose(flat[grid.cell_of(tasks).numpy()], TASK_VALUE, atol=1e-10)
    assert np.all(field.values[grid.fixed] == 0.0)
    assert grid.obstacle.any()


def test_own_cell_is_not_a_source() -> None:
    field = ipf_field(np.array([[-0.5, 0.0]]), np.array([[0.5, 0.0]]))
    assert 0.0 < field.value_at_agent < 1.0


# ---------------------------------------------------------------------- metamorphic checks
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 5), axis=st.sampled_from([0, 1]))
def test_mirrored_scene_gives_mirrored_field(seed: int, n: int, axis: int) -> None:
    agents, tasks = _scene(sim.World(), n, n, seed)
    flip = np.array([1.0, 1.0])
    flip[axis] = -1.0  # the box is symmetric about both axes
    field = ipf_field(agents, tasks, agent=0)
    mirrored = ipf_field(agents * flip, tasks * flip, agent=0)
    expected = np.flip(field.values, axis=1 - axis)  # x is the column axis
    np.testing.assert_allclose(mirrored.values, expected, atol=1e-10, rtol=0)
    assert mirrored.value_at_agent == pytest.approx(field.value_at_agent, abs=1e-10)


def test_claimed_task_leaves_the_field() -> None:
    agents, tasks = _scene(sim.World(), 3, 3, seed=5)
    claimed = np.array([False, True, False])
    with_claim = ipf_field(agents, tasks, agent=0, claimed=claimed)
    without = ipf_field(agents, tasks[~claimed], agent=0)
    np.testing.assert_array_equal(with_claim.values, without.values)
    grid = ipf_grid()
    pot = grid.agent_potentials(torch.from_numpy(agents)[None], torch.from_numpy(tasks)[None],
                                torch.from_numpy(~claimed)[None])
    assert float(pot[0, 0]) == pytest.approx(with_claim.value_at_agent, abs=1e-10)
    everything = ipf_field(agents, tasks, agent=0)
    assert not np.allclose(everything.values, with_claim.values)


def test_permuting_agents_and_tasks_permutes_rewards() -> None:
    agents, tasks = _scene(sim.World(), 5, 4, seed=2)
    grid = ipf_grid()
    perm_a, perm_t = np.array([3, 0, 4, 1, 2]), np.array([2, 3, 0, 1])
    a, t = torch.from_numpy(agents)[None], torch.from_numpy(tasks)[None]
    pot = grid.agent_potentials(a, t)[0]
    permuted = grid.agent_potentials(a[:, perm_a], t[:, perm_t])[0]
    torch.testing.assert_close(permuted, pot[perm_a], atol=1e-10, rtol=0)


# ---------------------------------------------------------------------- batched reward rules
def test_batched_potentials_equal_per_scene_fields() -> None:
    grid = ipf_grid(SHELVES)
    scenes = [_scene(SHELVES, 4, 4, seed=s) for s in range(3)]
    agents = torch.from_numpy(np.stack([a for a, _ in scenes]))
    tasks = torch.from_numpy(np.stack([t for _, t in scenes]))
    open_ = torch.tensor([[True] * 4, [True, False, True, False], [False] * 4])
    pot = grid.agent_potentials(agents, tasks, open_)
    for b, (a, t) in enumerate(scenes):
        for i in range(4):
            f = ipf_field(a, t, agent=i, world=SHELVES, claimed=~open_[b].numpy())
            assert float(pot[b, i]) == pytest.approx(f.value_at_agent, abs=1e-10)


def test_batched_rule_agent_wins_a_shared_cell() -> None:
    grid = ipf_grid()
    # AGV 1 stands on task 0's cell: the cell is -3 for AGV 0, as if the task were not there.
    agents = torch.tensor([[[-0.5, 0.0], [0.51, 0.01]]], dtype=torch.float64)
    tasks = torch.tensor([[[0.52, 0.02], [0.0, 0.6]]], dtype=torch.float64)
    pot = grid.agent_potentials(agents, tasks)
    alone = grid.agent_potentials(agents, tasks[:, 1:])
    assert float(pot[0, 0]) == pytest.approx(float(alone[0, 0]), abs=1e-12)
    # AGV 1's own cell holds task 0, one of its sources: it reads +5.
    assert float(pot[0, 1]) == TASK_VALUE
    # Two AGVs on one cell: each reads the other's -3.
    both = grid.agent_potentials(agents[:, [0, 0]], tasks)
    assert both.tolist() == [[AGENT_VALUE, AGENT_VALUE]]


def test_batched_source_on_fixed_cell_is_ignored() -> None:
    grid = ipf_grid()
    agents = torch.tensor([[[-0.5, 0.0], [0.99, 0.0]]], dtype=torch.float64)  # AGV 1 in the ring
    tasks = torch.tensor([[[0.0, 0.6]]], dtype=torch.float64)
    pot = grid.agent_potentials(agents, tasks)
    alone = grid.agent_potentials(agents[:, :1], tasks)
    assert float(pot[0, 0]) == pytest.approx(float(alone[0, 0]), abs=1e-12)
    assert float(pot[0, 1]) == 0.0


# ---------------------------------------------------------------------- bad input
def test_too_coarse_grid_names_a_resolution_that_works() -> None:
    agents = np.array([[-0.5, 0.0], [0.3, 0.3]])
    tasks = np.array([[0.38, 0.3]])
    with pytest.raises(ValueError, match=r"too coarse.*AGV 1 and task 0.*resolution <= 0.053"):
        ipf_field(agents, tasks, agent=0, resolution=0.2)
    assert ipf_field(agents, tasks, agent=0, resolution=0.05).values.shape == (40, 40)


def test_same_valued_sources_on_one_cell_merge() -> None:
    tasks = np.array([[0.3, 0.3], [0.31, 0.31]])
    merged = ipf_field(np.array([[-0.5, 0.0]]), tasks)
    single = ipf_field(np.array([[-0.5, 0.0]]), tasks[:1])
    np.testing.assert_array_equal(merged.values, single.values)


def test_source_on_an_obstacle_cell_is_refused() -> None:
    world = sim.World(obstacles=np.array([[0.0, 0.0, 0.35, 0.35]]))
    with pytest.raises(ValueError, match=r"task 0 .* a shelf .* finer resolution"):
        ipf_field(np.array([[-0.5, -0.5]]), np.array([[0.38, 0.2]]), world=world, resolution=0.2)
    ipf_field(np.array([[-0.5, -0.5]]), np.array([[0.38, 0.2]]), world=world)  # fine at 0.05
    with pytest.raises(ValueError, match="boundary ring"):
        ipf_field(np.array([[-0.5, -0.5]]), np.array([[0.97, 0.2]]))
    with pytest.raises(ValueError, match="inside a shelf"):
        ipf_field(np.array([[-0.5, -0.5]]), np.array([[0.2, 0.2]]), world=world)


def test_memory_guard_names_a_resolution_that_fits() -> None:
    from sim.scenarios import warehouse_world

    with pytest.raises(ValueError, match=r"MiB .* use resolution >= ([0-9.]+)") as err:
        IPFGrid(warehouse_world(), resolution=0.01)
    suggested = float(err.value.args[0].split("use resolution >= ")[1].split()[0])
    IPFGrid(warehouse_world(), resolution=suggested)  # the grid fits; G is built lazily


@pytest.mark.parametrize("resolution", [0.0, -0.1, float("nan"), 1.0])
def test_bad_resolutions_are_refused(resolution: float) -> None:
    with pytest.raises(ValueError, match="resolution"):
        IPFGrid(sim.World(), resolution)


@pytest.mark.parametrize("resolution", ["0.05", None, "fine", 1e-300])
def test_ipf_grid_names_a_resolution_that_is_not_a_usable_number(resolution) -> None:
    with pytest.raises(ValueError, match="resolution"):
        ipf_grid(sim.World(), resolution)


def test_cell_of_refuses_nan_instead_of_returning_cell_zero() -> None:
    grid = ipf_grid(sim.World(), COARSE)
    with pytest.raises(ValueError, match="points contain NaN"):
        grid.cell_of(np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"points must have shape \(\.\.\., 2\), got \(3,\)"):
        grid.cell_of(np.zeros(3))


def test_fields_refuse_cells_outside_the_grid_instead_of_an_index_error() -> None:
    grid = ipf_grid(sim.World(), COARSE)
    with pytest.raises(ValueError, match=r"source_cells must be flat cell indices in \[0, 400\)"):
        grid.fields(torch.tensor([[400]]), torch.tensor([[5.0]]))
    with pytest.raises(ValueError, match="source_values must have the shape of source_cells"):
        grid.fields(torch.tensor([[45, 46]]), torch.tensor([[5.0]]))
    with pytest.raises(ValueError, match="source_values must be finite"):
        grid.fields(torch.tensor([[45]]), torch.tensor([[float("nan")]]))


def test_jacobi_field_refuses_cells_outside_the_grid_instead_of_an_index_error() -> None:
    grid = ipf_grid(sim.World(), COARSE)
    with pytest.raises(ValueError, match=r"source_cells must be flat cell indices in \[0, 400\)"):
        jacobi_field(grid, np.array([-1]), np.array([5.0]))


def test_ipf_grid_refuses_a_world_that_is_not_a_world() -> None:
    with pytest.raises(ValueError, match="world must be a sim.World or None, got str"):
        ipf_grid("warehouse")


def test_bad_shapes_and_indices_are_refused() -> None:
    with pytest.raises(ValueError, match=r"agents must have shape \(K, 2\)"):
        ipf_field(np.zeros((3, 3)), np.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"agent must be an index in \[0, 2\)"):
        ipf_field(np.array([[0.0, 0.0], [0.5, 0.5]]), np.zeros((0, 2)), agent=2)
    with pytest.raises(ValueError, match=r"claimed must have shape \(1,\)"):
        ipf_field(np.array([[0.0, 0.0]]), np.array([[0.5, 0.5]]), claimed=[True, False])
    with pytest.raises(ValueError, match="method"):
        ipf_field(np.array([[0.0, 0.0]]), np.array([[0.5, 0.5]]), method="sor")


# ---------------------------------------------------------------------- public name, picture
def test_public_name_via_sim() -> None:
    field = sim.ipf_field(np.array([[-0.5, 0.0]]), np.array([[0.5, 0.0]]), agent=0, world=None)
    assert field.values.shape == (len(field.y), len(field.x)) == (40, 40)


def test_plot_field_returns_a_figure_and_saves(tmp_path) -> None:
    agents, tasks = _scene(SHELVES, 3, 3, seed=1)
    field = ipf_field(agents, tasks, agent=1, world=SHELVES)
    path = tmp_path / "ipf.png"
    fig = plot_field(field, agents, tasks, 1, path=str(path), claimed=[False, True, False])
    assert fig.axes and path.stat().st_size > 1000


# ---------------------------------------------------------------------- the reward's potentials
def _reward_scene(seed: int = 0):
    """Four 6v6 environments after a few random steps: claims, parked AGVs, a finished one."""
    env = sim.make_env("6v6", num_envs=4, reward="minidist", seed=seed)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(6):
        env.step(torch.rand(4, 6, 2, generator=gen) * 2 - 1)
    assert (env.agent_task >= 0).any() and (env.agent_task < 0).any()
    return env, torch.tensor([True, False, True, True])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_reward_potentials_pay_parked_agvs_the_task_value_and_inactive_envs_zero(dtype) -> None:
    env, active = _reward_scene()
    grid = ipf_grid(env.world)
    plain = grid.agent_potentials(env.agent_pos.double(), env.task_pos.double(),
                                  ~env.task_claimed, native=False)
    got = grid.reward_potentials(env.agent_pos, env.task_pos, env.task_claimed, env.agent_task,
                                 active, dtype=dtype)
    assert got.dtype == dtype
    parked = env.agent_task >= 0
    assert torch.all(got[1] == 0.0)
    keep = active.unsqueeze(1) & ~parked
    torch.testing.assert_close(got[keep].double(), plain[keep], atol=1e-5, rtol=0)
    assert torch.all(got[active.unsqueeze(1) & parked] == TASK_VALUE)


@pytest.mark.skipif(not native.available(), reason="fused kernels unavailable")
def test_reward_potentials_kernel_path_equals_torch_path() -> None:
    env, active = _reward_scene(seed=1)
    grid = ipf_grid(env.world)
    args = (env.agent_pos, env.task_pos, env.task_claimed, env.agent_task, active)
    kernel = grid.reward_potentials(*args, kernels=native.library())
    torch_path = grid.reward_potentials(*args, kernels=None)
    torch.testing.assert_close(kernel, torch_path, atol=1e-5, rtol=0)


@pytest.mark.skipif(not native.available(), reason="fused kernels unavailable")
def test_reward_potentials_kernel_path_refuses_wrong_dtypes_naming_them() -> None:
    env, active = _reward_scene()
    grid = ipf_grid(env.world)
    lib = native.library()
    with pytest.raises(ValueError, match="task_pos .*float32"):
        grid.reward_potentials(env.agent_pos, env.task_pos.double(), env.task_claimed,
                               kernels=lib)
    with pytest.raises(ValueError, match="agent_pos .*float32"):
        grid.reward_potentials(env.agent_pos.double(), env.task_pos, kernels=lib)


@pytest.mark.parametrize("seed", [0, 1])
def test_reward_potentials_without_parked_sources_match_the_field_of_the_rest(seed) -> None:
    # Independent: the whole field of (the other idle AGVs at -3, the open tasks at +5),
    # solved directly, read at each idle AGV's cell; parked AGVs are not in it.
    env, active = _reward_scene(seed)
    grid = ipf_grid(env.world)
    got = grid.reward_potentials(env.agent_pos, env.task_pos, env.task_claimed, env.agent_task,
                                 active, parked_sources=False)
    shipped = grid.reward_potentials(env.agent_pos, env.task_pos, env.task_claimed,
                                     env.agent_task, active)
    parked = env.agent_task >= 0
    checked = 0
    for b in torch.nonzero(active).flatten().tolist():
        assert torch.all(got[b][parked[b]] == TASK_VALUE)
        open_tasks = env.task_pos[b][~env.task_claimed[b]].double()
        for i in torch.nonzero(~parked[b]).flatten().tolist():
            others = [j for j in range(6) if j != i and not parked[b, j]]
            points = torch.cat([env.agent_pos[b, others].double(), open_tasks])
            values = torch.tensor([AGENT_VALUE] * len(others) + [TASK_VALUE] * len(open_tasks))
            field = grid.fields(grid.cell_of(points).long()[None], values[None])[0]
            want = field.flatten()[grid.cell_of(env.agent_pos[b, i:i + 1].double()).long()]
            assert float(got[b, i]) == pytest.approx(float(want[0]), abs=1e-6)
            checked += 1
    assert checked > 0 and torch.all(got[1] == 0.0)
    # Parked AGVs at -3 pull the idle AGVs' fields down: dropping them raises every value.
    idle = active.unsqueeze(1) & ~parked
    assert torch.all(got[idle] >= shipped[idle] - 1e-9) and torch.any(got[idle] > shipped[idle])


def test_agent_sources_are_checked_and_need_the_torch_path() -> None:
    env, _ = _reward_scene()
    grid = ipf_grid(env.world)
    with pytest.raises(ValueError, match=r"agent_sources must be a bool tensor of shape"):
        grid.agent_potentials(env.agent_pos, env.task_pos, agent_sources=torch.ones(4, 6))
    with pytest.raises(ValueError, match=r"agent_sources must be a bool tensor of shape"):
        grid.agent_potentials(env.agent_pos, env.task_pos,
                              agent_sources=torch.ones(4, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="agent_sources needs the torch paths"):
        grid.agent_potentials(env.agent_pos, env.task_pos, native=True,
                              agent_sources=torch.ones(4, 6, dtype=torch.bool))
    every = grid.agent_potentials(env.agent_pos, env.task_pos, native=False)
    same = grid.agent_potentials(env.agent_pos, env.task_pos,
                                 agent_sources=torch.ones(4, 6, dtype=torch.bool))
    torch.testing.assert_close(same, every)


def test_reward_potentials_refuse_rule_tensors_of_the_wrong_shape() -> None:
    env, active = _reward_scene()
    grid = ipf_grid(env.world)
    with pytest.raises(ValueError, match=r"agent_task must have shape \(4, 6\)"):
        grid.reward_potentials(env.agent_pos, env.task_pos, agent_task=env.agent_task[:, :3])
    with pytest.raises(ValueError, match=r"active must have shape \(4,\)"):
        grid.reward_potentials(env.agent_pos, env.task_pos, active=active[:2])
    with pytest.raises(ValueError, match="dtype must be"):
        grid.reward_potentials(env.agent_pos, env.task_pos, dtype=torch.int64)


# ---------------------------------------------------------------------- the two reward paths
def test_block_path_equals_general_path() -> None:
    grid = ipf_grid(SHELVES)
    scenes = [_scene(SHELVES, 5, 4, seed=s) for s in range(4)]
    agents = torch.from_numpy(np.stack([a for a, _ in scenes]))
    tasks = torch.from_numpy(np.stack([t for _, t in scenes]))
    _, index = grid._tables(torch.device("cpu"))
    cells = grid.cell_of(torch.cat([agents, tasks], dim=1))
    fidx = index[cells]
    candidate = fidx < grid.num_free
    candidate[1, 5:7] = False  # two claimed tasks
    block = grid._potentials_block(fidx, candidate, 5, TASK_VALUE, AGENT_VALUE, None)
    general = grid._potentials_general(cells, fidx, candidate, 5, TASK_VALUE, AGENT_VALUE)
    torch.testing.assert_close(block, general, atol=1e-11, rtol=0)


def test_task_cache_follows_resets_and_claims() -> None:
    from sim.ipf import TaskBlockCache

    env = sim.make_env("6v6", num_envs=8, reward="minidist", seed=3)
    grid = ipf_grid(env.world)
    cache = TaskBlockCache()
    gen = torch.Generator().manual_seed(0)
    for k in range(12):
        if k % 5 == 4:
            env.reset(env_ids=[0, 3, 5])
        env.step(torch.rand(8, 6, 2, generator=gen) * 2 - 1)
        args = (env.agent_pos, env.task_pos, ~env.task_claimed)
        # The torch path's cache (the C kernel's has its own test in test_native.py).
        cached = grid.agent_potentials(*args, cache=cache, native=False)
        fresh = grid.agent_potentials(*args, native=False)
        torch.testing.assert_close(cached, fresh, atol=1e-6, rtol=0)
    assert env.task_claimed.any()
