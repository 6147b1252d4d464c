"""The fused C kernels (sim.native) against the torch reference paths they replace."""

from __future__ import annotations

import ctypes
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import sim
from sim import native
from sim.env import AGVEnv
from sim.ipf import AGENT_VALUE, TASK_VALUE, TaskBlockCache, ipf_grid, jacobi_field
from sim.scenarios import Scenario, get_scenario, paper_scenario

pytestmark = pytest.mark.skipif(not native.available(),
                                reason=f"kernels unavailable: {native.disabled_reason()}")

ROOT = Path(__file__).resolve().parents[2]


def _pair(scenario: str | Scenario, reward: str = "minidist",
          num_envs: int = 32) -> tuple[AGVEnv, AGVEnv]:
    fast = AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=3, native=True)
    ref = AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=3, native=False)
    assert fast.native and not ref.native
    return fast, ref


def _assert_same_step(out_fast, out_ref) -> None:
    (o1, r1, d1, i1), (o2, r2, d2, i2) = out_fast, out_ref
    torch.testing.assert_close(o1, o2, atol=1e-6, rtol=0)
    torch.testing.assert_close(r1, r2, atol=1e-5, rtol=0)
    assert torch.equal(d1, d2)
    for key in ("claimed_now", "agent_task", "collision_pairs", "collisions_per_agent",
                "active"):
        assert torch.equal(i1[key], i2[key]), key
    torch.testing.assert_close(i1["team_reward"], i2["team_reward"], atol=1e-5, rtol=0)
    assert i1["reward_terms"].keys() == i2["reward_terms"].keys()
    for key in i1["reward_terms"]:
        torch.testing.assert_close(i1["reward_terms"][key], i2["reward_terms"][key],
                                   atol=1e-5, rtol=0)


def _run_both_paths(scenario: str | Scenario) -> int:
    """50 steps with resets on both paths, checked equal at every step; returns the claims."""
    fast, ref = _pair(scenario)
    assert torch.equal(fast.reset(), ref.reset())
    gen = torch.Generator().manual_seed(1)
    claimed = 0
    for t in range(50):
        actions = torch.rand(32, fast.num_agents, 2, generator=gen) * 2 - 1
        out_fast, out_ref = fast.step(actions), ref.step(actions)
        _assert_same_step(out_fast, out_ref)
        for name in ("agent_pos", "agent_vel", "task_claimed", "agent_task", "steps", "done"):
            assert torch.equal(getattr(fast, name), getattr(ref, name)), name
        claimed += int(out_fast[3]["claimed_now"].sum())
        if t % 20 == 19:
            for env in (fast, ref):
                env.reset(out_fast[2])
    return claimed


@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse", "10v4", "2v7", "1v1"])
def test_step_matches_torch_path(scenario: str) -> None:
    assert _run_both_paths(scenario) > 0 or scenario == "1v1"


@pytest.mark.parametrize("n, m, options", [
    (6, 6, dict(sensing_range=0.7)),  # entries hidden by the range (lanes)
    (8, 5, dict(k_tasks=3, k_agents=3, sensing_range=1.2)),  # ranks past k (lanes)
    (5, 3, dict(k_tasks=4, k_agents=6)),  # more slots than entries (lanes)
    (7, 8, dict(k_tasks=8, k_agents=2, sensing_range=1.0)),
    (8, 8, dict(k_tasks=3, k_agents=0)),  # no AGV slots (lanes)
    (5, 1, dict(k_tasks=0, k_agents=4, sensing_range=0.5)),  # no task slots (lanes)
    (3, 3, dict(k_tasks=2, k_agents=1, sensing_range=0.7)),  # short lists, scalar ranks
    (9, 4, dict(k_tasks=2, k_agents=3, sensing_range=1.0)),  # general path
])
def test_step_matches_torch_path_with_short_lists_and_range(n: int, m: int, options) -> None:
    _run_both_paths(paper_scenario(n, m, **options))


