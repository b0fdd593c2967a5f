"""Running the episodes: the inputs checked, the policy resolved, one record per episode.

An episode's record holds scalars (its CSV row) and, under ``series``, the per-step
figures the plots draw (JSON only). Timings are the fields named ``timing_*``: wall clock,
different every run, so :func:`without_timings` drops them before runs are compared.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.evaluation.records import TIMING_PREFIX
from agents.learning.evaluation.report import write_outputs
from tissue import ConfigError

SCRIPTED = "scripted"
RANDOM = "random"

Policy = Callable[[dict[str, Any]], Any]


def default_out(env_id: str) -> Path:
    """``probegym-out/evaluate/<env name>`` (the id without its ``probegym/``)."""
    from agents.outputs import default_output

    return default_output("evaluate", env_id.split("/")[-1])


def check_env_id(env_id: str) -> None:
    """A :class:`ConfigError` listing the valid ids unless ``env_id`` is one."""
    import envs

    if env_id not in envs.ENV_IDS:
        raise ConfigError(
            f"unknown environment {env_id!r}; expected one of {', '.join(envs.ENV_IDS)}"
        )


def check_counts(episodes: Any, seed: Any) -> None:
    """Episodes a whole number >= 1, the seed one >= 0 (gymnasium's seeds are)."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"--episodes must be a whole number >= 1; got {episodes!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"--seed must be a whole number >= 0; got {seed!r}")


def resolve_policy(
    env_id: str, policy: Any, env_kwargs: dict[str, Any] | None, seed: int = 0
) -> tuple[str, Callable[[], Policy], dict[str, Any]]:
    """The policy's label, a factory giving the policy for an episode, and the env's
    keyword arguments.

    ``"scripted"``: the task's scripted policy, a fresh one per episode. ``"random"``:
    uniform actions from one generator seeded with ``seed`` (the chance baseline). A path: a
    trained
    policy (:func:`agents.learning.train.load_policy`), its training env's kwargs the defaults that
    ``env_kwargs`` overrides; a different env id than the trained one is refused. A
    callable: used as it is (its ``reset()`` called before each episode, where it has one).
    """
    kwargs = dict(env_kwargs or {})
    if isinstance(policy, str) and policy == SCRIPTED:
        from agents.learning.policies import SCRIPTED_POLICIES

        scripted = SCRIPTED_POLICIES[env_id]
        return SCRIPTED, scripted, kwargs
    if isinstance(policy, str) and policy == RANDOM:
        from agents.learning.policies import RandomPolicy

        chance = RandomPolicy(seed)
        return RANDOM, lambda: chance, kwargs
    if isinstance(policy, (str, Path)):
        from agents.learning.train import TrainedPolicyError, load_policy

        try:
            trained = load_policy(policy)
        except TrainedPolicyError as error:
            raise ConfigError(
                f"--policy {policy}: {error}; or give --policy scripted for the task's "
                "scripted policy"
            ) from None
        trained_on = trained.config.get("env_id")
        if trained_on != env_id:
            raise ConfigError(
                f"--policy {policy} was trained on {trained_on!r}, not {env_id!r}"
                + _versions_differ(trained, str(trained_on), env_id, kwargs)
                + f"; evaluate it on {trained_on} (or give a model trained on {env_id})"
            )
        merged = dict(trained.config.get("env_kwargs") or {})
        merged.update(kwargs)
        return str(policy), lambda: trained, merged
    if callable(policy):
        return type(policy).__name__, lambda: policy, kwargs
    raise ConfigError(
        f"--policy must be 'scripted', 'random' or a trained model's path; got {policy!r}"
    )


def evaluate(
    env_id: str,
    policy: Any,
    episodes: int,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
    out: Path | str | None = None,
    *,
    command: str | None = None,
) -> list[dict[str, Any]]:
    """Run ``episodes`` episodes of ``env_id`` with ``policy``, episode k reset with seed
    ``seed + k``, and write ``episodes.json``, ``episodes.csv``, ``summary.json``,
    ``summary.md`` and the plots into ``out`` (default :func:`default_out`).

    Args:
        env_id: one of ``envs.ENV_IDS``.
        policy: ``"scripted"``, ``"random"``, a trained model's path (a ``probegym train``
            folder or a model ``.zip``), or a callable ``policy(observation) -> action``.
        episodes: how many episodes (>= 1).
        seed: the first episode's seed (>= 0).
        env_kwargs: keyword arguments of ``gymnasium.make`` (``contact``, ``mesh``,
            ``profile``, ``domain_randomization``, ...); for a trained policy they override
            its training configuration's.
        out: the output folder (created; refused if it is a file).
        command: the command that asked for the run, recorded in the summary.

    Returns:
        One record per episode (the CSV's columns, and ``series``: per-step forces, the
        lesion in the image, ForceScan's remaining path).
    """
    from agents.outputs import check_output_folder, exclusive_folder

    check_env_id(env_id)
    check_counts(episodes, seed)
    folder = check_output_folder(Path(out) if out is not None else default_out(env_id), "--out")
    label, make_policy, kwargs = resolve_policy(env_id, policy, env_kwargs, seed)

    import gymnasium as gym

    with exclusive_folder(folder, "probegym evaluate"):
        env = gym.make(env_id, **kwargs)
        try:
            records = [
                run_episode(env, make_policy(), index, seed + index) for index in range(episodes)
            ]
        finally:
            env.close()
        write_outputs(
            folder,
            records,
            env_id=env_id,
            policy=label,
            seed=seed,
            env_kwargs=kwargs,
            command=command,
        )
    return records


def run_episode(env: Any, policy: Policy, index: int, seed: int) -> dict[str, Any]:
    """One episode to its end (terminated, or truncated by the registration's step limit)."""
    reset = getattr(policy, "reset", None)
    if callable(reset):
        reset()
    observation, info = env.reset(seed=seed)
    contact: list[float] = []
    normal: list[float] = []
    lesion = [_lesion_point(observation)] if "lesion" in observation else None
    remaining = [_number(info.get("remaining_m"))] if "remaining_m" in info else None
    step_s: list[float] = []
    policy_s: list[float] = []
    total = 0.0
    terminated = truncated = False
    while not (terminated or truncated):
        started = time.perf_counter()
        action = policy(observation)
        acted = time.perf_counter()
        observation, reward, terminated, truncated, info = env.step(action)
        stepped = time.perf_counter()
        policy_s.append(acted - started)
        step_s.append(stepped - acted)
        total += float(reward)
        contact.append(float(info["contact_force_n"]))
        normal.append(_normal_force(env, info))
        if lesion is not None:
            lesion.append(_lesion_point(observation))
        if remaining is not None:
            remaining.append(_number(info.get("remaining_m")))
    tissue_info = info.get("tissue") or {}
    record: dict[str, Any] = {
        "episode": index,
        "seed": seed,
        "return": total,
        "success": bool(info.get("is_success", False)),
        "length": len(contact),
        "terminated": bool(terminated),
        "truncated": bool(truncated),
        "end": _end(info, terminated),
        "tissue_status": tissue_info.get("status"),
        "contact_force_mean_n": float(np.mean(contact)),
        "contact_force_peak_n": float(np.max(contact)),
        "normal_force_mean_n": float(np.mean(normal)),
        **_task_figures(info),
        "timing_step_ms_mean": 1e3 * float(np.mean(step_s)),
        "timing_step_ms_max": 1e3 * float(np.max(step_s)),
        "timing_policy_ms_mean": 1e3 * float(np.mean(policy_s)),
    }
    series: dict[str, Any] = {"contact_force_n": contact, "normal_force_n": normal}
    if lesion is not None:
        series["lesion"] = lesion
    if remaining is not None:
        series["remaining_m"] = remaining
    record["series"] = series
    return record


def _normal_force(env: Any, info: dict[str, Any]) -> float:
    """The step's normal contact force [N]: the task's ``info["normal_force_n"]``, else
    (BreastCompress) the env's own measure on its last tissue step: the simulated truth
    either way, never the (possibly noisy) wrench observation."""
    if "normal_force_n" in info:
        return float(info["normal_force_n"])
    base = env.unwrapped
    return float(base.normal_force_n(base.coupling.last_step))


def _lesion_point(observation: dict[str, Any]) -> list[float]:
    """The lesion in the image: [lateral, depth, visible] (zeros and 0 while not seen)."""
    lateral, depth, _, visible = (float(value) for value in observation["lesion"][:4])
    return [lateral, depth, 1.0 if visible >= 0.5 else 0.0]


def _number(value: Any) -> float | None:
    return None if value is None else float(value)


def _end(info: dict[str, Any], terminated: bool) -> str:
    """How the episode ended: success, a failure's name, or the step limit."""
    if info.get("is_success"):
        return "success"
    for failure in ("force_exceeded", "tissue_unstable", "robot_unstable"):
        if info.get(failure):
            return failure
    return "terminated" if terminated else "time_limit"


def _task_figures(info: dict[str, Any]) -> dict[str, Any]:
    """The centring error and the task's own end figures, from the last step's ``info``.

    LesionSearch: |lesion_lateral_m|. BreastCompress: |lesion_depth_m - target_depth_m|.
    ForceScan has no lesion target: centring is None; its own figures are the path left
    (``remaining_m``) and the good-step share at the end.
    """
    lateral = _number(info.get("lesion_lateral_m"))
    depth = _number(info.get("lesion_depth_m"))
    target = _number(info.get("target_depth_m"))
    centring = None
    if lateral is not None:
        centring = abs(lateral)
    elif depth is not None and target is not None:
        centring = abs(depth - target)
    return {
        "centring_error_m": centring,
        "lesion_lateral_end_m": lateral,
        "lesion_depth_end_m": depth,
        "target_depth_m": target,
        "remaining_end_m": _number(info.get("remaining_m")),
        "good_share_end": _number(info.get("good_share")),
    }


def without_timings(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The records less their ``timing_*`` fields: what must repeat for the same seed."""
    return [
        {key: value for key, value in record.items() if not key.startswith(TIMING_PREFIX)}
        for record in records
    ]


def _versions_differ(trained: Any, trained_on: str, env_id: str, env_kwargs: dict[str, Any]) -> str:
    """For a model of another version of ``env_id``'s task whose observation space differs
    from ``env_id``'s (v1 observes more than v0), a clause naming both; else nothing (other
    tasks are refused by their ids alone, before any environment is built)."""
    model = getattr(trained, "model", None)
    if model is None or trained_on.rsplit("-v", 1)[0] != env_id.rsplit("-v", 1)[0]:
        return ""
    return _spaces_differ(model.observation_space, env_id, env_kwargs)


def _spaces_differ(trained_space: Any, env_id: str, env_kwargs: dict[str, Any]) -> str:
    """A clause naming a model's observation space and ``env_id``'s where they differ."""
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids

    env = gym.make(env_id, **env_kwargs)
    try:
        wanted = env.observation_space
    finally:
        env.close()
    if wanted == trained_space:
        return ""
    return (
        f": the model observes {_describe_space(trained_space)}, {env_id} gives "
        f"{_describe_space(wanted)}"
    )


def _describe_space(space: Any) -> str:
    """A Dict space as ``{key (shape), ...}``; another as itself."""
    inner = getattr(space, "spaces", None)
    if not isinstance(inner, dict):
        return str(space)
    return "{" + ", ".join(f"{key} {tuple(box.shape)}" for key, box in inner.items()) + "}"
