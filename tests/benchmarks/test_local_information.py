"""``benchmarks/local_information.py`` (the coordinating rule at a local view) and
``benchmarks/dagger_probe.py`` (its full-view teacher taught to an entity policy)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from benchmark_scripts import ROOT, load

import allocator
import sim

local = load("local_information")
dagger = load("dagger_probe")
PARKED = ROOT / "benchmarks/results/scale/entity/bicnet-e-parked/parked.safetensors"


def test_own_share_leaves_the_task_a_rival_is_nearer_to() -> None:
    # the rival at (1, 0) is 0.1 from task 0; taking it myself would cost 0.9 + 1.5
    tasks = np.array([[0.9, 0.0], [-0.5, 0.0]])
    assert local.own_share(tasks, np.array([[1.0, 0.0]])) == 1
    assert local.own_share(tasks, np.zeros((0, 2))) == 1  # alone: the least cost is the nearest
    # more AGVs than tasks, the others nearer: mine is the nearest task
    assert local.own_share(tasks[:1], np.array([[1.0, 0.0]])) == 0


def test_velocity_action_keeps_the_direction_and_the_box() -> None:
    ph = sim.World().physics
    rel = np.array([[3.0, 1.0], [0.01, 0.0]])
    a = local.velocity_action(rel, np.zeros((2, 2)), ph, 2.0)
    assert np.abs(a).max() <= 1.0 + 1e-12
    assert np.allclose(a[0] / np.linalg.norm(a[0]), rel[0] / np.linalg.norm(rel[0]))
    # close by, from rest: the command arrives in one step (v = rel / dt)
    v = a[1] * ph.sensitivity * ph.dt / ph.mass
    assert np.allclose(v * ph.dt, rel[1])


def test_full_view_rule_is_the_teachers_assignment() -> None:
    scen = sim.get_scenario("10v10", k_tasks=10, k_agents=9)
    env = sim.make_env(scen, num_envs=3, seed=4)
    obs = env.observe()
    rule = local.LocalAssignment()
    rule.reset(env)
    for _ in range(6):  # every AGV sees the whole scene: each solves the teacher's problem
        ours, teacher = rule.act(obs), dagger.teacher_actions(env)
        assert torch.allclose(ours, teacher, atol=1e-5)
        obs, *_ = env.step(teacher)


def test_rule_finishes_small_scenes() -> None:
    m = sim.evaluate(local.LocalAssignment(), "3v3", episodes=10, seed=0)
    assert m.response_rate >= 0.9


def test_bad_input_is_named() -> None:
    for spec in ("6", "a:b", "0:3", "3:-1"):
        with pytest.raises(ValueError, match="view"):
            local.view(10, spec)
    assert local.view(10, "full") == (10, 9) and local.view(4, "6:5") == (4, 3)
    with pytest.raises(ValueError, match="max_speed"):
        local.LocalAssignment(max_speed=0.0)
    with pytest.raises(ValueError, match="reset"):
        local.LocalAssignment().act(torch.zeros(1, 3, 24))
    with pytest.raises(SystemExit):
        local.main(["--sizes", "3", "--episodes", "1", "2"])
    with pytest.raises(SystemExit):
        local.main(["--views", "x"])


def test_main_writes_the_table(tmp_path: Path) -> None:
    local.main(["--sizes", "3", "--episodes", "2", "--views", "1:1", "full",
                "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "local.json").read_text())["rows"]
    assert [(r["method"], r["view"], r["shield"]) for r in rows] == [
        ("hungarian", "-", False), ("local-assignment", "1:1", False),
        ("local-assignment", "1:1", True), ("local-assignment", "3:2", False),
        ("local-assignment", "3:2", True)]
    assert rows[0]["time_vs_hungarian"] == 1.0
    assert "| 3v3 | local-assignment | 3:2 | yes |" in (tmp_path / "local.md").read_text()


def test_detour_adds_a_shielded_detour_row_per_view(tmp_path: Path) -> None:
    local.main(["--sizes", "3", "--episodes", "2", "--views", "full", "--detour",
                "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "local.json").read_text())["rows"]
    assert [(r["shield"], r["detour"]) for r in rows] == [
        (False, False), (False, False), (True, False), (True, "squares")]
    assert rows[-1]["overlaps"] == 0
    assert "| 3:2 | yes + squares detour |" in (tmp_path / "local.md").read_text()
    local.main(["--sizes", "3", "--episodes", "2", "--views", "full", "--detour", "discs",
                "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "local.json").read_text())["rows"]
    assert rows[-1]["detour"] == "discs" and rows[-1]["overlaps"] == 0
    assert "| 3:2 | yes + discs detour |" in (tmp_path / "local.md").read_text()
    with pytest.raises(SystemExit):
        local.main(["--sizes", "3", "--episodes", "2", "--detour", "round",
                    "--out", str(tmp_path)])


def test_dagger_writes_a_policy_the_allocator_serves(tmp_path: Path) -> None:
    dagger.main(["--start", str(PARKED), "--iterations", "1", "--steps", "2",
                 "--sizes", "6v6", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["view"] == "6:5" and not probe["shield"]
    assert "shielded_response" in probe["final"]
    assert (tmp_path / "progress.csv").read_text().startswith("iteration,loss,seconds")
    solver = allocator.make("bicnet-ipf", scenario="6v6", shield=True,
                            checkpoint=tmp_path / "dagger.safetensors")
    assert sim.evaluate(solver, "6v6", episodes=2, seed=0).response_rate > 0


def test_dagger_refuses_what_it_cannot_teach(tmp_path: Path) -> None:
    paper = ROOT / "allocator/weights/6v6/bicnet-ipf.safetensors"
    with pytest.raises(SystemExit):  # not an entity policy
        dagger.main(["--start", str(paper), "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        dagger.main(["--start", str(PARKED), "--lr", "nan", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        dagger.main(["--start", str(tmp_path / "missing.safetensors"), "--out", str(tmp_path)])


def test_dagger_rolls_out_through_the_shield(tmp_path: Path) -> None:
    env = sim.make_env("6v6", num_envs=2, seed=0)
    learner = allocator.make("bicnet-ipf", scenario="6v6", checkpoint=PARKED).policy.learner
    gen = torch.Generator().manual_seed(0)
    obs, target, moving, slots = dagger.rollout(learner, sim.get_scenario("6v6"), 2, 0, 0.5,
                                                gen, shield=True)
    assert obs.shape[1:] == (6, env.obs_dim) and target.shape == (len(obs), 6, 2)
    assert moving.shape == (len(obs), 6) and target.abs().max() <= 1.0 + 1e-6
    assert slots.shape == (len(obs), 6) and slots.dtype == torch.int64
    assert not (slots[~moving] >= 0).any()  # only idle AGVs get a task from the teacher


def test_choice_slots_name_the_slot_of_the_teachers_task() -> None:
    env = sim.make_env("6v6", num_envs=4, seed=3)
    obs = env.observe()
    actions, chosen = dagger.teacher(env)
    slots = dagger.choice_slots(obs, env.obs_layout, chosen)
    layout = env.obs_layout
    t = obs[..., layout.tasks].reshape(4, 6, layout.k_tasks, 3)
    has = slots >= 0
    assert has.all()  # at the start every AGV is idle and sees every task (6 slots, 6 tasks)
    picked = t.gather(2, slots.clamp_min(0)[..., None, None].expand(4, 6, 1, 3)).squeeze(2)
    assert np.allclose(picked[..., :2].numpy(), chosen, atol=1e-5)
    # every AGV is sent to a different task: the teacher's assignment is one-to-one
    goals = (obs[..., layout.pos] + picked[..., :2]).numpy()
    for b in range(4):
        assert len({tuple(np.round(g, 5)) for g in goals[b]}) == 6
    # a goal out of view (NaN: no goal) names no slot
    chosen[0, 0] = np.nan
    assert dagger.choice_slots(obs, layout, chosen)[0, 0] == -1
    torch.testing.assert_close(actions, dagger.teacher_actions(env))


def test_dagger_trains_a_choice_head_student(tmp_path: Path) -> None:
    dagger.main(["--start", str(PARKED), "--iterations", "1", "--steps", "3",
                 "--sizes", "6v6", "--choice-head", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["choice_head"] and probe["choice_weight"] == 1.0
    assert probe["fresh"] and all(n.startswith("actor.choose.") for n in probe["fresh"])
    solver = allocator.make("bicnet-ipf", scenario="10v10", shield=True,
                            checkpoint=tmp_path / "dagger.safetensors")
    assert solver.policy.learner.config.choice_head
    assert sim.evaluate(solver, "10v10", episodes=2, seed=0).collisions == 0
    with pytest.raises(SystemExit):
        dagger.main(["--start", str(PARKED), "--choice-head", "--choice-weight", "-1",
                     "--out", str(tmp_path)])


def test_dagger_adds_an_intent_exchange_to_a_choice_head_student(tmp_path: Path) -> None:
    dagger.main(["--start", str(PARKED), "--iterations", "1", "--steps", "2",
                 "--sizes", "6v6", "--choice-head", "--choice-rounds", "1",
                 "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["choice_rounds"] == 1
    assert any(n.startswith("actor.choose.intent.") for n in probe["fresh"])
    solver = allocator.make("bicnet-ipf", scenario="10v10", shield=True,
                            checkpoint=tmp_path / "dagger.safetensors")
    assert solver.policy.learner.config.choice_rounds == 1
    assert sim.evaluate(solver, "10v10", episodes=2, seed=0).collisions == 0
    for bad in (["--choice-rounds", "-1", "--choice-head"], ["--choice-rounds", "1"]):
        with pytest.raises(SystemExit):
            dagger.main(["--start", str(PARKED), *bad, "--out", str(tmp_path)])


def test_dagger_regrets_widen_a_trained_exchange_without_changing_it(tmp_path: Path) -> None:
    from learners.algorithms import make_learner
    from learners.checkpoint import load_checkpoint

    talk = tmp_path / "talk"
    dagger.main(["--start", str(PARKED), "--iterations", "1", "--steps", "2",
                 "--sizes", "6v6", "--choice-head", "--choice-rounds", "1",
                 "--out", str(talk)])
    tensors, meta = load_checkpoint(talk / "dagger.safetensors", kind="policy")
    with torch.no_grad():  # a trained-looking exchange, so that the start is not trivial
        for name in tensors:
            if name.startswith("actor.choose.intent."):
                tensors[name] = torch.randn_like(tensors[name])
    wider = make_learner("bicnet-e", meta["obs_dim"], meta["state_dim"], meta["num_agents"],
                         {**meta["config"], "choice_regret": True})
    fitted, fresh = dagger.fitting_tensors(wider, tensors)
    assert fresh == ["actor.choose.intent.0.weight"]
    assert fitted[fresh[0]].shape[1] == tensors[fresh[0]].shape[1] + 2
    wider.load_policy_tensors(fitted)
    narrow = make_learner("bicnet-e", meta["obs_dim"], meta["state_dim"], meta["num_agents"],
                          meta["config"])
    narrow.load_policy_tensors(tensors)
    env = sim.make_env(sim.get_scenario("6v6"), num_envs=4, seed=1)
    obs = env.observe()
    torch.testing.assert_close(wider.act(obs), narrow.act(obs))
    dagger.main(["--start", str(talk / "dagger.safetensors"), "--iterations", "1",
                 "--steps", "2", "--sizes", "6v6", "--choice-regret", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["choice_regret"] is True and probe["choice_rounds"] == 1


def test_dagger_adds_the_assignment_exchange(tmp_path: Path) -> None:
    dagger.main(["--start", str(PARKED), "--iterations", "1", "--steps", "2",
                 "--sizes", "6v6", "--choice-head", "--choice-sinkhorn", "4",
                 "--first-share", "0.3", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["choice_sinkhorn"] == 4 and "actor.choose.sinkhorn_scale" in probe["fresh"]
    assert probe["first_share"] == 0.3
    solver = allocator.make("bicnet-ipf", scenario="10v10", shield=True,
                            checkpoint=tmp_path / "dagger.safetensors")
    assert solver.policy.learner.config.choice_sinkhorn == 4
    assert sim.evaluate(solver, "10v10", episodes=2, seed=0).collisions == 0
    # --iterations 0: the start under the flags, untrained, validated once
    untrained = tmp_path / "untrained"
    dagger.main(["--start", str(tmp_path / "dagger.safetensors"), "--iterations", "0",
                 "--choice-sinkhorn", "2", "--sinkhorn-beta", "100", "--out", str(untrained)])
    probe = json.loads((untrained / "dagger.probe.json").read_text())
    assert probe["choice_sinkhorn"] == 2 and probe["fresh"] == []
    assert probe["choice_sinkhorn_beta"] == 100.0
    again = allocator.make("bicnet-ipf", scenario="10v10",
                           checkpoint=untrained / "dagger.safetensors")
    assert again.policy.learner.config.choice_sinkhorn_beta == 100.0
    assert probe["final"]["iteration"] == 0 and probe["final"]["loss"] is None
    assert 0 < probe["final"]["response"] <= 1
    for bad in (["--choice-sinkhorn", "-1", "--choice-head"], ["--choice-sinkhorn", "2"],
                ["--iterations", "-1"], ["--sinkhorn-beta", "2"], ["--sinkhorn-beta", "nan"],
                ["--sinkhorn-beta", ""], ["--sinkhorn-beta", "1e9"], ["--sinkhorn-beta", "100"],
                ["--first-share", "1.5"], ["--first-share", "-0.1"]):
        with pytest.raises(SystemExit):
            dagger.main(["--start", str(PARKED), *bad, "--out", str(tmp_path)])


def test_imitation_loss_counts_only_movable_agvs_and_their_labels() -> None:
    act = torch.tensor([[[0.5, 0.0], [1.0, 1.0], [0.0, 0.0]]])
    target = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    movable = torch.tensor([[True, False, True]])  # AGV 1's error does not count
    w = torch.tensor([[[0.25, 0.75], [1.0, 0.0], [0.5, 0.5]]])
    labels = torch.tensor([[0, 0, -1]])  # AGV 2 has no label, AGV 1 cannot move
    loss = dagger.imitation_loss(act, target, movable, w, labels, choice_weight=2.0)
    expected = 0.25 / 2 + 2.0 * -torch.log(torch.tensor(0.25))
    torch.testing.assert_close(loss, expected)
    no_choice = dagger.imitation_loss(act, target, movable, None, labels, choice_weight=2.0)
    torch.testing.assert_close(no_choice, torch.tensor(0.125))
    assert dagger.imitation_loss(act, target, torch.zeros_like(movable), w, labels, 1.0) == 0
    # action_weight scales the action term only (0: the choice alone)
    choice = dagger.imitation_loss(act, target, movable, w, labels, 2.0, action_weight=0.0)
    torch.testing.assert_close(choice, expected - 0.125)
    torch.testing.assert_close(
        dagger.imitation_loss(act, target, movable, w, labels, 2.0, action_weight=3.0),
        3.0 * no_choice + choice)


def test_detour_labels_name_the_model() -> None:
    """True in a row means the squares model (rows written before discs became its
    default); a named model is named."""
    assert [local.detour_label(d) for d in (False, None, True, "squares", "discs")] == [
        "", "", " + detour", " + squares detour", " + discs detour"]
