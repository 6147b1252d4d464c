"""The public face of the environment: every bad input is a ValueError naming what is wrong."""

import numpy as np
import pytest
import torch

import sim
from sim import native as native_kernels

needs_kernels = pytest.mark.skipif(not native_kernels.available(),
                                   reason="fused CPU kernels unavailable")


@pytest.fixture
def env() -> sim.AGVEnv:
    return sim.make_env("3v3", num_envs=2, seed=0)


# ---------------------------------------------------------------------------- make_env
@pytest.mark.parametrize("scenario", [None, 3, 3.5, ["3v3"], b"3v3"])
def test_make_env_rejects_a_scenario_that_is_not_a_name_or_scenario(scenario: object) -> None:
    with pytest.raises(ValueError, match="scenario"):
        sim.make_env(scenario)
    with pytest.raises(ValueError, match="scenario"):
        sim.AGVEnv(scenario)


@pytest.mark.parametrize("reward", [["ipf"], 3, None, b"ipf"])
def test_make_env_rejects_a_reward_that_is_not_a_name_or_callable(reward: object) -> None:
    with pytest.raises(ValueError, match="reward"):
        sim.make_env("3v3", reward=reward)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_make_env_rejects_cuda_without_cuda() -> None:
    with pytest.raises(ValueError, match="device 'cuda'"):
        sim.make_env("3v3", device="cuda")


@pytest.mark.parametrize("device", ["gpu", 3, None])
def test_make_env_rejects_unknown_devices(device: object) -> None:
    with pytest.raises(ValueError, match="device"):
        sim.make_env("3v3", device=device)


@pytest.mark.parametrize("num_envs", [True, False, 0, -2, 2.0, "4", None])
def test_make_env_rejects_num_envs_that_is_not_a_positive_integer(num_envs: object) -> None:
    with pytest.raises(ValueError, match="num_envs"):
        sim.make_env("3v3", num_envs=num_envs)


@pytest.mark.parametrize("seed", [1.5, "1", True, -1, 2**64, [1]])
def test_make_env_rejects_seeds_that_are_not_integers_in_range(seed: object) -> None:
    with pytest.raises(ValueError, match="seed"):
        sim.make_env("3v3", seed=seed)


def test_make_env_accepts_numpy_integers_and_the_largest_seed() -> None:
    env = sim.make_env("3v3", num_envs=np.int64(2), seed=np.uint64(2**64 - 1))
    assert env.num_envs == 2


@pytest.mark.parametrize("native", ["yes", 1, 0.0, "False"])
def test_make_env_rejects_native_that_is_not_a_bool(native: object) -> None:
    with pytest.raises(ValueError, match="native"):
        sim.make_env("3v3", native=native)


# ---------------------------------------------------------------------------- user rewards
def _reward_returning(value: object):  # noqa: ANN202
    def reward(state: sim.SimState, ctx: sim.StepContext) -> object:
        return value(state) if callable(value) else value
    return reward


@pytest.mark.parametrize("native", [False, pytest.param(True, marks=needs_kernels)])
def test_reward_callable_returning_a_float_is_refused_in_the_step(native: bool) -> None:
    env = sim.make_env("3v3", num_envs=2, reward=_reward_returning({"r": 1.0}), native=native)
    with pytest.raises(ValueError, match="reward term 'r' must be a floating tensor"):
        env.step(torch.zeros(2, 3, 2))
    env = sim.make_env("3v3", num_envs=2, reward=_reward_returning(1.0), native=native)
    with pytest.raises(ValueError, match="must return a dict"):
        env.step(torch.zeros(2, 3, 2))


def test_reward_callable_returning_the_wrong_shape_is_refused() -> None:
    for shape in [(2,), (1, 3), (2, 3, 1), (3, 2)]:
        env = sim.make_env("3v3", num_envs=2, reward=_reward_returning({"r": torch.zeros(shape)}))
        with pytest.raises(ValueError, match=r"reward term 'r' must have shape \(2, 3\)"):
            env.step(torch.zeros(2, 3, 2))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_reward_callable_returning_nan_is_refused(bad: float) -> None:
    value = torch.zeros(2, 3)
    value[1, 2] = bad
    env = sim.make_env("3v3", num_envs=2, reward=_reward_returning({"r": value}))
    with pytest.raises(ValueError, match="'r' contains NaN or infinite"):
        env.step(torch.zeros(2, 3, 2))


