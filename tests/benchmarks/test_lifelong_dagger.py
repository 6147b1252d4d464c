"""``benchmarks/lifelong_dagger.py``: Hungarian's plan taught to a lifelong entity policy."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from benchmark_scripts import ROOT, load

import allocator
import sim
from sim.orders import CARRYING, OPEN, TO_PICKUP

dagger = load("lifelong_dagger")
SHIPPED = ROOT / "allocator/weights/lifelong/maddpg-greedy.safetensors"


def _student():
    from learners.algorithms import make_learner
    from learners.checkpoint import load_checkpoint

    tensors, meta = load_checkpoint(SHIPPED, kind="policy")
    learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"],
                           meta["num_agents"], meta["config"])
    learner.load_policy_tensors(tensors)
    return learner


def test_the_teacher_plans_without_assigning_and_aims_at_open_pickups() -> None:
    env = sim.make_env("warehouse-20", num_envs=2, seed=1)
    teacher = dagger.PlanTeacher()
    teacher.reset(env)
    gen = torch.Generator().manual_seed(0)
    for _ in range(40):
        action, rel, kind = teacher.teach(env)
        assert action.shape == (2, 20, 2) and action.abs().max() <= 1.0 + 1e-6
        status = env.agent_status.numpy()
        assert not (status == TO_PICKUP).any()  # nothing is ever assigned
        assert ((kind == 0) == (status == CARRYING)).all()
        planned = kind == 1
        st = env.orders.status.numpy()
        for b in range(2):
            slots = teacher.plan[b][planned[b]]
            assert (st[b][slots] == OPEN).all()
            assert len(set(slots.tolist())) == len(slots)  # one AGV per order
        goal = env.agent_pos.double().numpy() + rel
        pick = env.orders.pickup.double().numpy()
        for b, i in zip(*np.nonzero(planned), strict=True):
            assert np.allclose(goal[b, i], pick[b, teacher.plan[b, i]])
        assert np.isnan(rel[kind < 0]).all()
        env.step(action + 0.1 * torch.randn(action.shape, generator=gen))
    assert teacher.replans > 2


def test_the_teacher_alone_delivers_behind_the_shield() -> None:
    from allocator.shield import SafetyShield

    ctl = SafetyShield(dagger.TeacherDriver(), keep_right=0.5)
    m = sim.evaluate_lifelong(ctl, "warehouse-20", steps=150, seed=3)
    assert m.delivered > 0 and m.collisions_per_1000 == 0
    again = sim.evaluate_lifelong(SafetyShield(dagger.TeacherDriver(), keep_right=0.5),
                                  "warehouse-20", steps=150, seed=3)
    assert again.delivered == m.delivered  # the same seed, the same run


def test_candidate_labels_point_at_the_planned_pickup_slot() -> None:
    env = sim.make_env("warehouse-20", num_envs=2, seed=2)
    teacher = dagger.PlanTeacher()
    teacher.reset(env)
    _, rel, kind = teacher.teach(env)
    obs = env.observe()
    layout = env.obs_layout
    labels = dagger.candidate_labels(obs, layout, rel, kind)
    assert labels.shape == (2, 20) and (labels[torch.as_tensor(kind < 0)] == -1).all()
    t = obs[..., layout.pickups].reshape(2, 20, layout.k_pickups, 3)
    hit = labels >= 1
    assert hit.any()
    for b, i in zip(*torch.nonzero(hit, as_tuple=True), strict=True):
        assert np.allclose(t[b, i, labels[b, i] - 1, :2].numpy(), rel[b, i], atol=1e-3)
    # a planned pickup out of view has no label
    far = rel.copy()
    far[kind == 1] += 100.0
    assert not (dagger.candidate_labels(obs, layout, far, kind) >= 1).any()


def test_policy_and_choice_gives_the_waypoint_heads_candidates() -> None:
    learner = _student()
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    learner.reset(env)
    obs = env.observe()
    act, w = learner.policy_and_choice(obs)
    torch.testing.assert_close(act.detach(), learner.policy(obs))
    assert w.shape == (1, 20, 1 + env.obs_layout.k_pickups)
    torch.testing.assert_close(w.sum(-1), torch.ones(1, 20))  # pickups in view at the start


def test_main_writes_a_policy_the_allocator_serves(tmp_path: Path) -> None:
    dagger.main(["--start", str(SHIPPED), "--floor", "warehouse-20", "--iterations", "1",
                 "--envs", "1", "--horizon", "6", "--steps", "2", "--validation-steps", "5",
                 "--action-weight", "0", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["floor"] == "warehouse-20" and "throughput" in probe["final"]
    assert probe["action_weight"] == 0.0 and probe["validation_steps"] == 5
    assert probe["teacher_throughput"] >= 0.0
    assert (tmp_path / "progress.csv").read_text().startswith(
        "iteration,loss,accuracy,labelled")
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20",
                            weights=tmp_path / "dagger.safetensors", shield=True)
    m = sim.evaluate_lifelong(solver, "warehouse-20", steps=20, seed=0)
    assert m.collisions_per_1000 == 0


def test_hidden_starts_a_fresh_student_of_that_width(tmp_path: Path) -> None:
    """``--hidden 8``: the student is built afresh at width 8 with the start file's other
    settings (not its weights), and the allocator serves what it writes."""
    from learners.checkpoint import load_checkpoint

    dagger.main(["--start", str(SHIPPED), "--floor", "warehouse-20", "--iterations", "1",
                 "--envs", "1", "--horizon", "6", "--steps", "2", "--validation-steps", "5",
                 "--action-weight", "0", "--hidden", "8", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["hidden"] == 8 and probe["fresh"] is True
    tensors, meta = load_checkpoint(tmp_path / "dagger.safetensors", kind="policy")
    start, start_meta = load_checkpoint(SHIPPED, kind="policy")
    assert meta["config"]["hidden"] == 8 != start_meta["config"]["hidden"]
    assert tensors["actor.steer.score.0.weight"].shape[0] == 8
    assert start["actor.steer.score.0.weight"].shape[0] != 8
    for key, value in start_meta["config"].items():  # the start's other settings
        if key not in ("hidden", "shield_keep_right"):
            assert meta["config"][key] == value, key
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20",
                            weights=tmp_path / "dagger.safetensors", shield=True)
    m = sim.evaluate_lifelong(solver, "warehouse-20", steps=10, seed=0)
    assert m.collisions_per_1000 == 0


@pytest.mark.parametrize("bad", [
    ["--start", str(ROOT / "allocator/weights/6v6/bicnet-ipf.safetensors")],
    ["--start", str(SHIPPED), "--floor", "6v6"],
    ["--start", str(SHIPPED), "--keep-right", "2"],
    ["--start", str(SHIPPED), "--choice-weight", "nan"],
    ["--start", str(SHIPPED), "--action-weight", "-1"],
    ["--start", str(SHIPPED), "--action-weight", "nan"],
    ["--start", str(SHIPPED), "--action-weight", ""],
    ["--start", str(SHIPPED), "--action-weight", "1e400"],
    ["--start", str(SHIPPED), "--horizon", "0"],
    ["--start", "missing.safetensors"],
    ["--start", str(SHIPPED), "--view", "0"],
    ["--start", str(SHIPPED), "--view", "-4"],
    ["--start", str(SHIPPED), "--view", "four"],
    ["--start", str(SHIPPED), "--view", str(10**9)],  # more slots than AGVs: no huge obs
    ["--start", str(SHIPPED), "--teacher", "oracle"],
    ["--start", str(SHIPPED), "--validation-seeds", "-1"],
    ["--start", str(SHIPPED), "--validation-seeds"],
    ["--start", str(SHIPPED), "--validation-runs", "0"],
    ["--start", str(SHIPPED), "--waypoint-drive"],  # its action cannot be taught
    ["--start", str(SHIPPED), "--waypoint-drive", "--action-weight", "0.5"],
    ["--start", str(SHIPPED), "--drive-sight", "--action-weight", "0"],  # no waypoint drive
    ["--start", str(SHIPPED), "--floor", "warehouse-20", "warehouse-20"],
    ["--start", str(SHIPPED), "--floor", "warehouse-20", "6v6"],
    ["--start", str(SHIPPED), "--floor", "warehouse-50", "warehouse-20", "--view", "30"],
    ["--start", str(SHIPPED), "--hidden", "0"],
    ["--start", str(SHIPPED), "--hidden", "-8"],
    ["--start", str(SHIPPED), "--hidden", "2.5"],
    ["--start", str(SHIPPED), "--hidden", "nan"],
    ["--start", str(SHIPPED), "--hidden", ""],
    ["--start", str(SHIPPED), "--hidden", str(10**9)],  # no network that fills memory
])
def test_bad_input_is_refused(bad: list[str], tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        dagger.main([*bad, "--out", str(tmp_path)])


def _taught_floors(teachers: list, steps: int = 30):
    """Two warehouse-20 floors driven by the first teacher for ``steps`` steps; after every
    teacher has taught each step, yields (floor, idle AGVs, open orders, positions, pickups)
    for each floor with an open order."""
    from sim.orders import IDLE

    env = sim.make_env("warehouse-20", num_envs=2, seed=3)
    for teacher in teachers:
        teacher.reset(env)
    for _ in range(steps):
        action = teachers[0].teach(env)[0]
        for teacher in teachers[1:]:
            teacher.teach(env)
        status, st = env.agent_status.numpy(), env.orders.status.numpy()
        pos, pickup = env.agent_pos.double().numpy(), env.orders.pickup.double().numpy()
        for b in range(2):
            open_ = np.flatnonzero(st[b] == OPEN)
            if len(open_):
                yield b, np.flatnonzero(status[b] == IDLE), open_, pos, pickup
        assert action.abs().max() <= 1.0 + 1e-6
        env.step(action)


def test_the_local_teacher_gives_each_idle_agv_an_open_order_from_its_view() -> None:
    """``LocalTeacher``: every idle AGV gets an open order among its ``view`` nearest; with a
    view wide enough to see each other, no pickup point is aimed at by more idle AGVs than it
    has open orders; a view of 1 is each AGV's nearest open pickup."""
    wide, narrow = dagger.LocalTeacher(view=40), dagger.LocalTeacher(view=1)
    for b, idle, open_, pos, pickup in _taught_floors([wide, narrow]):
        assert (wide.plan[b, idle] >= 0).all() and np.isin(wide.plan[b, idle], open_).all()
        if len(open_) >= len(idle):  # no pickup point is aimed at by more idle AGVs
            # than it has open orders (orders that share a point are ties, broken
            # differently by each AGV's own assignment: harmless, there is one for each)
            aimed = [tuple(pickup[b, j].round(6)) for j in wide.plan[b, idle]]
            held = [tuple(pickup[b, j].round(6)) for j in open_]
            assert all(aimed.count(x) <= held.count(x) for x in set(aimed))
        for i in idle:  # view 1: the nearest open pickup
            d = np.linalg.norm(pickup[b, open_] - pos[b, i], axis=-1)
            assert narrow.plan[b, i] == open_[np.argmin(d)]
    with pytest.raises(ValueError, match="view must be an integer >= 1"):
        dagger.LocalTeacher(view=0)
    for bad in (2.5, float("nan"), "16", None, True, -3):
        with pytest.raises(ValueError, match="view must be an integer >= 1"):
            dagger.LocalTeacher(view=bad)
    assert dagger.LocalTeacher(view=10**9).view == 10**9  # wider than any floor: all in view


