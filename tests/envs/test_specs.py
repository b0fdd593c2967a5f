"""Each environment's docstring is its spec: it names every observation key (its Observation
space section) and every reward term (its Rewards section) the environment produces."""

from __future__ import annotations

import re

import gymnasium as gym
import numpy as np
import pytest

import envs


def _section(doc: str, title: str) -> str:
    return doc.split(f"## {title}", 1)[1].split("\n    ## ", 1)[0]


@pytest.mark.parametrize("env_id", envs.ENV_IDS)
def test_the_spec_names_every_observation_key_and_reward_term(env_id: str) -> None:
    env = gym.make(env_id, mesh=623, image=True)
    doc = type(env.unwrapped).__doc__ or ""
    observation, _ = env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    env.close()
    named_keys = set(re.findall(r"``(\w+)``", _section(doc, "Observation space")))
    assert set(observation) <= named_keys, sorted(set(observation) - named_keys)
    named_terms = set(re.findall(r"``(\w+)``", _section(doc, "Rewards")))
    assert set(info["reward_terms"]) <= named_terms, sorted(set(info["reward_terms"]) - named_terms)