def test_reward_callable_returning_integers_is_refused() -> None:
    env = sim.make_env("3v3", num_envs=2,
                       reward=_reward_returning({"r": torch.zeros(2, 3, dtype=torch.long)}))
    with pytest.raises(ValueError, match="floating tensor"):
        env.step(torch.zeros(2, 3, 2))


def test_a_good_reward_callable_is_summed_and_masked() -> None:
    env = sim.make_env("3v3", num_envs=2,
                       reward=_reward_returning(lambda s: {"a": s.agent_pos[..., 0],
                                                           "b": torch.ones(2, 3)}))
    _, reward, _, info = env.step(torch.zeros(2, 3, 2))
    torch.testing.assert_close(reward, env.agent_pos[..., 0] + 1.0)
    assert set(info["reward_terms"]) == {"a", "b"}


# ---------------------------------------------------------------------------- step
@pytest.mark.parametrize("actions", ["left", None, b"xx", {"a": 1}, object()])
def test_step_rejects_actions_that_are_not_numbers(env: sim.AGVEnv, actions: object) -> None:
    with pytest.raises(ValueError, match="actions"):
        env.step(actions)


@pytest.mark.parametrize("native", [False, pytest.param(True, marks=needs_kernels)])
def test_step_rejects_complex_actions(native: bool) -> None:
    env = sim.make_env("3v3", num_envs=2, seed=0, native=native)
    with pytest.raises(ValueError, match="actions must hold real numbers"):
        env.step(torch.zeros(2, 3, 2, dtype=torch.complex64))
    with pytest.raises(ValueError, match="actions must hold real numbers"):
        env.step(np.zeros((2, 3, 2), dtype=complex))


def test_step_rejects_boolean_actions(env: sim.AGVEnv) -> None:
    with pytest.raises(ValueError, match="actions must hold real numbers"):
        env.step(torch.zeros(2, 3, 2, dtype=torch.bool))


@pytest.mark.parametrize("shape", [(2, 3), (3, 2), (2, 3, 3), (1, 3, 2), (2, 3, 2, 1), ()])
def test_step_rejects_actions_of_the_wrong_shape(env: sim.AGVEnv, shape: tuple) -> None:
    with pytest.raises(ValueError, match="actions must have shape"):
        env.step(torch.zeros(shape))


def test_step_accepts_lists_ints_and_float64(env: sim.AGVEnv) -> None:
    ref = sim.make_env("3v3", num_envs=2, seed=0)
    ref_out = ref.step(torch.ones(2, 3, 2))
    for actions in ([[[1, 1]] * 3] * 2, np.ones((2, 3, 2), dtype=np.int32),
                    torch.ones(2, 3, 2, dtype=torch.float64)):
        e = sim.make_env("3v3", num_envs=2, seed=0)
        out = e.step(actions)
        assert torch.equal(out[0], ref_out[0]) and torch.equal(out[1], ref_out[1])


# ---------------------------------------------------------------------------- reset
@pytest.mark.parametrize("env_ids", [[0.5], [1.0], np.array([0.0]), torch.tensor([0.7]),
                                     "0", [[0, 1j]]])
def test_reset_rejects_env_ids_that_are_not_integers(env: sim.AGVEnv, env_ids: object) -> None:
    before = env.agent_pos.clone()
    with pytest.raises(ValueError, match="env_ids"):
        env.reset(env_ids=env_ids)
    assert torch.equal(env.agent_pos, before)


@pytest.mark.parametrize("env_ids", [[2], [-1], [True], np.array([True, False, True])])
def test_reset_rejects_env_ids_out_of_range_or_masks_of_the_wrong_length(
        env: sim.AGVEnv, env_ids: object) -> None:
    with pytest.raises(ValueError, match="env"):
        env.reset(env_ids=env_ids)


