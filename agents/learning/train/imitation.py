"""Behaviour cloning from a task's scripted policy: the start of ``probegym train
--pretrain-scripted N``.

The scripted policies (:data:`agents.learning.policies.SCRIPTED_POLICIES`) solve every task; a
network that first imitates one starts its reinforcement learning where the task's reward
is earned, not where random motion leads (for ForceScan: holding the force band while
moving along the skin, which PPO from scratch does not find; see docs/learning-runs.md).

:func:`scripted_demonstrations` runs the scripted policy for N seeded episodes in one env,
its action scales set to the env's, and returns every observation with the action taken
(clipped to the action space, as the env clips). :func:`clone_into` fits the policy
network's action mean to those actions by least squares (Adam, mini-batches), on the
observations as the training's normalisation will show them (its running statistics are
first updated with the demonstrations). The value network is left as it is: PPO's first
updates fit it to the cloned policy's returns.

Limitations: the clone sees only states the scripted policy visits, so its errors compound
off them (the covariate shift DAgger corrects, not done here); the log standard deviation
is kept at its initial value, so PPO's exploration around the clone is the run's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Demonstrations:
    """What the scripted policy did: observations by key, (n, ...) each; actions (n, 6)
    within the action space; the episodes run and how many succeeded."""

    observations: dict[str, NDArray[np.float32]]
    actions: NDArray[np.float32]
    episodes: int
    successes: int

    @property
    def samples(self) -> int:
        return int(self.actions.shape[0])


def scripted_demonstrations(
    env_id: str, env_kwargs: dict[str, Any], episodes: int, seed: int
) -> Demonstrations:
    """Run the task's scripted policy for ``episodes`` episodes (episode k reset with
    ``seed + k``) in ``gymnasium.make(env_id, **env_kwargs)``."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the environments
    from agents.learning.policies import SCRIPTED_POLICIES

    env = gym.make(env_id, **env_kwargs)
    scales = env.unwrapped.action_config  # type: ignore[attr-defined]
    low, high = env.action_space.low, env.action_space.high  # type: ignore[attr-defined]
    observations: dict[str, list[NDArray[np.float32]]] = {}
    actions: list[NDArray[np.float32]] = []
    successes = 0
    try:
        for episode in range(episodes):
            policy = SCRIPTED_POLICIES[env_id]()
            # The scripted policies command metres and radians: tell them the env's scales.
            for name in ("max_translation_m", "max_rotation_rad"):
                if hasattr(policy, name):
                    setattr(policy, name, getattr(scales, name))
            observation, _ = env.reset(seed=seed + episode)
            done = False
            info: dict[str, Any] = {}
            while not done:
                action = np.clip(np.asarray(policy(observation), np.float32), low, high)
                for key, value in observation.items():
                    observations.setdefault(key, []).append(np.asarray(value, np.float32))
                actions.append(action)
                observation, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
            successes += bool(info.get("is_success", False))
    finally:
        env.close()
    return Demonstrations(
        {key: np.stack(values) for key, values in observations.items()},
        np.stack(actions),
        episodes,
        successes,
    )


def clone_into(
    model: Any,
    demonstrations: Demonstrations,
    normalization: Any | None,
    epochs: int = 50,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    seed: int = 0,
) -> list[float]:
    """Fit ``model``'s (an SB3 on-policy model with a Gaussian policy) action mean to the
    demonstrated actions; returns the mean squared error of each epoch.

    ``normalization``: the training's ``VecNormalize`` (None: observations as they are);
    its observation statistics are updated with the demonstrations first and stay so.
    """
    import torch

    observations = demonstrations.observations
    if normalization is not None:
        for key, stats in normalization.obs_rms.items():
            stats.update(observations[key])
        observations = normalization.normalize_obs(observations)
    policy = model.policy
    tensors = {key: torch.as_tensor(np.asarray(value)) for key, value in observations.items()}
    target = torch.as_tensor(demonstrations.actions)
    # The actor alone: the shared feature extractor (a flatten), its hidden layers and head.
    actor = [
        *policy.mlp_extractor.policy_net.parameters(),
        *policy.action_net.parameters(),
    ]
    optimizer = torch.optim.Adam(actor, lr=learning_rate)
    generator = torch.Generator().manual_seed(seed)
    count = demonstrations.samples
    losses = []
    policy.set_training_mode(True)
    for _ in range(epochs):
        order = torch.randperm(count, generator=generator)
        total = 0.0
        for start in range(0, count, batch_size):
            batch = order[start : start + batch_size]
            mean = policy.get_distribution({k: v[batch] for k, v in tensors.items()})
            error = ((mean.distribution.mean - target[batch]) ** 2).mean()
            optimizer.zero_grad()
            error.backward()
            optimizer.step()
            total += float(error.detach()) * len(batch)
        losses.append(total / count)
    policy.set_training_mode(False)
    return losses
