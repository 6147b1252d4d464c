"""Our MADDPG beside BenchMARL's (on TorchRL), on our PettingZoo environment, in one run.

Both learners train on ``3v3`` with the IPF reward; both are scored at checkpoints by
``sim.evaluate`` on the same validation scenes (eval seed 12345, 300 episodes; not the test
seeds), and the report gives the wall-clock seconds (scoring excluded) and the env steps
(joint steps of one environment) at which each first reaches 80% and 90% task response.

* ours: :func:`learners.train.train`, the ``default`` preset (the shipped weights' settings);
* BenchMARL 1.5.2's ``MaddpgConfig`` with its own experiment defaults except the budget,
  the evaluation (ours replaces its own) and the loggers (none), on
  ``torchrl.envs.PettingZooWrapper`` around :func:`sim.pettingzoo_env`, a custom
  ``TaskClass``.

Needs the optional extra ``[bench]`` (``benchmarl``, ``torchrl``, ``tensordict``) in an
environment with a CPU torch, e.g.::

    python3 -m venv /work/venv-bench
    /work/venv-bench/bin/pip install -c constraints.txt -e . benchmarl==1.5.2 torchrl==0.11.1

Pitfall: TorchRL's collector sets torch's thread count (from 1 to 2) when it shuts its
environments down, which in BenchMARL happens before the last batch's scoring; the thread
count is put back to ``--threads`` at every callback and checked at the end.

Run: ``python benchmarks/benchmarl_peer.py [--seeds 0 1] [--frames 120000]``; writes
``benchmarks/results/benchmarl/benchmarl_peer.md`` and one JSON record per run.
"""

from __future__ import annotations

import argparse
import copy
import csv
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

import sim
from sim.io import atomic_write_text
from sim.parallel_env import AGVParallelEnv

RESULTS = Path(__file__).resolve().parent / "results" / "benchmarl"
SCENARIO, REWARD, EVAL_SEED, EVAL_EPISODES = "3v3", "ipf", 12345, 300
THRESHOLDS = (0.8, 0.9)


def first_reaching(curve: list[dict], level: float) -> dict | None:
    """The first checkpoint of ``curve`` (dicts with ``response``) at or above ``level``."""
    for point in curve:
        if point["response"] >= level:
            return point
    return None


# ---------------------------------------------------------------------------- ours
def run_ours(seed: int, episodes: int, eval_every: int, threads: int) -> dict:
    """Our trainer, default preset; the curve from its progress.csv evaluations."""
    from learners.train import TrainConfig, train

    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(algo="maddpg", reward=REWARD, scenario=SCENARIO, episodes=episodes,
                          seed=seed, run_dir=tmp, eval_every=eval_every,
                          eval_episodes=EVAL_EPISODES, eval_seed=EVAL_SEED,
                          checkpoint_every=10**9, progress=False, tensorboard=False,
                          threads=threads)
        cpu = time.process_time()
        r = train(cfg)
        cpu = time.process_time() - cpu
        with open(Path(tmp) / "progress.csv", newline="") as f:
            curve = [{"env_steps": int(row["env_steps"]), "seconds": float(row["seconds"]),
                      "response": float(row["eval_response_rate"])}
                     for row in csv.DictReader(f) if row.get("eval_response_rate")]
    return {"system": "ours (learners.train, default preset)", "seed": seed,
            "env_steps": r.env_steps, "seconds": r.seconds, "cpu": cpu, "curve": curve,
            "threads_at_end": torch.get_num_threads()}


# ---------------------------------------------------------------------------- BenchMARL
try:  # the optional extra [bench]
    from benchmarl.environments.common import TaskClass
    from benchmarl.experiment.callback import Callback
    from torchrl.envs import PettingZooWrapper
except ImportError as err:  # pragma: no cover - depends on the environment
    raise SystemExit(f"benchmarks/benchmarl_peer.py needs the [bench] extra (benchmarl, torchrl):"
                     f" {err}") from err


def _flat_info(infos: dict) -> dict:
    """Per-agent infos with the nested ``terms`` dict flattened to ``term_<name>`` floats
    (TorchRL 0.11's PettingZoo wrapper makes its info spec with ``torch.as_tensor`` on every
    value, which a dict is not)."""
    out = {}
    for agent, info in infos.items():
        flat = {k: v for k, v in info.items() if k != "terms"}
        flat.update({f"term_{k}": float(v) for k, v in info.get("terms", {}).items()})
        out[agent] = flat
    return out


class FlatInfoAGVEnv(AGVParallelEnv):
    """:func:`sim.pettingzoo_env`'s environment with flat per-agent infos."""

    def reset(self, seed=None, options=None):
        obs, infos = super().reset(seed=seed, options=options)
        return obs, _flat_info(infos)

    def step(self, actions):
        obs, rewards, terminated, truncated, infos = super().step(actions)
        return obs, rewards, terminated, truncated, _flat_info(infos)


