"""The training loop: collect, store, sample, update, soft-update; evaluate; log; checkpoint.

:func:`train` runs one learner on B parallel environments. Every iteration it

1. **collects** one vectorized step with the exploring policy (Gaussian noise, decaying
   linearly with the number of finished episodes),
2. **stores** the B joint transitions in the replay buffer, then resets the environments that
   finished (their final transition is stored first: the simulator freezes finished
   environments until they are reset),
3. **samples** ``updates_per_step`` batches and **updates** the critics and actors, each update
   ending with the **soft update** of the target networks.

Episodes end when every task is claimed (a true terminal: no bootstrap) or at the step limit (a
time-limit truncation: the observations hold no clock, so the state is not terminal and the
target bootstraps from the next state).

**Lifelong floors** (``warehouse-N``, entity learners only): a training "episode" is a
fixed-length window of ``TrainConfig.window`` steps of a lifelong run in each of the B
environments; the run goes on across windows (no transition is terminal: every target
bootstraps), and the floor restarts from the depot with a new order stream at the scenario's
``max_steps``. The running score is the windows' throughput (deliveries per 1000 steps); an
evaluation is ``TrainConfig.eval_runs`` (default 1) ``sim.evaluate_lifelong`` runs of
``TrainConfig.eval_steps`` steps on ``eval_seed`` (their throughput averaged), and
``best.safetensors`` keeps the policy of the highest evaluated throughput.

At episode milestones it writes a CSV row (``progress.csv``: the curves of the paper's Fig. 9;
mirrored to TensorBoard when it is installed),
evaluates the greedy policy with the paper's metrics (``sim.evaluate``), and writes checkpoints:
``checkpoint.safetensors`` (everything needed to resume bit-for-bit: networks, optimizers,
replay buffer, environments mid-episode, random generators, counters) and
``policy.safetensors`` / ``best.safetensors`` (the actor alone, latest and best evaluated:
highest task response, then least time) and, on episodic scenes, ``fastest.safetensors`` (the
least evaluated time at ``TrainConfig.fastest_min_response`` or more).
A run killed at any point resumes from its last checkpoint with ``resume=True`` and then
computes exactly what the uninterrupted run would have; SIGINT / SIGTERM stop at the end of the
current iteration and write a checkpoint first.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import json
import math
import os
import signal
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

import sim
from learners.algorithms import (
    ALGORITHMS,
    ENTITY_ALGORITHMS,
    REWARD_NAMES,
    check_algo,
    make_config,
)
from learners.buffer import Batch, ReplayBuffer
from learners.checkpoint import (
    code_version,
    load_checkpoint,
    read_metadata,
    resolve_checkpoint_path,
    save_checkpoint,
    write_sidecar,
)
from learners.common import ActorCritic, check_bool, check_int, check_real
from learners.policy import build_learner, is_lifelong
from sim.io import atomic_write_bytes, atomic_write_text, clean_stale_temporaries

__all__ = ["TrainConfig", "TrainResult", "train", "default_run_dir", "portable_copy",
           "CSV_COLUMNS", "LIFELONG_CSV_COLUMNS"]

CSV_COLUMNS = [
    "episode", "env_steps", "updates", "seconds", "noise_std",
    "train_response_rate", "train_return", "critic_loss", "actor_loss", "q",
    "eval_response_rate", "eval_avg_reward", "eval_avg_time", "eval_collisions",
    "eval_finished_rate",
]
"""Columns of ``progress.csv``; per-term reward columns ``train_term_<name>`` follow."""
LIFELONG_CSV_COLUMNS = [
    "episode", "env_steps", "updates", "seconds", "noise_std",
    "train_throughput", "train_return", "critic_loss", "actor_loss", "q",
    "eval_throughput", "eval_throughput_bound", "eval_wait_mean", "eval_collisions_per_1000",
    "eval_utilization",
]
"""Columns of a lifelong run's ``progress.csv`` (throughput in deliveries per 1000 steps)."""

FASTEST = "fastest.safetensors"
"""The policy of the least validation time at ``TrainConfig.fastest_min_response`` or more."""

_ENV_FIELDS = ("agent_pos", "agent_vel", "task_pos", "task_claimed", "agent_task", "steps", "done")
_RECENT = 100  # finished training episodes in the running response rate