@pytest.mark.parametrize("seed", [1.5, "3", -1, 2**64, True, float("nan")])
def test_reset_rejects_bad_seeds(env: sim.AGVEnv, seed: object) -> None:
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=seed)


def test_reset_seed_gives_the_same_scenes(env: sim.AGVEnv) -> None:
    a = env.reset(seed=np.int64(7))
    b = env.reset(seed=7)
    assert torch.equal(a, b)


# ---------------------------------------------------------------------------- set_state
@pytest.mark.parametrize("bad", ["abc", None, [[["a", "b"]] * 3] * 2])
def test_set_state_rejects_positions_that_are_not_numbers(env: sim.AGVEnv, bad: object) -> None:
    with pytest.raises(ValueError, match="agent_pos"):
        env.set_state(bad, env.task_pos)


def test_set_state_rejects_complex_and_boolean_positions(env: sim.AGVEnv) -> None:
    with pytest.raises(ValueError, match="task_pos must hold real numbers"):
        env.set_state(env.agent_pos, env.task_pos.to(torch.complex64))
    with pytest.raises(ValueError, match="agent_pos must hold real numbers"):
        env.set_state(np.zeros((2, 3, 2), dtype=bool), env.task_pos)
    with pytest.raises(ValueError, match="agent_vel must hold real numbers"):
        env.set_state(env.agent_pos, env.task_pos, agent_vel=np.zeros((2, 3, 2), dtype=complex))


def test_set_state_accepts_float64_and_lists(env: sim.AGVEnv) -> None:
    a, t = env.agent_pos.clone(), env.task_pos.clone()
    env.set_state(a.double(), t.tolist())
    assert torch.equal(env.agent_pos, a) and torch.equal(env.task_pos, t)


# ---------------------------------------------------------------------------- state setters
def test_task_pos_setter_rejects_float64_that_gave_a_wrong_team_reward_on_the_c_path() -> None:
    for native in (False, True) if native_kernels.available() else (False,):
        env = sim.make_env("3v3", num_envs=2, seed=0, native=native)
        with pytest.raises(ValueError, match=r"task_pos must be a torch.float32 tensor of shape "
                                             r"\(2, 3, 2\)"):
            env.task_pos = env.task_pos.double()


@pytest.mark.parametrize("name, bad", [
    ("agent_pos", lambda e: e.agent_pos.double()),
    ("agent_pos", lambda e: e.agent_pos[:1]),
    ("agent_pos", lambda e: e.agent_pos.numpy()),
    ("agent_pos", lambda e: e.agent_pos.reshape(2, 6)),
    ("agent_vel", lambda e: e.agent_vel.half()),
    ("task_pos", lambda e: e.task_pos[:, :2]),
    ("task_claimed", lambda e: e.task_claimed.long()),
    ("task_claimed", lambda e: e.task_claimed[:, :1]),
    ("agent_task", lambda e: e.agent_task.int()),
    ("agent_task", lambda e: e.agent_task.float()),
    ("steps", lambda e: e.steps.int()),
    ("steps", lambda e: e.steps[:1]),
    ("done", lambda e: e.done.long()),
])
def test_state_setters_reject_wrong_dtype_shape_or_type(name: str, bad) -> None:  # noqa: ANN001
    env = sim.make_env("3v3", num_envs=2, seed=0)
    before = getattr(env, name).clone()
    with pytest.raises(ValueError, match=name):
        setattr(env, name, bad(env))
    assert torch.equal(getattr(env, name), before)


def test_state_setters_reject_non_finite_positions(env: sim.AGVEnv) -> None:
    pos = env.agent_pos.clone()
    pos[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="agent_pos contains NaN"):
        env.agent_pos = pos


@pytest.mark.parametrize("value", [-2, 3, 100])
def test_agent_task_setter_rejects_task_indices_out_of_range(env: sim.AGVEnv, value: int) -> None:
    with pytest.raises(ValueError, match=r"agent_task values must lie in \[-1, 3\)"):
        env.agent_task = torch.full((2, 3), value)


def test_steps_setter_rejects_negative_steps(env: sim.AGVEnv) -> None:
    with pytest.raises(ValueError, match="steps must be >= 0"):
        env.steps = torch.tensor([0, -1])