@pytest.mark.parametrize("scenario", ["3v3", "6v6", "9v4", "warehouse"])
def test_fused_step_equals_each_rules_torch_reference(scenario: str) -> None:
    # The kernel's claims, overlaps, team reward R_t and observations, each against the one
    # torch function that defines it (sim.tasks, sim.physics, sim.observations).
    from sim import physics, tasks
    from sim.observations import observe

    seen: list[sim.StepContext] = []

    def spy(state: sim.SimState, ctx: sim.StepContext) -> dict:
        seen.append(ctx)
        return {}

    env = AGVEnv(scenario, num_envs=64, reward=spy, seed=5, native=True)
    gen = torch.Generator().manual_seed(2)
    claims = 0
    for _ in range(30):
        obs, _, _, info = env.step(torch.rand(64, env.num_agents, 2, generator=gen) * 2 - 1)
        ctx = seen[-1]
        rel = env.task_pos.unsqueeze(1) - env.agent_pos.unsqueeze(2)
        dist = torch.linalg.vector_norm(rel, dim=-1)
        torch.testing.assert_close(ctx.agent_task_dist, dist, atol=1e-6, rtol=0)
        agent_task, task_claimed, claimed_now, _ = tasks.claim(
            ctx.agent_task_dist, ctx.prev_agent_task, ctx.prev_task_claimed, ctx.active,
            env.world.capture_radius)
        assert torch.equal(env.agent_task, agent_task)
        assert torch.equal(env.task_claimed, task_claimed)
        assert torch.equal(info["claimed_now"], claimed_now)
        claims += int(claimed_now.sum())
        pair = physics.pair_distances(env.agent_pos)
        eye = torch.eye(env.num_agents, dtype=torch.bool)
        per_agent, pairs = physics.collisions(pair, ctx.active, env.world.agent_radius, eye,
                                              torch.ones_like(eye).triu(1))
        assert torch.equal(info["collisions_per_agent"], per_agent)
        assert torch.equal(info["collision_pairs"], pairs)
        team = tasks.team_reward(ctx.agent_task_dist, pairs, ctx.active)
        torch.testing.assert_close(info["team_reward"], team, atol=1e-5, rtol=0)
        reference = observe(env.agent_pos, env.agent_vel, env.task_claimed, env.agent_task,
                            env.obs_layout, env.scenario.sensing_range, (rel, dist), pair, eye)
        torch.testing.assert_close(obs, reference, atol=1e-6, rtol=0)
        done = env.done
        if done.any():
            env.reset(env_ids=done)
    assert claims > 0


def test_step_outputs_are_fresh_contiguous_float32() -> None:
    """The step allocates its outputs from expanded templates (torch.empty_like)."""
    env = AGVEnv("6v6", num_envs=4, seed=0, native=True)
    env.reset()
    first = env.step(torch.zeros(4, 6, 2))
    second = env.step(torch.zeros(4, 6, 2))
    for out in (first, second):
        obs, reward, _, info = out
        tensors = [obs, reward, info["team_reward"], info["collision_pairs"],
                   info["collisions_per_agent"], *info["reward_terms"].values()]
        assert all(t.is_contiguous() and t.dtype == torch.float32 for t in tensors)
        assert obs.shape == (4, 6, env.obs_dim)
        assert info["collision_pairs"].shape == (4,)
    assert first[0].data_ptr() != second[0].data_ptr()
    assert first[3]["collision_pairs"].data_ptr() != second[3]["collision_pairs"].data_ptr()


@pytest.mark.parametrize("scenario", ["3v3", "warehouse"])
def test_ipf_step_matches_torch_path(scenario: str) -> None:
    fast, ref = _pair(scenario, reward="ipf")
    fast.reset(), ref.reset()
    gen = torch.Generator().manual_seed(2)
    for t in range(30):
        actions = torch.rand(32, fast.num_agents, 2, generator=gen) * 2 - 1
        out_fast, out_ref = fast.step(actions), ref.step(actions)
        _assert_same_step(out_fast, out_ref)
        if t % 10 == 9:
            for env in (fast, ref):
                env.reset(env_ids=[0, 5, 7])