def test_the_path_priced_local_teacher_prices_by_the_floors_distances() -> None:
    """``LocalTeacher(path=True)``: each idle AGV's share of the least-cost assignment among
    its view (the straight-line nearest pickups and idle AGVs), the costs the floor's travel
    distances round the shelves; on the same states it sometimes chooses otherwise than the
    straight-line teacher."""
    from scipy.optimize import linear_sum_assignment

    teacher, straight = dagger.LocalTeacher(view=4, path=True), dagger.LocalTeacher(view=4)
    checked = differs = 0
    for b, idle, open_, pos, pickup in _taught_floors([teacher, straight]):
        cost = teacher.distances.distance(pos[b, idle], pickup[b, open_])
        for k, i in enumerate(idle):
            near = np.argsort(np.linalg.norm(pickup[b, open_] - pos[b, i], axis=-1),
                              kind="stable")[:4]
            gap = np.linalg.norm(pos[b, idle] - pos[b, i], axis=-1)
            gap[k] = np.inf
            rivals = np.argsort(gap, kind="stable")[:min(4, len(idle) - 1)]
            rows, cols = linear_sum_assignment(cost[np.concatenate([[k], rivals])][:, near])
            mine = cols[rows == 0]
            want = near[mine[0]] if len(mine) else near[np.argmin(cost[k, near])]
            assert teacher.plan[b, i] == open_[want]
            checked += 1
            differs += int(teacher.plan[b, i] != straight.plan[b, i])
    assert checked > 50 and differs > 0
    for bad in (1, None, "yes"):
        with pytest.raises(ValueError, match="path must be a bool"):
            dagger.LocalTeacher(view=4, path=bad)