def test_agent_pos_setter_refreshes_the_observation_of_the_torch_path() -> None:
    envs = [sim.make_env("3v3", num_envs=2, seed=0, native=n)
            for n in ((False, True) if native_kernels.available() else (False,))]
    for env in envs:
        env.observe()
        env.agent_pos = env.agent_pos + 0.05
    observed = [env.observe() for env in envs]
    assert torch.equal(observed[0][..., envs[0].obs_layout.pos], envs[0].agent_pos)
    assert torch.equal(observed[0][..., envs[0].obs_layout.tasks],
                       observed[-1][..., envs[0].obs_layout.tasks])


def test_state_setters_accept_the_right_tensors_and_both_paths_agree() -> None:
    outs = []
    for native in (False, True) if native_kernels.available() else (False,):
        env = sim.make_env("3v3", num_envs=2, seed=0, native=native)
        env.task_pos = env.task_pos.flip(1).contiguous()
        env.agent_vel = torch.full((2, 3, 2), 0.3)[..., :].transpose(0, 1).contiguous() \
            .transpose(0, 1)  # non-contiguous: stored contiguous
        assert env.agent_vel.is_contiguous()
        outs.append(env.step(torch.zeros(2, 3, 2)))
    for a, b in zip(outs[0][:3], outs[-1][:3], strict=True):
        torch.testing.assert_close(a, b)
    torch.testing.assert_close(outs[0][3]["team_reward"], outs[-1][3]["team_reward"])


# ---------------------------------------------------------------------------- layout
def test_obs_layout_names_every_feature() -> None:
    env = sim.make_env("6v6", num_envs=1, seed=0)
    lay = env.obs_layout
    assert lay.size == env.obs_dim == env.observe().shape[-1]
    width = [lay.vel, lay.pos, lay.tasks, lay.agents, lay.holding]
    assert sum(s.stop - s.start for s in width) == lay.size
    assert lay.tasks.stop - lay.tasks.start == 3 * lay.k_tasks
    assert lay.agents.stop - lay.agents.start == 5 * lay.k_agents
    assert lay.task_rel(0) == slice(4, 6) and lay.task_mask(0) == slice(6, 7)
    assert lay.agent_mask(lay.k_agents - 1).stop == lay.holding.start
    obs = env.observe()
    torch.testing.assert_close(obs[..., lay.vel], env.agent_vel)
    torch.testing.assert_close(obs[..., lay.pos], env.agent_pos)
    with pytest.raises(ValueError, match="slot k"):
        lay.task_rel(lay.k_tasks)
    with pytest.raises(ValueError, match="k_tasks"):
        sim.observations.ObsLayout(-1, 2)


@pytest.mark.parametrize("native", [False, pytest.param(True, marks=needs_kernels)])
def test_step_with_actions_that_require_grad_builds_no_graph_across_steps(native: bool) -> None:
    # A policy's output passed without detach() made the velocities part of an autograd graph
    # that grew with every step (and the C path wrote into such a tensor behind autograd).
    env = sim.make_env("3v3", num_envs=2, seed=0, native=native)
    ref = sim.make_env("3v3", num_envs=2, seed=0, native=native)
    weight = torch.ones((), requires_grad=True)
    for _ in range(3):
        actions = torch.full((2, 3, 2), 0.5) * weight
        out = env.step(actions)
        expected = ref.step(actions.detach())
        assert torch.equal(out[0], expected[0]) and torch.equal(out[1], expected[1])
    for name in ("agent_pos", "agent_vel"):
        assert not getattr(env, name).requires_grad, name
    assert not out[0].requires_grad and not out[1].requires_grad


def test_reset_and_set_state_reject_repeated_env_ids(env: sim.AGVEnv) -> None:
    # A repeated id placed two scenes in one environment, and which one stayed was undefined.
    with pytest.raises(ValueError, match="env_ids must not repeat"):
        env.reset(env_ids=[1, 1])
    with pytest.raises(ValueError, match="env_ids must not repeat"):
        env.set_state(torch.cat([env.agent_pos[:1], env.agent_pos[1:]]),
                      torch.cat([env.task_pos[:1], env.task_pos[1:]]), env_ids=[0, 0])