def test_observation_ties_go_to_the_lower_index() -> None:
    fast, ref = _pair("3v3", num_envs=1)
    # Tasks 0 and 2 at the same distance from AGV 0, AGVs 1 and 2 too: lower index first.
    agents = torch.tensor([[[0.0, 0.0], [0.5, 0.0], [-0.5, 0.0]]])
    tasks = torch.tensor([[[0.0, 0.6], [0.9, 0.9], [0.0, -0.6]]])
    for env in (fast, ref):
        env.set_state(agents, tasks)
    obs_fast, obs_ref = fast.observe(), ref.observe()
    assert torch.equal(obs_fast, obs_ref)
    first_task = obs_fast[0, 0, 4:6]
    assert first_task.tolist() == pytest.approx([0.0, 0.6])  # task 0 before task 2
    first_agent = obs_fast[0, 0, 4 + 3 * fast.k_tasks: 6 + 3 * fast.k_tasks]
    assert first_agent.tolist() == pytest.approx([0.5, 0.0])  # AGV 1 before AGV 2


def test_observation_ties_in_lanes_go_to_the_lower_index() -> None:
    """The vector-lane path (5 to 8 AGVs): symmetric scenes full of equal distances."""
    fast, ref = _pair("6v6", num_envs=2)
    ring = torch.tensor([[0.0, 0.5], [0.5, 0.0], [0.0, -0.5], [-0.5, 0.0], [0.5, 0.5]])
    agents = torch.cat([torch.zeros(1, 2), ring]).expand(2, 6, 2).clone()
    agents[1] = agents[1].flip(0)
    tasks = (ring.flip(0) * 1.4).repeat(2, 1)[:6].expand(2, 6, 2).clone()
    for env in (fast, ref):
        env.set_state(agents, tasks)
    obs_fast, obs_ref = fast.observe(), ref.observe()
    assert torch.equal(obs_fast, obs_ref)
    # AGV 0 sees task 1 at (-0.7, 0) first of the four tasks 0.7 away ...
    assert obs_fast[0, 0, 4:7].tolist() == pytest.approx([-0.7, 0.0, 1.0])
    # ... and AGV 1 at (0, 0.5) before AGVs 2, 3, 4 at the same distance.
    k = 4 + 3 * fast.k_tasks
    assert obs_fast[0, 0, k:k + 2].tolist() == pytest.approx([0.0, 0.5])


@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse", "20v20"])
def test_spawn_gives_the_same_scenes(scenario: str) -> None:
    sc = get_scenario(scenario)
    scenes = [sc.spawn(256, torch.Generator().manual_seed(5), torch.device("cpu"), kernels=lib)
              for lib in (native.library(), None)]
    assert torch.equal(scenes[0][0], scenes[1][0])
    assert torch.equal(scenes[0][1], scenes[1][1])


