"""Errors of the RL layer (importable without stable-baselines3)."""


class TrainError(ValueError):
    """A training configuration or run folder is invalid."""
