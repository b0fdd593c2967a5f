"""Gymnasium environments: a MuJoCo arm holding a linear US probe, coupled two ways to the
FE breast of :mod:`tissue`.

Importing this package registers the environments::

    import gymnasium as gym
    import envs  # noqa: F401 - registers probegym/...

    env = gym.make("probegym/BreastCompress-v0", contact="lm", mesh=1363)

| id | task |
| --- | --- |
| ``probegym/BreastCompress-v0`` | compress the breast until a lesion reaches a depth in the image |
| ``probegym/LesionSearch-v0`` | find a lesion, centre it in the image, hold the force in a band |
| ``probegym/ForceScan-v0`` | sweep a line on the skin, the force in a band, the face normal to it |
| ``probegym/LesionSearch-v1`` | v0's task with a shaped reward, the sweep observed, 2 mm a step |
| ``probegym/ForceScan-v1`` | v0's task with a shaped reward, the force's history, 2 mm a step |
| ``probegym/BreastCompress-v1`` | v0's task, the compression asked at most 28 % of the depth |
| ``probegym/BreastCompress-v2`` | v1's task with a shaped reward, the hold observed, 2 mm a step |

Every task takes ``domain_randomization=True`` (or a dict, or a :class:`DomainRandomization`):
tissue and lesion stiffness, lesion placement, F/T noise and bias, probe pose noise, drawn
from the reset's seed (:mod:`envs.randomization`).
"""

from __future__ import annotations

import gymnasium as gym

from envs.randomization import DomainRandomization
from envs.tasks.breast_compress import MAX_EPISODE_STEPS as _COMPRESS_STEPS
from envs.tasks.force_scan import MAX_EPISODE_STEPS as _SCAN_STEPS
from envs.tasks.lesion_search import MAX_EPISODE_STEPS as _SEARCH_STEPS

ENV_IDS = (
    "probegym/BreastCompress-v0",
    "probegym/LesionSearch-v0",
    "probegym/ForceScan-v0",
    "probegym/LesionSearch-v1",
    "probegym/ForceScan-v1",
    "probegym/BreastCompress-v1",
    "probegym/BreastCompress-v2",
)


def _register() -> None:
    if "probegym/BreastCompress-v0" not in gym.registry:
        gym.register(
            id="probegym/BreastCompress-v0",
            entry_point="envs.tasks.breast_compress:BreastCompressEnv",
            max_episode_steps=_COMPRESS_STEPS,
        )
    if "probegym/LesionSearch-v0" not in gym.registry:
        gym.register(
            id="probegym/LesionSearch-v0",
            entry_point="envs.tasks.lesion_search:LesionSearchEnv",
            max_episode_steps=_SEARCH_STEPS,
        )
    if "probegym/ForceScan-v0" not in gym.registry:
        gym.register(
            id="probegym/ForceScan-v0",
            entry_point="envs.tasks.force_scan:ForceScanEnv",
            max_episode_steps=_SCAN_STEPS,
        )

    if "probegym/LesionSearch-v1" not in gym.registry:
        gym.register(
            id="probegym/LesionSearch-v1",
            entry_point="envs.tasks.lesion_search_v1:LesionSearchV1Env",
            max_episode_steps=_SEARCH_STEPS,
        )

    if "probegym/ForceScan-v1" not in gym.registry:
        gym.register(
            id="probegym/ForceScan-v1",
            entry_point="envs.tasks.force_scan_v1:ForceScanV1Env",
            max_episode_steps=_SCAN_STEPS,
        )

    if "probegym/BreastCompress-v1" not in gym.registry:
        gym.register(
            id="probegym/BreastCompress-v1",
            entry_point="envs.tasks.breast_compress_v1:BreastCompressV1Env",
            max_episode_steps=_COMPRESS_STEPS,
        )

    if "probegym/BreastCompress-v2" not in gym.registry:
        gym.register(
            id="probegym/BreastCompress-v2",
            entry_point="envs.tasks.breast_compress_v2:BreastCompressV2Env",
            max_episode_steps=_COMPRESS_STEPS,
        )


_register()

__all__ = ["ENV_IDS", "DomainRandomization"]
