"""What ``probegym train`` leaves in its ``--out`` folder, and loading a trained policy back.

Layout of a training folder::

    config.json        the fully resolved configuration (env id and kwargs, algorithm and
                       hyper-parameters, seed, versions, code revision, command)
    model.zip          the final model (SB3's format)
    vecnormalize.pkl   observation-normalisation statistics, where they were used
    checkpoints/       model_<steps>_steps.zip (+ model_vecnormalize_<steps>_steps.pkl)
    eval/              evaluations.npz (SB3's EvalCallback log), best_model.zip and its
                       best_vecnormalize.pkl
    monitor/           Monitor CSVs, one per training env
    tb/                TensorBoard event files

:func:`load_policy` turns a folder (or a ``.zip`` inside one) into a callable ``policy(obs)
-> action`` that applies the saved normalisation, deterministic by default.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue import ConfigError

CONFIG_FILE = "config.json"
MODEL_FILE = "model.zip"
NORMALIZE_FILE = "vecnormalize.pkl"
BEST_NORMALIZE_FILE = "best_vecnormalize.pkl"
CHECKPOINTS = "checkpoints"
CHECKPOINT_PREFIX = "model"


class TrainedPolicyError(ConfigError):
    """A path that is not a training folder or model: the message says what was expected."""


def training_folder(path: str | Path) -> tuple[Path, Path]:
    """The training folder and the model file ``path`` names (a folder: its final model, else
    its latest checkpoint; a ``.zip``: that model in its folder or in ``checkpoints/``)."""
    path = Path(path)
    if path.is_dir():
        model = path / MODEL_FILE
        if not model.is_file():
            latest = latest_checkpoint(path)
            if latest is None:
                raise TrainedPolicyError(
                    f"{path} holds no {MODEL_FILE} and no checkpoint: give the --out folder of "
                    "a probegym train run, or a model .zip"
                )
            model = latest[0]
        return path, model
    if path.suffix == ".zip" and path.is_file():
        folder = path.parent.parent if path.parent.name == CHECKPOINTS else path.parent
        if path.parent.name == "eval":
            folder = path.parent.parent
        return folder, path
    raise TrainedPolicyError(
        f"{path} is neither a probegym train folder nor a model .zip (does it exist?)"
    )


def latest_checkpoint(folder: Path) -> tuple[Path, int] | None:
    """The latest checkpoint in ``folder/checkpoints`` and its step count, or None."""
    found = []
    for candidate in (folder / CHECKPOINTS).glob(f"{CHECKPOINT_PREFIX}_*_steps.zip"):
        steps = checkpoint_steps(candidate)
        if steps is not None:
            found.append((steps, candidate))
    if not found:
        return None
    steps, path = max(found)
    return path, steps


def checkpoint_steps(checkpoint: Path) -> int | None:
    """The step count in a checkpoint's name (``model_<steps>_steps.zip``), or None."""
    middle = checkpoint.stem[len(CHECKPOINT_PREFIX) + 1 : -len("_steps")]
    if checkpoint.parent.name != CHECKPOINTS or not middle.isdigit():
        return None
    return int(middle)


def checkpoint_normalization(folder: Path, steps: int) -> Path:
    """The normalisation statistics saved with the checkpoint at ``steps`` in a training
    folder (SB3's CheckpointCallback name)."""
    return folder / CHECKPOINTS / f"{CHECKPOINT_PREFIX}_vecnormalize_{steps}_steps.pkl"


def read_config(folder: Path) -> dict[str, Any]:
    """The folder's ``config.json``."""
    path = folder / CONFIG_FILE
    if not path.is_file():
        raise TrainedPolicyError(
            f"{folder} has no {CONFIG_FILE}: it was not written by probegym train"
        )
    config: dict[str, Any] = json.loads(path.read_text())
    return config


@dataclass
class TrainedPolicy:
    """A trained SB3 model as ``policy(observation) -> action`` (one env's observation).

    Attributes:
        model: the SB3 algorithm.
        config: the training folder's configuration (``config.json``).
        normalizer: the saved VecNormalize (None where none was used); applied to each
            observation, never updated.
        deterministic: whether actions are the policy's mode.
    """

    model: Any
    config: dict[str, Any]
    normalizer: Any = None
    deterministic: bool = True

    def __call__(self, observation: dict[str, NDArray[Any]]) -> NDArray[np.float32]:
        batch = {key: np.asarray(value)[None] for key, value in observation.items()}
        if self.normalizer is not None:
            batch = self.normalizer.normalize_obs(batch)
        action, _ = self.model.predict(batch, deterministic=self.deterministic)
        return np.asarray(action[0], dtype=np.float32)

    def reset(self) -> None:
        """Nothing to forget (the policies are feed-forward); for the scripted policies'
        interface."""


def normalization_of(folder: Path, model_path: Path, config: dict[str, Any]) -> Path | None:
    """The normalisation statistics saved with ``model_path`` (the final model's, a
    checkpoint's or the best model's), None for a run trained without normalisation.

    Raises:
        TrainedPolicyError: the run normalised observations but the file is missing.
    """
    if not config.get("normalize"):
        return None
    stats = folder / NORMALIZE_FILE
    steps = checkpoint_steps(model_path)
    if steps is not None:
        stats = checkpoint_normalization(folder, steps)
    elif model_path.parent.name == "eval":
        stats = model_path.parent / BEST_NORMALIZE_FILE
    if not stats.is_file():
        raise TrainedPolicyError(
            f"{folder} was trained with observation normalisation but {stats.name} is "
            "missing: the model cannot see observations as it learnt them"
        )
    return stats


def load_policy(path: str | Path, deterministic: bool = True) -> TrainedPolicy:
    """Load a trained policy from a ``probegym train`` folder or a model ``.zip`` in one."""
    folder, model_path = training_folder(path)
    config = read_config(folder)
    from stable_baselines3 import PPO, SAC

    algorithms: dict[str, Any] = {"ppo": PPO, "sac": SAC}
    algo = str(config.get("algo", "")).lower()
    if algo not in algorithms:
        raise TrainedPolicyError(
            f"{folder}/{CONFIG_FILE} names algorithm {algo!r}; expected ppo or sac"
        )
    model = algorithms[algo].load(model_path, device="cpu")
    normalizer = None
    stats = normalization_of(folder, model_path, config)
    if stats is not None:
        import pickle

        with stats.open("rb") as handle:
            normalizer = pickle.load(handle)  # SB3's own format (VecNormalize.save)
        normalizer.training = False
        normalizer.norm_reward = False
    return TrainedPolicy(model, config, normalizer, deterministic)