def test_main_teaches_the_local_teachers_choice_to_a_waypoint_drive_student(
        tmp_path: Path) -> None:
    """``--teacher local --view K --waypoint-drive``: the student sees K slots, is taught the
    LocalTeacher's choice alone, and its file drives as WaypointDriver through the allocator
    (the best validation kept as ``best.safetensors``)."""
    from learners.checkpoint import read_metadata

    dagger.main(["--start", str(SHIPPED), "--floor", "warehouse-20", "--iterations", "2",
                 "--envs", "1", "--horizon", "6", "--steps", "3", "--validation-steps", "20",
                 "--validation-seeds", "5", "6", "--validation-runs", "1",
                 "--teacher", "local", "--view", "8", "--waypoint-drive",
                 "--action-weight", "0", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert (probe["teacher"], probe["teacher_view"], probe["view"]) == ("local", 8, 8)
    assert probe["waypoint_drive"] is True and probe["validation_seeds"] == [5, 6]
    assert probe["best"]["iteration"] == 2 and 0.0 <= probe["final"]["accuracy"] <= 1.0
    for name in ("dagger.safetensors", "best.safetensors"):
        meta = read_metadata(tmp_path / name)
        assert meta["config"]["waypoint_drive"] is True
        assert meta["config"]["shield_keep_right"] == 0.5  # the lanes it was taught behind
    _served_without_overlaps(tmp_path / "best.safetensors")


def _served_without_overlaps(path: Path) -> None:
    """The policy file runs through the allocator behind the shield on warehouse-20 (an
    8-slot view) for 20 steps without an overlap."""
    scen = sim.get_scenario("warehouse-20", k_pickups=8, k_agents=8)
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20", weights=path,
                            shield=True)
    assert sim.evaluate_lifelong(solver, scen, steps=20, seed=0).collisions_per_1000 == 0


def test_main_teaches_an_idle_token_student_from_a_start_without_it(tmp_path: Path) -> None:
    """``--idle-token --drive-sight``: the start (without the bit) is widened, the file
    records both, and the allocator serves it behind the shield."""
    from learners.checkpoint import load_checkpoint

    dagger.main(["--start", str(SHIPPED), "--floor", "warehouse-20", "--iterations", "1",
                 "--envs", "1", "--horizon", "6", "--steps", "3", "--validation-steps", "20",
                 "--validation-seeds", "5", "--validation-runs", "1", "--teacher", "local",
                 "--view", "8", "--waypoint-drive", "--action-weight", "0", "--idle-token",
                 "--drive-sight", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert probe["idle_token"] is True and probe["drive_sight"] is True
    tensors, meta = load_checkpoint(tmp_path / "best.safetensors", kind="policy")
    assert meta["config"]["idle_token"] is True and meta["config"]["drive_sight"] is True
    assert tensors["actor.encoder.agent.0.weight"].shape[-1] == 6
    _served_without_overlaps(tmp_path / "best.safetensors")


def test_main_teaches_on_several_floors(tmp_path: Path) -> None:
    """``--floor A B``: rollouts on both floors, a validation column per floor and the mean
    share of the teacher's throughput, which selects the best."""
    import csv

    dagger.main(["--start", str(SHIPPED), "--floor", "warehouse-20", "warehouse-50",
                 "--iterations", "2", "--envs", "1", "--horizon", "6", "--steps", "4",
                 "--validation-steps", "40", "--validation-seeds", "5", "--validation-runs",
                 "1", "--teacher", "local", "--view", "8", "--waypoint-drive",
                 "--action-weight", "0", "--out", str(tmp_path)])
    probe = json.loads((tmp_path / "dagger.probe.json").read_text())
    assert list(probe["teacher_by_floor"]) == ["warehouse-20", "warehouse-50"]
    assert probe["teacher_throughput"] == probe["teacher_by_floor"]["warehouse-20"]
    rows = list(csv.DictReader(open(tmp_path / "progress.csv")))
    last = rows[-1]
    assert {"throughput", "throughput_warehouse-50", "share"} <= set(last)
    teacher = probe["teacher_by_floor"]
    want = np.mean([float(last["throughput"]) / max(teacher["warehouse-20"], 1e-9),
                    float(last["throughput_warehouse-50"]) / max(teacher["warehouse-50"],
                                                                 1e-9)])
    assert abs(float(last["share"]) - want) < 1e-3
    assert probe["best"]["share"] == max(float(r["share"]) for r in rows if r["share"])
    solver = allocator.make("maddpg-greedy", scenario="warehouse-50",
                            weights=tmp_path / "best.safetensors", shield=True)
    scen = sim.get_scenario("warehouse-50", k_pickups=8, k_agents=8)
    assert sim.evaluate_lifelong(solver, scen, steps=10, seed=0).collisions_per_1000 == 0


def test_validate_averages_the_seeds() -> None:
    from allocator.shield import SafetyShield

    one = [dagger.validate(dagger.TeacherDriver(8), "warehouse-20", 0.5, 60, seeds=(s,),
                           runs=1) for s in (1, 2)]
    both = dagger.validate(dagger.TeacherDriver(8), "warehouse-20", 0.5, 60, seeds=(1, 2),
                           runs=1)
    assert both == pytest.approx(np.mean(one))
    m = sim.evaluate_lifelong(SafetyShield(dagger.TeacherDriver(8), keep_right=0.5),
                              "warehouse-20", steps=60, seed=1, runs=1)
    assert one[0] == m.throughput
