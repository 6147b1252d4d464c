"""PettingZoo's own conformance tests, with warnings raised as errors, and rendering."""

import warnings

import pytest

import sim
from sim.controllers import NearestTaskController

pz_test = pytest.importorskip("pettingzoo.test")


@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse"])
def test_parallel_api(scenario: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pz_test.parallel_api_test(sim.pettingzoo_env(scenario, seed=0), num_cycles=100)


def test_parallel_seed() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pz_test.parallel_seed_test(lambda: sim.pettingzoo_env("3v3"), num_cycles=100)


def _layout(info: object) -> object:
    """The key-and-type layout of an info, as a wrapper building its spec from it sees it."""
    if isinstance(info, dict):
        return {k: _layout(v) for k, v in info.items()}
    return type(info).__name__


@pytest.mark.parametrize("reward", sorted(sim.REWARDS))
def test_reset_infos_have_the_step_infos_keys(reward: str) -> None:
    # TorchRL's PettingZooWrapper builds its info layout from the reset's infos: empty infos
    # at reset dropped the step's task and reward terms without a word.
    env = sim.pettingzoo_env("3v3", reward=reward, seed=0)
    _, reset_infos = env.reset(seed=0)
    _, _, _, _, step_infos = env.step({a: env.action_space(a).sample() for a in env.agents})
    assert sorted(reset_infos) == sorted(step_infos) == env.possible_agents
    for agent in env.possible_agents:
        assert _layout(reset_infos[agent]) == _layout(step_infos[agent])
        assert reset_infos[agent]["task"] == -1
        assert reset_infos[agent]["terms"]
        assert set(reset_infos[agent]["terms"].values()) == {0.0}


def test_bad_actions_named() -> None:
    env = sim.pettingzoo_env("3v3", seed=0)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="missing"):
        env.step({"agv_0": [0, 0]})
    with pytest.raises(ValueError, match="shape"):
        env.step({a: [0, 0, 0] for a in env.agents})


def test_render_scene_and_episode(tmp_path) -> None:
    env = sim.make_env("warehouse", num_envs=2, seed=0)
    png = tmp_path / "scene.png"
    sim.render_scene(env, env_index=1, path=png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    gif = tmp_path / "ep.gif"
    sim.render_episode(NearestTaskController(), "3v3", seed=0, path=gif, still=tmp_path / "s.png")
    assert gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    assert (tmp_path / "s.png").exists()
    assert not list(tmp_path.glob(".*"))  # no temporary files left behind
    rgb = sim.pettingzoo_env("3v3", seed=0, render_mode="rgb_array")
    rgb.reset(seed=0)
    assert rgb.render().ndim == 3