class AGVTask(TaskClass):
    """3v3 IPF AGV task allocation through TorchRL's ``PettingZooWrapper`` (module level:
    BenchMARL pickles its task)."""

    def get_env_fun(self, num_envs, continuous_actions, seed, device):
        def make():
            return PettingZooWrapper(FlatInfoAGVEnv(SCENARIO, reward=REWARD, seed=seed),
                                     return_state=False,
                                     categorical_actions=False, device=device,
                                     use_mask=False, done_on_any=False)
        return make

    def supports_continuous_actions(self):
        return True

    def supports_discrete_actions(self):
        return False

    def has_render(self, env):
        return False

    def max_steps(self, env):
        return sim.get_scenario(SCENARIO).max_steps

    def group_map(self, env):
        return env.group_map

    def observation_spec(self, env):
        spec = env.observation_spec.clone()
        for group in self.group_map(env):
            for key in list(spec[group].keys()):
                if key != "observation":
                    del spec[group][key]
        return spec

    def info_spec(self, env):
        return None

    def state_spec(self, env):
        return None

    def action_spec(self, env):
        return env.full_action_spec

    def action_mask_spec(self, env):
        return None

    @staticmethod
    def env_name():
        return "agv"


def _agv_task(seed: int) -> AGVTask:
    return AGVTask(name="AGV_3V3_IPF", config={"seed": seed})


class _Scorer(Callback):
    """BenchMARL callback: scores the deterministic policy with ``sim.evaluate`` every
    ``every`` collected frames, and keeps the wall-clock without the scoring (module level:
    BenchMARL pickles its callbacks)."""

    def __init__(self, every: int, threads: int) -> None:
        super().__init__()
        self.every, self.threads = every, threads
        self.curve: list[dict] = []
        self.scoring = 0.0
        self.start = time.perf_counter()
        self.next_at = every
        self.thread_resets = 0

    def on_train_end(self, training_td, group):
        self.after_train(self.experiment)

    def controller(self, experiment):
        from tensordict import TensorDict
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        policy = experiment.policy
        group = next(iter(experiment.group_map))

        @torch.no_grad()
        def act(obs: torch.Tensor) -> torch.Tensor:
            td = TensorDict({group: TensorDict({"observation": obs}, batch_size=obs.shape[:2])},
                            batch_size=obs.shape[:1])
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                out = policy(td)
            return out[group, "action"]
        return act

    def after_train(self, experiment) -> None:
        if torch.get_num_threads() != self.threads:
            self.thread_resets += 1
            torch.set_num_threads(self.threads)
        frames = experiment.total_frames
        if frames < self.next_at:
            return
        while self.next_at <= frames:
            self.next_at += self.every
        t = time.perf_counter()
        m = sim.evaluate(self.controller(experiment), SCENARIO, episodes=EVAL_EPISODES,
                         seed=EVAL_SEED)
        done = time.perf_counter()
        self.curve.append({"env_steps": int(frames),
                           "seconds": t - self.start - self.scoring,
                           "response": float(m.response_rate)})
        self.scoring += done - t
        print(f"  benchmarl frames {frames}: response {m.response_rate:.3f} "
              f"({self.curve[-1]['seconds']:.0f} s)", flush=True)


