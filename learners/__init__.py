"""Multi-agent learners (MADDPG, BiCNet): networks, replay buffer, training, checkpoints.

Typical use::

    from learners.train import TrainConfig, train
    result = train(TrainConfig(algo="bicnet", reward="ipf", scenario="3v3", episodes=5000))
    from learners.policy import LearnedPolicy
    policy = LearnedPolicy.load(result.run_dir / "best.safetensors")  # policy.act(obs)

``learners`` imports ``sim`` only, never ``allocator``. See ``docs/learners.md``.
"""
