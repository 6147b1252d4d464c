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