def run_benchmarl(seed: int, frames: int, every: int, threads: int,
                  ours_hparams: bool = False) -> dict:
    """BenchMARL's MADDPG on our environment; ``ours_hparams``: our settings where
    BenchMARL has a matching one (lr, gamma, tau, batch, updates per frame, grad clip)."""
    from benchmarl.algorithms import MaddpgConfig
    from benchmarl.experiment import Experiment, ExperimentConfig
    from benchmarl.models.mlp import MlpConfig

    exp = ExperimentConfig.get_from_yaml()
    exp.loggers, exp.create_json, exp.render, exp.evaluation = [], False, False, False
    exp.checkpoint_interval, exp.checkpoint_at_end = 0, False
    exp.sampling_device = exp.train_device = exp.buffer_device = "cpu"
    exp.max_n_frames = frames
    if every < exp.off_policy_collected_frames_per_batch:  # score more often, same ratio
        exp.off_policy_n_optimizer_steps = max(1, exp.off_policy_n_optimizer_steps * every
                                               // exp.off_policy_collected_frames_per_batch)
        exp.off_policy_collected_frames_per_batch = every
    label = "BenchMARL 1.5.2 MADDPG, its defaults"
    if ours_hparams:
        from learners.maddpg import MADDPGConfig

        ours = MADDPGConfig()
        exp.lr, exp.gamma, exp.polyak_tau = ours.actor_lr, ours.gamma, ours.tau
        exp.off_policy_train_batch_size = ours.batch_size
        exp.off_policy_n_envs_per_worker = ours.num_envs
        batch = exp.off_policy_collected_frames_per_batch
        # our ratio: updates_per_step updates per num_envs transitions
        exp.off_policy_n_optimizer_steps = max(1, batch * ours.updates_per_step // ours.num_envs)
        exp.clip_grad_val, exp.off_policy_init_random_frames = ours.grad_clip, 0
        exp.off_policy_memory_size = ours.buffer_size
        label = "BenchMARL 1.5.2 MADDPG, our hyperparameters where it has them"
    scorer = _Scorer(every, threads)
    with tempfile.TemporaryDirectory() as tmp:
        exp.save_folder = tmp
        experiment = Experiment(task=_agv_task(seed), algorithm_config=MaddpgConfig.get_from_yaml(),
                                model_config=MlpConfig.get_from_yaml(),
                                critic_model_config=MlpConfig.get_from_yaml(), seed=seed,
                                config=exp, callbacks=[scorer])
        torch.set_num_threads(threads)
        cpu = time.process_time()
        scorer.start = time.perf_counter()
        experiment.run()
        seconds = time.perf_counter() - scorer.start - scorer.scoring
        cpu = time.process_time() - cpu
    threads_at_end = torch.get_num_threads()
    torch.set_num_threads(threads)
    return {"system": label, "seed": seed, "env_steps": int(experiment.total_frames),
            "seconds": seconds, "cpu": cpu, "curve": scorer.curve,
            "thread_resets": scorer.thread_resets, "threads_at_end": threads_at_end,
            "config": {k: getattr(exp, k) for k in (
                "lr", "gamma", "polyak_tau", "off_policy_train_batch_size",
                "off_policy_n_envs_per_worker", "off_policy_n_optimizer_steps",
                "off_policy_collected_frames_per_batch", "clip_grad_val")}}


# ---------------------------------------------------------------------------- report
def report(records: list[dict], command: str) -> str:
    """The markdown report of a list of run records."""
    import benchmarl
    import torchrl

    lines = ["# Our MADDPG beside BenchMARL's, 3v3 IPF", "", f"`{command}`; torch "
             f"{torch.__version__}, BenchMARL {benchmarl.__version__}, TorchRL "
             f"{torchrl.__version__}, one torch thread, {platform.machine()}, a shared 2-core "
             f"machine (load average {os.getloadavg()[0]:.1f} at the end).", "",
             "Scored by `sim.evaluate` on the validation scenes (eval seed 12345, 300 "
             "episodes) at checkpoints; seconds: wall-clock of the training, scoring "
             "excluded; CPU s: the process's CPU time of the run, scoring included; env "
             "steps: joint steps of one environment.", "",
             "| system | seed | env steps to 80% | s to 80% | env steps to 90% | s to 90% | "
             "best response (at env steps) | env steps trained | env steps/s | "
             "env steps/CPU s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        cells = []
        for level in THRESHOLDS:
            p = first_reaching(r["curve"], level)
            cells += ["-", "-"] if p is None else [str(p["env_steps"]), f"{p['seconds']:.0f}"]
        best = max(r["curve"], key=lambda p: p["response"]) if r["curve"] else None
        best_s = "-" if best is None else f"{best['response']:.3f} ({best['env_steps']})"
        lines.append(f"| {r['system']} | {r['seed']} | {' | '.join(cells)} | {best_s} | "
                     f"{r['env_steps']} | {r['env_steps'] / r['seconds']:.0f} | "
                     f"{r['env_steps'] / r['cpu']:.0f} |")
    lines += ["", "`-`: not reached within the run. Curves (env steps: response):", ""]
    for r in records:
        pts = ", ".join(f"{p['env_steps']}: {p['response']:.3f}" for p in r["curve"])
        extra = ""
        if "thread_resets" in r:
            extra = (f" (torch threads found changed {r['thread_resets']} time(s) during "
                     f"the run, put back; {r['threads_at_end']} at its end)")
        lines.append(f"- {r['system']}, seed {r['seed']}{extra}: {pts}")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--frames", type=int, default=120_000,
                        help="BenchMARL's budget in env steps")
    parser.add_argument("--episodes", type=int, default=3000, help="our budget in episodes")
    parser.add_argument("--every", type=int, default=6000,
                        help="BenchMARL: env steps between scorings")
    parser.add_argument("--ours-every", type=int, default=200,
                        help="ours: episodes between scorings")
    parser.add_argument("--systems", nargs="+", default=["ours", "benchmarl"],
                        choices=["ours", "benchmarl", "benchmarl-ours-hparams"])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/benchmarl_peer.py " + " ".join(
        f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
        for k, v in vars(args).items() if k != "out")
    records = []
    for seed in args.seeds:
        for system in args.systems:
            print(f"{system} seed {seed}", flush=True)
            if system == "ours":
                rec = run_ours(seed, args.episodes, args.ours_every, args.threads)
            else:
                rec = run_benchmarl(seed, args.frames, args.every, args.threads,
                                    ours_hparams=system == "benchmarl-ours-hparams")
            records.append(copy.deepcopy(rec))
            atomic_write_text(out / f"{system}-s{seed}.json", json.dumps(rec, indent=1))
            print({k: v for k, v in rec.items() if k != "curve"}, flush=True)
            atomic_write_text(out / "benchmarl_peer.md", report(records, command))
    print(f"wrote {out / 'benchmarl_peer.md'}")


if __name__ == "__main__":
    main()
