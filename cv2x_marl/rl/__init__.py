"""RL adaptors (stable-baselines3): the agents x copies VecEnv and PPO training."""