def test_set_state_with_tensors_that_require_grad_keeps_no_graph(env: sim.AGVEnv) -> None:
    a = env.agent_pos.clone().requires_grad_()
    env.set_state(a, env.task_pos)
    assert not env.agent_pos.requires_grad
    env.step(torch.zeros(2, 3, 2))
    assert not env.agent_pos.requires_grad and not env.agent_vel.requires_grad


@pytest.mark.parametrize("reward", ["minidist", "greedy"])
@pytest.mark.parametrize("native", [False, pytest.param(True, marks=needs_kernels)])
def test_env_works_the_same_under_a_float64_default_dtype(native: bool, reward: str) -> None:
    # torch.set_default_dtype(torch.float64), common in scientific code, made the physics
    # promote the positions to float64 (the next step then failed inside torch.bmm) and the
    # spawn draw other scenes.
    def run() -> list[torch.Tensor]:
        env = sim.make_env("warehouse", num_envs=4, seed=2, native=native, reward=reward)
        out = [env.reset()]
        for _ in range(4):
            obs, r, done, _ = env.step(torch.full((4, 6, 2), 0.3, dtype=torch.float32))
            out += [obs, r, env.agent_pos, env.agent_vel]
        return out

    expected = run()
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        got = run()
    finally:
        torch.set_default_dtype(old)
    for a, b in zip(expected, got, strict=True):
        assert a.dtype == b.dtype == torch.float32 and torch.equal(a, b)


def test_device_cpu_0_is_the_cpu_tensors_report() -> None:
    # "cpu:0" compared unequal to the "cpu" of every tensor: the setters refused the env's own
    # tensors and every action took the slow conversion path.
    env = sim.make_env("3v3", num_envs=2, seed=0, device="cpu:0")
    assert env.device == env.agent_pos.device == torch.device("cpu")
    env.task_pos = env.task_pos.clone()
    env.step(torch.zeros(2, 3, 2))


@pytest.mark.parametrize("points", [[["a", "b"]], [[1 + 2j, 0.0]], [[True, False]],
                                    [[0.0, 0.0], [1.0]]],
                         ids=["strings", "complex", "bool", "ragged"])
def test_world_check_positions_refuses_what_is_not_real_numbers(points) -> None:
    """numpy raised its own error for strings and kept only the real part of complex numbers."""
    with pytest.raises(ValueError, match="agent_pos"):
        sim.World().check_positions(points, "agent_pos")


def test_given_scene_scenario_starts_every_episode_from_the_scene() -> None:
    """A scene the random spawner could not draw (20 AGVs on the 3v3 box, close together) runs
    as given; before, callers had to subclass Scenario and override its private checks."""
    base = sim.get_scenario("3v3")
    agents = np.stack([np.linspace(-0.8, 0.8, 20), np.zeros(20)], axis=1)
    tasks = np.array([[0.0, 0.7], [0.5, -0.6]])
    scn = sim.Scenario.given_scene(base, agents, tasks, max_steps=7)
    assert (scn.num_agents, scn.num_tasks, scn.max_steps) == (20, 2, 7)
    env = sim.make_env(scn, num_envs=3, seed=0)
    for _ in range(2):
        assert torch.equal(env.agent_pos, torch.as_tensor(agents, dtype=torch.float32)
                           .expand(3, -1, -1))
        assert torch.equal(env.task_pos[1], torch.as_tensor(tasks, dtype=torch.float32))
        env.reset()


@pytest.mark.parametrize("agents, match", [([[5.0, 0.0]], "outside the world"),
                                           ([[0.0, 0.0, 0.0]], "shape"),
                                           ([["a", "b"]], "real numbers")])
def test_given_scene_refuses_positions_it_cannot_run(agents, match) -> None:
    with pytest.raises(ValueError, match=match):
        sim.Scenario.given_scene(sim.get_scenario("3v3"), agents, [[0.0, 0.5]])
    with pytest.raises(ValueError, match="unknown scenario option"):
        sim.Scenario.given_scene(sim.get_scenario("3v3"), [[0.0, 0.0]], [[0.0, 0.5]], steps=3)