@dataclass
class TrainConfig:
    """What to train and how to run it; the learner's hyperparameters are in its own config
    (:class:`~learners.maddpg.MADDPGConfig`, :class:`~learners.bicnet.BiCNetConfig`)."""

    algo: str = "maddpg"
    """Learning algorithm: ``maddpg`` or ``bicnet``."""
    reward: str = "ipf"
    """Reward: ``minidist``, ``greedy`` or ``ipf``."""
    scenario: str = "3v3"
    """Scenario name for ``sim.make_env`` (``3v3``, ``6v6``, ``1v1``, ...)."""
    episodes: int = 5000
    """Training episodes (summed over the parallel environments) after which training stops."""
    seed: int = 0
    """Seed of the networks' initialization, the environments, the noise and the sampling."""
    run_dir: str | None = None
    """Folder for the log and checkpoints; default ``runs/<algo>-<reward>-<scenario>-s<seed>``."""
    eval_every: int = 500
    """Evaluate the deterministic policy every this many episodes (0: only at the end)."""
    eval_episodes: int = 300
    """Test episodes per evaluation (the paper: 300)."""
    eval_seed: int = 12345
    """Seed of the evaluation scenes (the same scenes at every evaluation)."""
    log_every: int = 100
    """Write a CSV row every this many episodes."""
    checkpoint_every: int = 1000
    """Write a resumable checkpoint every this many episodes (and always at the end)."""
    stop_response: float | None = None
    """Stop early once an evaluation reaches this task response rate (None: never)."""
    critic_warmup: int = 0
    """Gradient updates at the start of the run during which only the critic(s) learn: the
    actors' learning rate is zero (their Adam moments go on gathering, so that the first real
    steps are not full-size).
    Meant for a run started from a deployed policy (``init_from`` a ``kind="policy"`` file,
    which carries no critic): the new critic first learns the values of that policy, so that
    the policy is not pulled around by an untrained critic."""
    fastest_min_response: float = 0.97
    """Episodic only: ``fastest.safetensors`` keeps the policy of the least validation time
    among the evaluations whose task response is at least this (issue 16's time target is
    read at 97% response; ``best.safetensors`` keeps the highest response)."""
    threads: int = 1
    """torch intra-op threads (1 is fastest and steadiest on a shared 2-core machine)."""
    progress: bool = True
    """Show a tqdm progress bar with the running task response rate."""
    tensorboard: bool = True
    """Also write the CSV's curves as TensorBoard scalars (``RUN_DIR/tb``) when the
    ``tensorboard`` package is installed (silently skipped otherwise)."""
    window: int = 100
    """Lifelong floors only: steps per training episode (a window of a lifelong run)."""
    eval_steps: int = 500
    """Lifelong floors only: steps of each evaluation run (``sim.evaluate_lifelong``)."""
    eval_runs: int = 1
    """Lifelong floors only: independent runs per evaluation (all on ``eval_seed``, batched),
    whose throughput is averaged. One run's throughput swings from one evaluation to the next
    (on warehouse-50 between 88 and 200 deliveries per 1000 steps), so that
    ``best.safetensors``, the best of many one-run evaluations, tends to be a lucky run."""

    @property
    def lifelong(self) -> bool:
        """Whether ``scenario`` is a lifelong floor (``warehouse-N``)."""
        return is_lifelong(self.scenario)

    def resolved_run_dir(self) -> Path:
        """``run_dir`` or its default."""
        return Path(self.run_dir or default_run_dir(self.algo, self.reward, self.scenario,
                                                    self.seed))

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check every field (type and range); normalise NumPy numbers and paths.

        Raises
        ------
        ValueError
            Naming the first bad field and what is valid.
        """
        check_algo(self.algo)
        if not isinstance(self.reward, str) or self.reward not in REWARD_NAMES:
            raise ValueError(f"unknown reward {self.reward!r}; expected one of "
                             f"{list(REWARD_NAMES)}")
        if not isinstance(self.scenario, str):
            raise ValueError(f"scenario must be a scenario name (a string), got "
                             f"{self.scenario!r}")
        if is_lifelong(self.scenario) and self.algo not in ENTITY_ALGORITHMS:
            raise ValueError(f"scenario {self.scenario!r} is lifelong; {self.algo!r} trains on "
                             "the paper's episodic scenarios ('3v3', '6v6', 'NvM', "
                             f"'warehouse'); the entity learners {list(ENTITY_ALGORITHMS)} "
                             "train on lifelong floors too")
        for name in ("episodes", "eval_episodes", "log_every", "checkpoint_every", "threads",
                     "window", "eval_steps", "eval_runs"):
            setattr(self, name, check_int(name, getattr(self, name), 1))
        self.critic_warmup = check_int("critic_warmup", self.critic_warmup, 0)
        self.eval_every = check_int("eval_every", self.eval_every, 0)
        # the noise and sampling generators are seeded with seed + 1 and seed + 2
        self.seed = check_int("seed", self.seed, 0, 2**63 - 3)
        self.eval_seed = check_int("eval_seed", self.eval_seed, 0, 2**63 - 1)
        if self.stop_response is not None:
            self.stop_response = check_real("stop_response", self.stop_response, 0.0, 1.0)
        self.fastest_min_response = check_real("fastest_min_response",
                                               self.fastest_min_response, 0.0, 1.0)
        if self.run_dir is not None:
            if not isinstance(self.run_dir, (str, os.PathLike)) or not os.fspath(self.run_dir):
                raise ValueError(f"run_dir must be a folder path or None, got {self.run_dir!r}")
            self.run_dir = os.fspath(self.run_dir)
        self.progress = check_bool("progress", self.progress)
        self.tensorboard = check_bool("tensorboard", self.tensorboard)


@dataclass
class TrainResult:
    """What :func:`train` returns."""

    run_dir: Path
    """The run folder (log and checkpoints)."""
    learner: ActorCritic
    """The trained learner."""
    episodes: int
    """Training episodes finished."""
    env_steps: int
    """Environment steps taken (agent-steps / N), summed over the parallel environments."""
    updates: int
    """Gradient updates done."""
    seconds: float
    """Wall-clock training time, summed over resumed segments."""
    last_eval: dict[str, float] = field(default_factory=dict)
    """Metrics of the last evaluation."""
    best_response_rate: float = -1.0
    """Best evaluated task response rate."""
    interrupted: bool = False
    """True if a signal stopped the run before its episode budget."""
    best_throughput: float = -1.0
    """Lifelong runs: best evaluated throughput (deliveries per 1000 steps); -1 otherwise."""


def default_run_dir(algo: str, reward: str, scenario: str, seed: int) -> str:
    """``runs/<algo>-<reward>-<scenario>-s<seed>``."""
    return os.path.join("runs", f"{algo}-{reward}-{scenario}-s{seed}")


def _noise_std(cfg: Any, episodes: int) -> float:
    frac = min(episodes / max(cfg.noise_decay_episodes, 1), 1.0)
    return cfg.noise_start + frac * (cfg.noise_end - cfg.noise_start)


def _best_time(path: Path) -> float:
    """The validation time of the best policy so far (inf if none): of two evaluations with
    the same task response, ``best.safetensors`` keeps the faster (issue 16), as
    ``benchmarks/train_policies.py`` ranks them."""
    if not path.is_file():
        return math.inf
    return float(read_metadata(path).get("last_eval", {}).get("avg_time", math.inf))


def _crossed(before: int, now: int, every: int) -> bool:
    return every > 0 and now // every > before // every


class _StopRequest:
    """Turns SIGINT / SIGTERM into a flag checked between iterations (main thread only)."""

    def __init__(self) -> None:
        self.requested = False
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:  # a second signal: stop now
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc: Any) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


class _CsvLog:
    """``progress.csv``, appended row by row; on resume, rows past the checkpoint are dropped."""

    def __init__(self, path: Path, columns: list[str], keep_until: int | None) -> None:
        self.path, self.columns = path, columns
        rows: list[dict[str, str]] = []
        if keep_until is not None and path.is_file():
            with path.open(newline="") as f:
                rows = [r for r in csv.DictReader(f) if int(r["episode"]) <= keep_until]
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
        atomic_write_bytes(path, buf.getvalue().encode())

        self.tb: Any = None

    def enable_tensorboard(self, folder: Path) -> None:
        """Mirror every row into TensorBoard scalars if ``tensorboard`` is installed."""
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:  # tensorboard is optional
            return
        self.tb = SummaryWriter(str(folder))

    def write(self, row: dict[str, Any]) -> None:
        with self.path.open("a", newline="") as f:
            csv.DictWriter(f, fieldnames=self.columns, extrasaction="ignore").writerow(
                {k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
        if self.tb is not None:
            for k, v in row.items():
                if k != "episode" and isinstance(v, (int, float)) and math.isfinite(v):
                    self.tb.add_scalar(k, v, global_step=int(row["episode"]))
            self.tb.flush()


def _env_tensors(env: Any) -> dict[str, Tensor]:
    if getattr(env, "lifelong", False):
        return {f"env.lifelong.{k}": v for k, v in env.state_tensors().items()}
    out = {f"env.{k}": getattr(env, k).clone() for k in _ENV_FIELDS}
    out["rng.env"] = env.generator.get_state()
    return out


def _load_env(env: Any, tensors: dict[str, Tensor]) -> None:
    """Put B environments back mid-episode exactly as saved."""
    if getattr(env, "lifelong", False):
        prefix = "env.lifelong."
        env.load_state_tensors({k[len(prefix):]: v for k, v in tensors.items()
                                if k.startswith(prefix)})
        return
    env.set_state(tensors["env.agent_pos"], tensors["env.task_pos"], tensors["env.agent_vel"])
    for k in ("task_claimed", "agent_task", "steps", "done"):
        setattr(env, k, tensors[f"env.{k}"].clone())
    env.generator.set_state(tensors["rng.env"])


def _term_names(scenario: str, reward: str) -> list[str]:
    env = sim.make_env(scenario, num_envs=1, reward=reward, seed=0)
    _, _, _, info = env.step(torch.zeros(1, env.num_agents, 2))
    return sorted(info["reward_terms"])


def _metadata(config: TrainConfig, learner: ActorCritic, env: Any, kind: str,
              counters: dict[str, Any]) -> dict[str, Any]:
    return {
        "kind": kind,
        "algo": config.algo,
        "reward": config.reward,
        "scenario": config.scenario,
        "seed": config.seed,
        "num_agents": env.num_agents,
        "num_tasks": env.num_tasks,
        "obs_dim": env.obs_dim,
        "state_dim": env.state_dim,
        "config": dataclasses.asdict(learner.config),
        "train_config": dataclasses.asdict(config),
        "code_version": code_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **counters,
    }


def train(
    config: TrainConfig,
    learner_config: Any = None,
    *,
    resume: bool = False,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    init_from: str | os.PathLike[str] | None = None,
    make_shield: Callable[[Any], Any] | None = None,
    init_other_reward: bool = False,
) -> TrainResult:
    """Train a MADDPG or BiCNet learner.

    Parameters
    ----------
    config : TrainConfig
        What to train (algorithm, reward, scenario, episodes, seed) and where to write.
    learner_config : MADDPGConfig, BiCNetConfig, dict or None
        Hyperparameters (a dict overrides the defaults); ignored-but-checked when resuming.
    resume : bool
        Continue the run in ``config.run_dir`` from its last checkpoint, up to
        ``config.episodes``. A checkpoint without its replay buffer (:func:`portable_copy`)
        resumes too, with an empty buffer that refills from the restored policy: the run goes
        on from its networks, optimizers, counters and schedules, but no longer bit for bit
        like an uninterrupted one (a warning says so).
    on_checkpoint : callable, optional
        Called with the checkpoint's counters after every periodic checkpoint (used by tests to
        simulate a crash).
    init_from : path-like, optional
        A training checkpoint of the same algorithm, reward and network width (with other
        learning rates, noise or batch) whose networks, targets, Adam moments and update
        count start this new run; the replay buffer, environments and counters start afresh.
        For the entity learners (``learners.algorithms.ENTITY_ALGORITHMS``), whose weights do
        not depend on N, possibly of another scenario (e.g. the previous stage of a
        curriculum, :mod:`learners.curriculum`); for the others, of the same scenario (e.g. a
        long run's checkpoint, to fine-tune with its critic).
        Or a deployed policy (``kind="policy"``, e.g. a shipped ``best.safetensors``) of any
        algorithm, on the same scenario unless it is an entity learner's: only its actor
        carries over (the critic starts fresh, see ``TrainConfig.critic_warmup``), and its
        reward may differ from this run's (a fine-tune with another reward).
    make_shield : callable, optional
        Builds the safety shield of a learner config with ``shield=True`` from the controller
        it wraps: ``allocator.SafetyShield`` (what ``agv train`` passes). ``learners`` does not
        import ``allocator``, so the caller hands it in; ``shield=True`` without it is a
        ``ValueError``.
    init_other_reward : bool
        Let ``init_from`` be a checkpoint trained on another reward (default False: the
        rewards must match). The critic then starts from values learned for the old reward,
        which suits a fine-tune whose reward changes a term (``benchmarks/entity_probe.py``).

    Returns
    -------
    TrainResult

    Raises
    ------
    ValueError
        For an unknown algorithm, reward or scenario; when resuming with nothing to resume or
        with settings that differ from the checkpoint's; when starting a new run in a folder
        that already holds one.
    """
    config.validate()
    run_dir = config.resolved_run_dir()
    ckpt_path = run_dir / "checkpoint.safetensors"
    saved: dict[str, Tensor] | None = None
    if resume:
        if not ckpt_path.is_file():
            raise ValueError(f"nothing to resume: expected a checkpoint at {ckpt_path} (written "
                             f"by `agv train --run-dir {run_dir}` every --checkpoint-every "
                             "episodes)")
        saved, meta = load_checkpoint(ckpt_path, kind="training")
        _saved_train_config(meta, ckpt_path, run_dir)
        for key in ("algo", "reward", "scenario", "seed"):
            if meta[key] != getattr(config, key):
                raise ValueError(f"cannot resume {run_dir}: it was trained with {key}="
                                 f"{meta[key]!r}, this call asks for {getattr(config, key)!r}")
        learner_cfg = make_config(config.algo, meta["config"])
        if learner_config is not None:
            given = (learner_config if isinstance(learner_config, dict)
                     else dataclasses.asdict(learner_config))
            diff = {k: v for k, v in given.items() if meta["config"].get(k) != v}
            if diff:
                raise ValueError(f"cannot resume {run_dir} with different hyperparameters "
                                 f"{diff}; the checkpoint has {meta['config']}")
    else:
        if ckpt_path.exists():
            raise ValueError(f"{run_dir} already holds a run ({ckpt_path.name}); continue it "
                             "with --resume or choose another --run-dir")
        learner_cfg = (learner_config if learner_config is not None and
                       not isinstance(learner_config, dict)
                       else make_config(config.algo, learner_config))
    init: dict[str, Tensor] | None = None
    init_kind = ""
    if init_from is not None:
        init, init_kind = _init_tensors(init_from, config, learner_cfg, resume,
                                        init_other_reward)
    cfg = learner_cfg
    config_class = ALGORITHMS[config.algo][1]
    if not isinstance(cfg, config_class):
        raise ValueError(f"learner_config for {config.algo} must be a {config_class.__name__} "
                         f"or a dict of its fields, got {type(cfg).__name__}")
    cfg.validate()

    # ---------------------------------------------------------------- setup
    torch.set_num_threads(config.threads)
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.manual_seed(config.seed)
    env = sim.make_env(config.scenario, num_envs=cfg.num_envs, reward=config.reward,
                       seed=config.seed)
    lifelong = bool(getattr(env, "lifelong", False))
    learner = build_learner(config.algo, env.obs_dim, env.state_dim, env.num_agents, cfg,
                            lifelong=lifelong)
    if lifelong:
        learner.reset(env)  # the observation layout and the floor's waypoints
    buffer = ReplayBuffer(cfg.buffer_size, env.num_agents, env.obs_dim, env.state_dim)
    noise_gen = torch.Generator().manual_seed(config.seed + 1)
    sample_gen = torch.Generator().manual_seed(config.seed + 2)
    terms = _term_names(config.scenario, config.reward)
    B = env.num_envs
    counters: dict[str, Any] = {"episodes": 0, "env_steps": 0, "updates": 0, "seconds": 0.0,
                                "best_response_rate": -1.0, "last_eval": {}}
    # lifelong: deliveries and steps at the start of the current window, per environment
    window_delivered = torch.zeros(B, dtype=torch.int64)
    window_steps = torch.zeros(B, dtype=torch.int64)
    best_throughput = -1.0
    recent: deque[float] = deque(maxlen=_RECENT)  # response rate of recent training episodes
    recent_return: deque[float] = deque(maxlen=_RECENT)
    ep_return = torch.zeros(B)  # running episode return (mean over agents), per environment
    ep_terms = {t: torch.zeros(B) for t in terms}
    recent_terms: dict[str, deque[float]] = {t: deque(maxlen=_RECENT) for t in terms}
    if saved is not None:
        learner.load_training_tensors(saved)
        if "buffer.obs" in saved:
            buffer.load_state_dict(saved)
        else:  # a portable copy: the buffer refills from the restored policy
            warnings.warn(f"{ckpt_path} holds no replay buffer (a portable copy): the run "
                          "resumes with an empty one, so it no longer follows an "
                          "uninterrupted run bit for bit", stacklevel=2)
        _load_env(env, saved)
        noise_gen.set_state(saved["rng.noise"])
        sample_gen.set_state(saved["rng.sample"])
        torch.set_rng_state(saved["rng.torch"])
        ep_return = saved["stats.ep_return"].clone()
        ep_terms = {t: saved[f"stats.ep_term.{t}"].clone() for t in terms}
        recent.extend(saved["stats.recent"].tolist())
        recent_return.extend(saved["stats.recent_return"].tolist())
        for t in terms:
            recent_terms[t].extend(saved[f"stats.recent_term.{t}"].tolist())
        counters.update({k: meta[k] for k in counters})
        if lifelong:
            window_delivered = saved["stats.window_delivered"].clone()
            window_steps = saved["stats.window_steps"].clone()
            best_throughput = float(counters["last_eval"].get("best_throughput", -1.0))
    elif init is not None:
        try:
            init = learner.adapt_init_tensors(init)
            if init_kind == "training":
                learner.load_training_tensors(init)
            else:
                learner.load_policy_tensors(init)
        except RuntimeError as err:  # a shape the metadata checks did not catch
            raise ValueError(f"init_from {init_from}: its networks do not fit this run's "
                             f"({str(err).strip().splitlines()[-1].strip()})") from err
    shield = None
    shield_penalty = float(getattr(cfg, "shield_penalty", 0.0))
    if getattr(cfg, "shield", False):  # the entity learners' option: the shield in the loop
        if make_shield is None:
            raise ValueError("shield=True needs make_shield=allocator.SafetyShield (learners "
                             "does not import allocator; agv train passes it)")
        lanes = float(getattr(learner.config, "shield_keep_right", 0.0))
        if lanes:
            make_shield = functools.partial(make_shield, keep_right=lanes)
        shield = make_shield(_Still())
        shield.reset(env)
    run_dir.mkdir(parents=True, exist_ok=True)
    clean_stale_temporaries(run_dir)  # left by a run killed in the middle of a write
    if resume:  # a kill between a checkpoint and its sidecar leaves the sidecar behind
        for name in ("checkpoint", "policy", "best"):
            if (run_dir / f"{name}.safetensors").is_file():
                write_sidecar(run_dir / f"{name}.safetensors")
    config.run_dir = str(run_dir)
    if not resume:
        atomic_write_text(run_dir / "config.json", json.dumps(
            {"train": dataclasses.asdict(config), config.algo: dataclasses.asdict(cfg)},
            indent=2) + "\n")
    log = _CsvLog(run_dir / "progress.csv",
                  (LIFELONG_CSV_COLUMNS if lifelong else CSV_COLUMNS)
                  + [f"train_term_{t}" for t in terms],
                  counters["episodes"] if resume else None)
    if config.tensorboard:
        log.enable_tensorboard(run_dir / "tb")
    obs, state = env.observe(), env.global_state()
    losses: dict[str, float] = {}

    def close_episodes(ids: Tensor, scores: list[float]) -> None:
        """Record the episodes (lifelong: windows) of environments ``ids`` that just ended,
        with their scores (response rate, or deliveries per 1000 steps), and zero their
        running returns."""
        recent.extend(scores)
        recent_return.extend(ep_return[ids].tolist())
        ep_return[ids] = 0.0
        for t in terms:
            recent_terms[t].extend(ep_terms[t][ids].tolist())
            ep_terms[t][ids] = 0.0
        counters["episodes"] += len(ids)

    def deployed() -> Any:
        """What an evaluation runs: the learner, shielded when it trains shielded (a fresh
        shield, so that the training shield's state and counters stay the training env's)."""
        return learner if shield is None else make_shield(learner)

    def evaluate() -> dict[str, float]:
        if lifelong:
            return evaluate_lifelong()
        m = sim.evaluate(deployed(), config.scenario, episodes=config.eval_episodes,
                         seed=config.eval_seed)
        counters["last_eval"] = m.as_dict()
        if m.response_rate > counters["best_response_rate"] or (
                m.response_rate == counters["best_response_rate"]
                and m.avg_time < _best_time(run_dir / "best.safetensors")):
            counters["best_response_rate"] = m.response_rate
            save_checkpoint(run_dir / "best.safetensors", learner.policy_tensors(),
                            _metadata(config, learner, env, "policy", counters))
        if (m.response_rate >= config.fastest_min_response
                and m.avg_time < _best_time(run_dir / FASTEST)):
            save_checkpoint(run_dir / FASTEST, learner.policy_tensors(),
                            _metadata(config, learner, env, "policy", counters))
        return m.as_dict()

    def evaluate_lifelong() -> dict[str, float]:
        nonlocal best_throughput
        m = sim.evaluate_lifelong(deployed(), config.scenario, steps=config.eval_steps,
                                  seed=config.eval_seed, runs=config.eval_runs,
                                  batch_size=config.eval_runs)
        learner.reset(env)  # back to the training floor's layout (the same floor)
        out = {f.name: float(getattr(m, f.name)) for f in dataclasses.fields(m)
               if isinstance(getattr(m, f.name), (int, float))
               and not isinstance(getattr(m, f.name), bool)}
        if m.throughput > best_throughput:
            best_throughput = float(m.throughput)
            counters["last_eval"] = {**out, "best_throughput": best_throughput}
            save_checkpoint(run_dir / "best.safetensors", learner.policy_tensors(),
                            _metadata(config, learner, env, "policy", counters))
        counters["last_eval"] = {**out, "best_throughput": best_throughput}
        return out

    def write_checkpoint() -> None:
        tensors = {**learner.training_tensors(), **buffer.state_dict(), **_env_tensors(env),
                   "rng.noise": noise_gen.get_state(), "rng.sample": sample_gen.get_state(),
                   "rng.torch": torch.get_rng_state(),
                   "stats.ep_return": ep_return, "stats.recent": torch.tensor(list(recent)),
                   "stats.recent_return": torch.tensor(list(recent_return))}
        if lifelong:
            tensors["stats.window_delivered"] = window_delivered
            tensors["stats.window_steps"] = window_steps
        for t in terms:
            tensors[f"stats.ep_term.{t}"] = ep_terms[t]
            tensors[f"stats.recent_term.{t}"] = torch.tensor(list(recent_terms[t]))
        save_checkpoint(ckpt_path, tensors,
                        _metadata(config, learner, env, "training", counters))
        save_checkpoint(run_dir / "policy.safetensors", learner.policy_tensors(),
                        _metadata(config, learner, env, "policy", counters))

    from tqdm.auto import tqdm

    bar = tqdm(total=config.episodes, initial=min(counters["episodes"], config.episodes),
               disable=not config.progress, unit="ep", dynamic_ncols=True,
               desc=f"{config.algo}-{config.reward} {config.scenario}")
    start = time.perf_counter() - counters["seconds"]
    interrupted = False
    with _StopRequest() as stop:
        while counters["episodes"] < config.episodes:
            episodes_before = counters["episodes"]
            # 1. collect one vectorized step with exploration noise
            noise_std = _noise_std(cfg, counters["episodes"])
            action = learner.explore(obs, noise_std, noise_gen)
            # with the shield in the loop the simulator executes the shield's action, and the
            # policy's intended action is what is stored: the critic learns what an intention
            # leads to through the shield
            executed = shield.filter(action) if shield is not None else action
            next_obs, reward, done, info = env.step(executed)
            if shield_penalty:  # what the shield had to change, charged to the intention
                reward = reward - shield_penalty * torch.linalg.vector_norm(
                    action - executed, dim=-1)
            next_state = env.global_state()
            # every task claimed: terminal; step limit only: truncated, so bootstrap;
            # lifelong operation has no terminal state
            terminal = torch.zeros(B, dtype=torch.bool) if lifelong \
                else env.task_claimed.all(dim=1)

            # 2. store the B transitions, then reset the finished environments
            buffer.add(Batch(obs, state, action, reward * cfg.reward_scale, next_obs,
                             next_state, terminal.float()))
            counters["env_steps"] += B
            ep_return += reward.mean(dim=1)
            for t in terms:
                ep_terms[t] += info["reward_terms"][t].mean(dim=1)
            if lifelong:  # a window ends (all B floors step together) or the runs restart
                ended = ((env.steps - window_steps) >= config.window) | done
            if lifelong and bool(ended.any()):
                ids = ended.nonzero().flatten()
                span = (env.steps - window_steps)[ids].clamp_min(1).double()
                close_episodes(ids, ((env.delivered - window_delivered)[ids].double() * 1000.0
                                     / span).tolist())
                window_delivered = torch.where(ended, env.delivered, window_delivered)
                window_steps = torch.where(ended, env.steps, window_steps)
                if bool(done.any()):
                    obs, state = env.reset(env_ids=done), env.global_state()
                    window_delivered = torch.where(done, 0, window_delivered)
                    window_steps = torch.where(done, 0, window_steps)
                else:
                    obs, state = next_obs, next_state
            elif not lifelong and bool(done.any()):
                ids = done.nonzero().flatten()
                close_episodes(ids, env.task_claimed[ids].float().mean(dim=1).tolist())
                obs, state = env.reset(env_ids=done), env.global_state()
            else:
                obs, state = next_obs, next_state

            # 3. sample, update critics and actors, soft-update the targets
            if len(buffer) >= cfg.learning_starts:
                for _ in range(cfg.updates_per_step):
                    if learner.updates <= config.critic_warmup:  # only around the warm-up
                        _freeze_actor(learner, learner.updates < config.critic_warmup)
                    losses = learner.update(buffer.sample(cfg.batch_size, sample_gen))
            counters["updates"] = learner.updates
            counters["seconds"] = time.perf_counter() - start

            # 4. log, evaluate, checkpoint at episode milestones
            now = counters["episodes"]
            finished = now >= config.episodes
            running = sum(recent) / len(recent) if recent else float("nan")
            row: dict[str, Any] | None = None
            if _crossed(episodes_before, now, config.log_every) or finished:
                row = {"episode": now, "env_steps": counters["env_steps"],
                       "updates": counters["updates"], "seconds": counters["seconds"],
                       "noise_std": noise_std,
                       ("train_throughput" if lifelong else "train_response_rate"): running,
                       "train_return": (sum(recent_return) / len(recent_return)
                                        if recent_return else float("nan")),
                       **{k: losses.get(k, float("nan"))
                          for k in ("critic_loss", "actor_loss", "q")},
                       **{f"train_term_{t}": (sum(v) / len(v) if v else float("nan"))
                          for t, v in recent_terms.items()}}
            if _crossed(episodes_before, now, config.eval_every) or finished:
                metrics = evaluate()
                row = row or {"episode": now, "env_steps": counters["env_steps"],
                              "updates": counters["updates"], "seconds": counters["seconds"]}
                row.update({f"eval_{k}": v for k, v in metrics.items() if k != "episodes"})
                if lifelong:
                    bar.set_postfix_str(f"thr {running:.1f} eval {metrics['throughput']:.1f}")
                else:
                    bar.set_postfix_str(f"resp {running:.2f} eval "
                                        f"{metrics['response_rate']:.3f}")
                if (config.stop_response is not None and not lifelong
                        and metrics["response_rate"] >= config.stop_response):
                    finished = True
            if row is not None:
                log.write(row)
            bar.update(min(now, config.episodes) - min(episodes_before, config.episodes))
            if _crossed(episodes_before, now, 10 * B):
                key, name = ("throughput", "thr") if lifelong else ("response_rate", "resp")
                bar.set_postfix_str(f"{name} {running:.2f} eval "
                                    f"{counters['last_eval'].get(key, math.nan):.3f}")
            if stop.requested:
                interrupted = not finished
                finished = True
            if _crossed(episodes_before, now, config.checkpoint_every) or finished:
                write_checkpoint()
                if on_checkpoint is not None and not finished:
                    on_checkpoint(dict(counters))
            if finished:
                break
    bar.close()
    if interrupted:
        print(f"interrupted at episode {counters['episodes']}; checkpoint written. Continue with: "
              f"agv train --resume {run_dir}")
    return TrainResult(run_dir, learner, counters["episodes"], counters["env_steps"],
                       counters["updates"], counters["seconds"], counters["last_eval"],
                       counters["best_response_rate"], interrupted, best_throughput)


class _Still:
    """The controller a training shield wraps (the learner's actions go to ``filter``)."""

    name = "learner"

    def reset(self, env: Any) -> None:
        pass

    def act(self, obs: Tensor) -> Tensor:  # pragma: no cover - filter() is used instead
        return torch.zeros(*obs.shape[:2], 2)


INIT_FROM_SHAPES = ("hidden",)
"""The learner settings a run started with ``init_from`` must share with its checkpoint (they
set the networks' shapes); the others (learning rates, noise, batch, buffer, environments,
shield) may change, e.g. to fine-tune on another floor."""


def _freeze_actor(learner: ActorCritic, frozen: bool) -> None:
    """Set the actor optimizer's learning rate to 0 (``frozen``) or back to the config's.

    Adam keeps gathering its moments while the rate is 0, so that its first real steps are
    scaled by the gradients' history rather than being a full ``actor_lr`` in the sign of
    one gradient, as with moments started afresh."""
    lr = 0.0 if frozen else learner.config.actor_lr
    for group in learner.actor_optimizer.param_groups:
        group["lr"] = lr


def _init_tensors(path: str | os.PathLike[str], config: TrainConfig, learner_cfg: Any,
                  resume: bool, other_reward: bool = False) -> tuple[dict[str, Tensor], str]:
    """The learner tensors that start a new run (``init_from``): every tensor of a training
    checkpoint, or the actor of a deployed policy, with the checkpoint's kind (``"training"``
    or ``"policy"``).

    Raises
    ------
    ValueError
        When resuming; for a checkpoint of another algorithm, reward (unless
        ``other_reward``; a policy may always have another reward), mode (lifelong or
        episodic), network width (:data:`INIT_FROM_SHAPES`), or, for weights that depend on N
        (MADDPG's and BiCNet's, training or policy), scenario.
    """
    from learners.algorithms import ENTITY_ALGORITHMS

    if resume:
        raise ValueError("init_from starts a new run; a resumed run continues from its own "
                         "checkpoint")
    tensors, meta = load_checkpoint(path)
    if meta["kind"] == "policy":
        other_reward = True  # a policy carries no values of its reward
        if (meta["algo"] == config.algo and config.algo not in ENTITY_ALGORITHMS
                and meta["scenario"] != config.scenario):
            raise ValueError(f"init_from {path} is a {config.algo} policy for "
                             f"{meta['scenario']!r}; its weights (their observation size, "
                             "and MADDPG's per-agent actors) fit only that scenario, this run "
                             f"is on {config.scenario!r}")
    elif config.algo not in ENTITY_ALGORITHMS and meta["scenario"] != config.scenario:
        raise ValueError(f"init_from {path} is a {meta['algo']} training checkpoint for "
                         f"{meta['scenario']!r}; {config.algo}'s networks depend on N, so it "
                         f"can start only a run on the same scenario, this run is on "
                         f"{config.scenario!r} (only {list(ENTITY_ALGORITHMS)} move between "
                         "scenarios)")
    if is_lifelong(meta["scenario"]) != config.lifelong:
        modes = {True: "a lifelong floor", False: "episodic scenes"}
        raise ValueError(f"init_from {path} was trained on {modes[is_lifelong(meta['scenario'])]}"
                         f" ({meta['scenario']!r}), this run on {modes[config.lifelong]} "
                         f"({config.scenario!r}); their networks differ")
    for key in ("algo",) if other_reward else ("algo", "reward"):
        if meta[key] != getattr(config, key):
            raise ValueError(f"init_from {path} was trained with {key}={meta[key]!r}, this run "
                             f"has {getattr(config, key)!r}")
    for key in INIT_FROM_SHAPES:
        if meta["config"].get(key) != getattr(learner_cfg, key):
            raise ValueError(f"init_from {path} has networks of {key}={meta['config'].get(key)!r}"
                             f", this run asks for {key}={getattr(learner_cfg, key)!r}; the "
                             "networks must have the same shape")
    return tensors, meta["kind"]


PORTABLE_POLICIES = ("policy", "best", "fastest")
"""The policy files of a run folder that :func:`portable_copy` carries (each with its sidecar)."""


def portable_copy(run_dir: str | os.PathLike[str], target: str | os.PathLike[str]) -> Path:
    """Copy a run folder without its replay buffer: a few MB that resume anywhere.

    The replay buffer is nearly all of a checkpoint (about 70 MB per 25k joint transitions on
    6v6, up to ``buffer_size``); the networks, targets, Adam moments, environments, random
    generators and counters are a few MB. The copy holds that slim ``checkpoint.safetensors``,
    the policy files (``policy``, ``best``, ``fastest``, with their sidecars),
    ``progress.csv`` and ``config.json``, so a long run can be committed or moved to another
    machine and continued there with ``train(resume=True)`` / ``agv train --resume TARGET``
    (its buffer refills from the restored policy), or a fine-tune can start from it with
    ``init_from``.

    Parameters
    ----------
    run_dir : path-like
        A run folder holding ``checkpoint.safetensors``.
    target : path-like
        The new folder (created); it must not hold a run already.

    Returns
    -------
    Path
        The slim checkpoint written.

    Raises
    ------
    ValueError
        If ``run_dir`` holds no training checkpoint (or a bad one), or ``target`` is
        ``run_dir`` or already holds a checkpoint.
    """
    src, dest = Path(run_dir), Path(target)
    ckpt = src / "checkpoint.safetensors"
    if not ckpt.is_file():
        raise ValueError(f"portable_copy: no run to copy, expected a checkpoint at {ckpt}")
    if dest.exists() and dest.resolve() == src.resolve():
        raise ValueError(f"portable_copy: the target {dest} is the run folder itself")
    if (dest / "checkpoint.safetensors").exists():
        raise ValueError(f"portable_copy: {dest} already holds a run (checkpoint.safetensors)")
    tensors, meta = load_checkpoint(ckpt, kind="training")
    dest.mkdir(parents=True, exist_ok=True)
    for name in ("progress.csv", "config.json"):
        if (src / name).is_file():
            atomic_write_bytes(dest / name, (src / name).read_bytes())
    for name in PORTABLE_POLICIES:
        if (src / f"{name}.safetensors").is_file():
            policy, policy_meta = load_checkpoint(src / f"{name}.safetensors", kind="policy")
            save_checkpoint(dest / f"{name}.safetensors", policy, policy_meta)
    slim = {k: v for k, v in tensors.items() if not k.startswith("buffer.")}
    return save_checkpoint(dest / "checkpoint.safetensors", slim, meta)


def load_run_config(run_dir: str | os.PathLike[str]) -> tuple[TrainConfig, dict[str, Any]]:
    """The TrainConfig and learner config stored in a run's checkpoint (for ``--resume``).

    Raises
    ------
    ValueError
        If the folder holds no checkpoint to resume.
    """
    path = resolve_checkpoint_path(run_dir)
    if not path.is_file():
        raise ValueError(f"nothing to resume: expected a checkpoint at {path} (written by "
                         f"`agv train --run-dir {run_dir}`)")
    meta = read_metadata(path)
    if meta.get("kind") != "training":
        raise ValueError(f"{path} is a {meta.get('kind')!r} checkpoint; resuming needs the "
                         "run's checkpoint.safetensors")
    folder = Path(run_dir) if Path(run_dir).is_dir() else path.parent
    return _saved_train_config(meta, path, folder), meta["config"]


def _saved_train_config(meta: dict[str, Any], path: Path, run_dir: Path) -> TrainConfig:
    """The TrainConfig stored in a training checkpoint's header, checked, with ``run_dir``."""
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    saved = meta["train_config"]
    unknown = sorted(set(saved) - names)
    if unknown:
        raise ValueError(f"checkpoint {path} has a bad header: field 'train_config' holds "
                         f"unknown TrainConfig field(s) {unknown}")
    try:
        return TrainConfig(**{**saved, "run_dir": str(run_dir)})
    except ValueError as err:
        raise ValueError(f"checkpoint {path} has a bad header: field 'train_config' is "
                         f"invalid: {err}") from None
