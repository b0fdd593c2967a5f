"""Training with stable-baselines3: ``probegym train`` and loading what it saved."""

from agents.learning.train.artifacts import TrainedPolicy, TrainedPolicyError, load_policy

__all__ = ["TrainedPolicy", "TrainedPolicyError", "load_policy"]