def _random_sources(world: sim.World, B: int, N: int, M: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    xmin, ymin, xmax, ymax = world.bounds
    lo, span = torch.tensor([xmin, ymin]), torch.tensor([xmax - xmin, ymax - ymin])
    agents = lo + span * torch.rand(B, N, 2, generator=gen)
    tasks = lo + span * torch.rand(B, M, 2, generator=gen)
    agents[: B // 4, 1] = agents[: B // 4, 0] + 1e-3  # two AGVs on one cell
    agents[B // 4: B // 2, 0] = tasks[B // 4: B // 2, 1]  # an AGV on a task's cell
    tasks[B // 2: 3 * B // 4, 1] = tasks[B // 2: 3 * B // 4, 0]  # two tasks on one cell
    open_ = torch.rand(B, M, generator=gen) < 0.7
    return agents.float(), tasks.float(), open_


@pytest.mark.parametrize("scenario", ["6v6", "warehouse", "12v5"])
def test_ipf_kernel_matches_torch_paths(scenario: str) -> None:
    world = get_scenario(scenario).world
    grid = ipf_grid(world)
    n, m = get_scenario(scenario).num_agents, get_scenario(scenario).num_tasks
    agents, tasks, open_ = _random_sources(world, 64, n, m, seed=len(scenario))
    for mask in (open_, None):
        claimed = None if mask is None else ~mask
        kernel = grid.reward_potentials(agents, tasks, claimed, kernels=native.library())
        torch_path = grid.agent_potentials(agents.double(), tasks.double(), mask, native=False)
        torch.testing.assert_close(kernel, torch_path, atol=1e-10, rtol=0)


def test_ipf_kernel_matches_jacobi() -> None:
    world = sim.World(obstacles=np.array([[-0.6, -0.2, -0.1, 0.2]]))
    grid = ipf_grid(world, 0.1)
    agents = torch.tensor([[[-0.8, -0.7], [0.3, 0.4], [0.7, -0.5]]], dtype=torch.float32)
    tasks = torch.tensor([[[0.0, 0.7], [0.6, 0.0]]], dtype=torch.float32)
    pot = grid.reward_potentials(agents, tasks, kernels=native.library())
    for i in range(3):
        others = np.delete(agents[0].double().numpy(), i, axis=0)
        cells = grid.cell_of(np.concatenate([others, tasks[0].double().numpy()])).numpy()
        values = np.r_[np.full(2, AGENT_VALUE), np.full(2, TASK_VALUE)]
        reference = jacobi_field(grid, cells, values, tol=1e-10)
        own = int(grid.cell_of(agents[0, i].double()))
        assert abs(float(pot[0, i]) - reference.ravel()[own]) < 1e-8


def test_ipf_kernel_cache_follows_resets_and_claims() -> None:
    env = sim.make_env("6v6", num_envs=16, seed=3)
    grid = ipf_grid(env.world)
    cache = TaskBlockCache()
    gen = torch.Generator().manual_seed(0)
    for k in range(15):
        if k % 5 == 4:
            env.reset(env_ids=[0, 3, 5])
        env.step(torch.rand(16, 6, 2, generator=gen) * 2 - 1)
        args = (env.agent_pos, env.task_pos, env.task_claimed)
        cached = grid.reward_potentials(*args, kernels=native.library(), cache=cache)
        fresh = grid.reward_potentials(*args, kernels=native.library())
        assert torch.equal(cached, fresh)
    assert env.task_claimed.any()


def test_ipf_kernel_refuses_bad_shapes_and_converts_masks() -> None:
    grid = ipf_grid()
    agents, tasks = torch.zeros(2, 3, 2), torch.full((2, 2, 2), 0.5)
    with pytest.raises(ValueError, match=r"task mask must have shape \(2, 2\)"):
        grid.agent_potentials(agents, tasks, torch.ones(2, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"agent_pos must have shape \(B, N, 2\)"):
        grid.agent_potentials(torch.zeros(2, 3), tasks)
    with pytest.raises(ValueError, match=r"task_pos must have shape \(2, M, 2\)"):
        grid.agent_potentials(agents, torch.zeros(3, 2, 2))
    with pytest.raises(ValueError, match=r"active must have shape \(2,\)"):
        grid.reward_potentials(agents, tasks, active=torch.ones(3, dtype=torch.bool),
                               kernels=native.library())
    # A float mask (converted inside) gives the same values as the bool mask.
    agents = torch.tensor([[[-0.5, 0.0], [0.5, 0.1], [0.0, -0.5]]] * 2)
    mask = torch.tensor([[1.0, 0.0], [0.0, 1.0]])
    as_float = grid.agent_potentials(agents, tasks + torch.tensor([0.0, 0.2]), mask)
    as_bool = grid.agent_potentials(agents, tasks + torch.tensor([0.0, 0.2]), mask.bool())
    assert torch.equal(as_float, as_bool)


def test_ipf_kernel_parked_and_inactive_rules() -> None:
    grid = ipf_grid()
    agents = torch.tensor([[[-0.5, 0.0], [0.5, 0.1]]] * 2)
    tasks = torch.tensor([[[0.0, 0.6], [0.5, -0.6]]] * 2)
    plain = grid.reward_potentials(agents, tasks, kernels=native.library())
    held = torch.tensor([[-1, 0], [-1, -1]])
    active = torch.tensor([True, False])
    ruled = grid.reward_potentials(agents, tasks, agent_task=held, active=active,
                                   kernels=native.library())
    assert ruled[0, 0] == plain[0, 0] and ruled[0, 1] == TASK_VALUE
    assert ruled[1].tolist() == [0.0, 0.0]


def test_clear_error_when_kernels_are_forced_but_unusable(monkeypatch) -> None:
    monkeypatch.setattr(native, "_lib", None)
    monkeypatch.setattr(native, "_reason", "no compiler here")
    with pytest.raises(ValueError, match="native=True.*no compiler here"):
        sim.make_env("3v3", native=True)
    assert not sim.make_env("3v3").native  # the default falls back to torch
    monkeypatch.undo()
    grid = ipf_grid()
    with pytest.raises(ValueError, match="native=True"):
        grid.agent_potentials(torch.zeros(1, 2, 2, dtype=torch.float64),
                              torch.ones(1, 1, 2, dtype=torch.float64) * 0.5, native=True)


def _run(code: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, env={**os.environ, **env}, timeout=120)


def test_agv_native_0_switches_the_kernels_off() -> None:
    code = ("import sim; env = sim.make_env('3v3'); print(env.native)\n"
            "try:\n    sim.make_env('3v3', native=True)\nexcept ValueError as e:\n"
            "    print('refused:', e)")
    out = _run(code, AGV_NATIVE="0")
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0] == "False"
    assert "AGV_NATIVE=0" in out.stdout


def test_failed_build_warns_and_falls_back(tmp_path) -> None:
    code = ("import warnings, torch, sim\nwarnings.simplefilter('always')\n"
            "env = sim.make_env('3v3', num_envs=2, seed=0)\n"
            "print(env.native, env.step(torch.zeros(2, 3, 2))[0].shape)")
    out = _run(code, CC="false", AGV_CACHE_DIR=str(tmp_path))
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[0] == "False"
    assert "kernels unavailable" in out.stderr


def _tiny_library(tmp_path: Path) -> tuple[Path, Path]:
    """A one-function C file that includes a header (compiles in a fraction of a second, where
    the kernels take seconds)."""
    (tmp_path / "tiny.h").write_text("#define TINY 7\n")
    (tmp_path / "tiny.c").write_text('#include "tiny.h"\nint agv_tiny(void) { return TINY; }\n')
    return tmp_path / "tiny.c", tmp_path / "tiny.h"


TINY_FLAGS = ["-O0", "-fPIC", "-shared"]


def test_damaged_cache_entry_is_rebuilt(tmp_path, monkeypatch) -> None:
    source, header = _tiny_library(tmp_path)
    monkeypatch.setenv("AGV_CACHE_DIR", str(tmp_path / "first"))
    assert native.load_cached(source, TINY_FLAGS, "tiny", [source, header]).agv_tiny() == 7
    (built,) = (tmp_path / "first").glob("tiny_*.so")
    # the same entry, damaged, in a cache this process has never loaded from
    damaged = tmp_path / "second" / built.name
    damaged.parent.mkdir()
    damaged.write_bytes(b"not a shared library")
    monkeypatch.setenv("AGV_CACHE_DIR", str(damaged.parent))
    assert native.load_cached(source, TINY_FLAGS, "tiny", [source, header]).agv_tiny() == 7
    assert damaged.read_bytes()[:4] == b"\x7fELF" or sys.platform != "linux"


def test_signature_table_is_read_from_every_exported_c_function() -> None:
    table = native.signatures()
    defined = set()
    for path in native.sources():
        for line in path.read_text().splitlines():
            head = line.split("(")[0].split()
            if len(head) == 2 and head[1].startswith("agv_") and not line.startswith("static"):
                defined.add(head[1])
    assert defined == set(table)
    assert {"agv_prepare", "agv_post_step", "agv_observe", "agv_ipf", "agv_spawn_pick",
            "agv_collide_shelves"} <= set(table)
    assert table["agv_prepare"] == (ctypes.c_int64, [ctypes.c_int64] * 2 + [ctypes.c_void_p] * 5)
    # Every kernel a Python module calls is in the table, so it is called with checked types.
    called = set()
    for path in (ROOT / "sim").rglob("*.py"):
        called |= set(re.findall(r"\.(agv_\w+)\(", path.read_text()))
    assert called and called <= set(table)
    lib = native.library()
    for name, (restype, argtypes) in table.items():
        assert getattr(lib, name).argtypes == argtypes
        assert getattr(lib, name).restype == restype


def test_signature_parser_refuses_a_c_type_it_cannot_map() -> None:
    with pytest.raises(ValueError, match=r"agv_x: parameter 'uint8_t flag'"):
        native.parse_signatures("int agv_x(int64_t n, uint8_t flag) {\n")
    assert native.parse_signatures("void agv_y(const float *a,\n    double x) {") == {
        "agv_y": (None, [ctypes.c_void_p, ctypes.c_double])}
    assert native.parse_signatures("static int agv_z(int64_t n) {") == {}


def test_kernel_calls_with_the_wrong_argument_count_are_refused() -> None:
    with pytest.raises(TypeError):
        native.library().agv_prepare(1, 1)


def test_build_key_covers_every_included_source_file(tmp_path, monkeypatch) -> None:
    # kernels.c includes the concept files: every file it includes is an input of the key
    included = set()
    for path in native.sources():
        included |= set(re.findall(r'#include "([^"]+)"', path.read_text()))
    assert included and included <= {p.name for p in native.sources()}
    # and a change in an input (not the compiled file itself) builds a new library
    source, header = _tiny_library(tmp_path)
    monkeypatch.setenv("AGV_CACHE_DIR", str(tmp_path / "cache"))
    assert native.load_cached(source, TINY_FLAGS, "tiny", [source, header]).agv_tiny() == 7
    header.write_text("#define TINY 8\n")
    assert native.load_cached(source, TINY_FLAGS, "tiny", [source, header]).agv_tiny() == 8
    assert len(list((tmp_path / "cache").glob("tiny_*.so"))) == 2


@pytest.mark.parametrize("bad, match", [
    (torch.zeros(2, 3, 2, dtype=torch.float64), "dtype torch.float64"),
    (torch.zeros(2, 3, 3), r"shape \(2, 3, 3\)"),
    (torch.zeros(3, 2, 2).transpose(0, 1), "non-contiguous"),
    (np.zeros((2, 3, 2), dtype=np.float32), "got ndarray"),
    (torch.zeros(2, 3, 2, dtype=torch.int32), "dtype torch.int32"),
])
def test_pointer_refuses_what_c_would_misread(bad, match: str) -> None:  # noqa: ANN001
    with pytest.raises(ValueError, match=f"task_pos must be a C-contiguous CPU tensor.*{match}"):
        native.pointer(bad, torch.float32, (2, 3, 2), "task_pos")


def test_pointer_accepts_the_exact_tensor_and_wildcards() -> None:
    t = torch.zeros(2, 3, 2)
    assert native.pointer(t, torch.float32, (2, 3, 2), "t") == t.data_ptr()
    assert native.pointer(t, torch.float32, (-1, 3, 2), "t") == t.data_ptr()
    with pytest.raises(ValueError, match="shape"):
        native.pointer(t, torch.float32, (-1, 3), "t")


@pytest.mark.parametrize("n, m, options", [
    (20, 30, dict(k_tasks=4, k_agents=4)),  # lists longer than SMALL: the lanes selection
    (12, 20, dict(k_tasks=3, k_agents=2, sensing_range=1.5)),  # k < 4, some hidden by range
    (10, 16, dict(k_tasks=6, k_agents=5)),  # k > 4: the insertion sort
])
def test_long_lists_on_a_grid_tie_as_torch(n: int, m: int, options: dict) -> None:
    # AGVs and tasks on a coarse integer grid: many exactly equal distances, so any other tie
    # rule than torch's (the lower index first) shows.
    sc = paper_scenario(n, m, **options)
    fast, ref = _pair(sc, num_envs=6)
    g = np.random.default_rng(0)
    half = sc.world.bounds[2] * 0.9
    grid = np.linspace(-half, half, 5)
    for _ in range(3):
        agents = g.choice(grid, size=(6, n, 2))
        tasks = g.choice(grid, size=(6, m, 2))
        for env in (fast, ref):
            env.set_state(agents, tasks)
        assert torch.equal(fast.observe(), ref.observe())
