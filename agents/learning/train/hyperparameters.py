"""``probegym train``'s default hyper-parameters, per algorithm and per task, in one table.

In the manner of rl-baselines3-zoo's hyper-parameter files: each algorithm has a ``default``
entry that every task starts from, and an entry per environment id holds only what that
task changes (none does yet: the published baselines, docs/baselines.md, were all trained
with the defaults). SB3's names; anything not here is SB3's default. ``--hyperparameters
JSON`` on the command line, or
:class:`agents.learning.train.run.TrainSettings`' ``hyperparameters``, overrides single
values for a run; its ``config.json`` records what was resolved.
"""

from __future__ import annotations

import copy
from typing import Any

#: Algorithm -> ``"default"`` or an environment id -> SB3 keyword arguments.
HYPERPARAMETERS: dict[str, dict[str, dict[str, Any]]] = {
    "ppo": {
        # 1,024 steps per env per update (four BreastCompress episodes), minibatches of 256,
        # a small network, and a narrower start than SB3's spread of 1 (e^-1 of the action
        # box): the tasks' tolerances (1-3 mm) are small against a full action (2-5 mm a step).
        "default": {
            "n_steps": 1024,
            "batch_size": 256,
            "n_epochs": 10,
            "learning_rate": 3e-4,
            "gamma": 0.99,
            "gae_lambda": 0.95,
            "clip_range": 0.2,
            "ent_coef": 0.0,
            "policy_kwargs": {"net_arch": [128, 128], "log_std_init": -1.0},
        },
    },
    "sac": {
        # SB3's defaults with a 100k buffer and learning from 1,000 steps.
        "default": {
            "buffer_size": 100_000,
            "learning_starts": 1_000,
            "batch_size": 256,
            "learning_rate": 3e-4,
            "gamma": 0.99,
            "policy_kwargs": {"net_arch": [256, 256]},
        },
    },
}


def default_hyperparameters(
    algo: str,
    env_id: str | None = None,
    table: dict[str, dict[str, dict[str, Any]]] | None = None,
) -> dict[str, Any]:
    """``algo``'s hyper-parameters for ``env_id``: the algorithm's defaults, updated with the
    task's own entry where the table has one (``policy_kwargs`` merged key by key). A copy:
    the caller may change it. ``table``: another table of :data:`HYPERPARAMETERS`' shape.

    Raises:
        KeyError: the table has no entry for ``algo``.
    """
    entries = (HYPERPARAMETERS if table is None else table)[algo]
    merged = copy.deepcopy(entries["default"])
    task = copy.deepcopy(entries.get(env_id or "", {}))
    policy_kwargs = {**merged.get("policy_kwargs", {}), **task.pop("policy_kwargs", {})}
    merged.update(task)
    if policy_kwargs:
        merged["policy_kwargs"] = policy_kwargs
    return merged
