"""Multi-agent learners (MADDPG, BiCNet): networks, replay buffer, training, checkpoints."""
