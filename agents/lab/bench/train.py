"""``probegym bench train``: what a training run's environment step costs, by phase.

For each environment id and contact method (robust profile, the environments' default skin),
one environment in this process, records with a ``phase`` key:

- ``press``: the scripted press of ``probegym bench env`` (reset with seed 0, 40 steps pressing
  0.2 mm a step along the probe's axis, 60 sliding along the image's lateral axis), steps per
  second from the median CPU time of a step;
- ``exploring``: actions as a freshly initialised PPO policy draws them: Gaussian about SB3's
  initial mean (close to 0: its action layer starts with weights of gain 0.01) with the
  spread ``probegym train`` gives PPO on the task (``log_std_init`` of
  :mod:`agents.learning.train.hyperparameters`), clipped to the action box as SB3 clips them,
  episodes reset with seeds 1, 2, ... as they end. Timed over the steps whose tissue step
  starts with the probe in contact (``contact_share`` says how many that was), median
  CPU time, with the mean Newton iterations of the tissue's steps beside it.

- ``replay`` (where ``--model`` names a run trained on the id): the trained policy's own
  actions (deterministic, as ``probegym evaluate`` takes them) from episodes reset with seeds
  1, 2, ..., timed as ``exploring`` is: what a step costs once a policy has learnt the task.

- ``train`` (per algorithm of ``--algo``): ``probegym train``'s own code path
  (:func:`agents.learning.train.run.train`: ``n_envs`` worker processes, ``VecNormalize``, the
  callbacks) with the run's default hyper-parameters for a fixed number of steps (PPO: three
  updates' rollouts; SAC: :data:`SAC_STEPS`, two thirds of them with gradient steps), no
  evaluation falling inside it; environment steps per wall second of the learning loop, and
  the loop's parts (:mod:`agents.lab.bench.train_timing`: environment steps, transfer between
  processes, normalisation, policy inference, gradient updates), with ``n_envs`` and the
  machine's ``cores``.

- ``threads``: whether ``n_envs`` environments would step faster in threads of one process
  than one after another (the in-process vector environment's premise: the compiled
  kernels and PARDISO release the GIL): each environment takes :data:`THREAD_STEPS` exploring
  actions, first one environment after another in this thread, then each in its own thread,
  fresh environments reset with the same seeds; ``thread_speedup`` is the sequential wall
  time over the threaded one (``n_envs`` at best, 1 where the step holds the GIL).

The ``press``, ``exploring`` and ``replay`` environments live side by side and step in turn,
in proportion to their planned steps (:func:`phase_records`): a shared machine's speed
drifts by up to 1.5 x within minutes (docs/speed.md), and phases timed one after another
took that drift into their ratio.

``exploring_over_press`` is the ratio the training-speed work aims to raise to 0.85;
``train_over_press`` the end-to-end rate over (environments that have a core each x the
press's rate), which it aims to raise to 0.75 for PPO.

"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.bench.contact import threading_environment
from agents.lab.bench.env import scripted_press
from agents.lab.bench.report import BenchRecord, MarkdownTable, write_records
from agents.lab.bench.timed_runs import TimedRun, interleave, replaying, run_alone, timed_steps
from tissue import ConfigError

#: The task users train now (v2: 3 mm a step at full action, sized to its 1 mm band as the
#: teaching versions are; v0 and v1 move 5 mm, and their exploring steps cost more Newton
#: iterations for it: ``--ids`` measures them).
DEFAULT_IDS = ("probegym/BreastCompress-v2",)
DEFAULT_METHODS = ("lm",)
DEFAULT_LEVEL = 1363
#: Exploring steps drawn per record (episodes reset as they end).
EXPLORING_STEPS = 300
#: The ratio of the exploring step's rate to the press's that the training-speed work aims at.
TARGET_EXPLORING_OVER_PRESS = 0.85
#: PPO's end-to-end rate over (environments with a core each x the press's rate) aimed at.
TARGET_TRAIN_OVER_PRESS = 0.75
DEFAULT_ALGOS = ("ppo", "sac")
DEFAULT_N_ENVS = 2
#: PPO's updates in the ``train`` phase (each after n_steps x n_envs environment steps).
PPO_UPDATES = 3
#: SAC's steps in the ``train`` phase: its first 1,000 (``learning_starts``) take no gradient
#: step, the rest one each.
SAC_STEPS = 3_000
#: Exploring actions per environment in the ``threads`` phase.
THREAD_STEPS = 100


def exploring_spread(env_id: str | None = None) -> float:
    """The standard deviation of a fresh PPO policy's actions under ``probegym train``."""
    from agents.learning.train.hyperparameters import default_hyperparameters

    policy_kwargs = default_hyperparameters("ppo", env_id).get("policy_kwargs", {})
    return float(np.exp(policy_kwargs.get("log_std_init", 0.0)))


def _make(env_id: str, contact: str, level: int) -> Any:
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids

    return gym.make(env_id, contact=contact, mesh=level, profile="robust")


def _identity(env: Any, env_id: str, contact: str, level: int, phase: str) -> dict[str, Any]:
    unwrapped = env.unwrapped
    return {
        "phase": phase,
        "env_id": env_id,
        "contact": contact,
        "profile": unwrapped.tissue.spec.profile,
        "level": level,
        "tets": int(unwrapped.tissue.tets.shape[0]),
        "collision_edge_m": unwrapped.tissue.spec.collision_edge_m,
    }


def press_record(env_id: str, contact: str, level: int) -> dict[str, Any]:
    """The ``press`` phase (see the module docstring): every step timed, as ``bench env``."""
    return run_alone(_press_run(env_id, contact, level))


def exploring_record(
    env_id: str, contact: str, level: int, steps: int = EXPLORING_STEPS, seed: int = 0
) -> dict[str, Any]:
    """The ``exploring`` phase (see the module docstring): the steps in contact timed."""
    return run_alone(_exploring_run(env_id, contact, level, steps, seed))


def phase_records(
    env_id: str, contact: str, level: int, policy: Any = None, steps: int = EXPLORING_STEPS
) -> list[dict[str, Any]]:
    """The ``press``, ``exploring`` and (given a trained ``policy``) ``replay`` records, their
    environments stepped in turn (:func:`~agents.lab.bench.timed_runs.interleave`), so that
    the ratios between them hold on a machine whose speed drifts while they run."""
    runs = [_press_run(env_id, contact, level), _exploring_run(env_id, contact, level, steps)]
    if policy is not None:
        runs.append(_replay_run(env_id, contact, level, policy, steps))
    return interleave(runs)


def _press_run(env_id: str, contact: str, level: int) -> TimedRun:
    env = _make(env_id, contact, level)
    observation, _ = env.reset(seed=0)
    record = _identity(env, env_id, contact, level, "press")
    actions = scripted_press(env.unwrapped)
    timed = yield from timed_steps(
        env, replaying(actions), observation, len(actions), contact_only=False
    )
    env.close()
    return record | timed


def _exploring_run(
    env_id: str, contact: str, level: int, steps: int = EXPLORING_STEPS, seed: int = 0
) -> TimedRun:
    env = _make(env_id, contact, level)
    low, high = env.action_space.low, env.action_space.high
    draws = replaying(_exploring_actions(low.shape, low, high, seed, steps, env_id))
    observation, _ = env.reset(seed=1)
    record = _identity(env, env_id, contact, level, "exploring")
    record |= yield from timed_steps(env, draws, observation, steps, contact_only=True, next_seed=2)
    env.close()
    record["action_std"] = exploring_spread(env_id)
    return record


def load_replayed_policy(model: Path, env_ids: list[str]) -> Any:
    """The trained policy of ``model`` (a ``probegym train`` folder or a model .zip in one),
    checked to have been trained on one of ``env_ids``.

    Raises:
        ConfigError: the model cannot be loaded, or was trained on another id.
    """
    from agents.learning.train import TrainedPolicyError, load_policy
    from agents.learning.train.artifacts import read_config, training_folder

    try:
        trained_on = read_config(training_folder(model)[0]).get("env_id")
        if trained_on not in env_ids:
            raise ConfigError(
                f"--model {model} was trained on {trained_on!r}, which --ids does not name "
                f"({', '.join(env_ids)}); add it to --ids or give a model trained on one of them"
            )
        trained = load_policy(model)
    except TrainedPolicyError as error:
        raise ConfigError(f"--model {model}: {error}") from None
    return trained


def replay_record(
    env_id: str, contact: str, level: int, policy: Any, steps: int = EXPLORING_STEPS
) -> dict[str, Any]:
    """The ``replay`` phase (see the module docstring): ``policy``'s own actions for
    ``steps`` steps, the steps in contact timed."""
    return run_alone(_replay_run(env_id, contact, level, policy, steps))


def _replay_run(
    env_id: str, contact: str, level: int, policy: Any, steps: int = EXPLORING_STEPS
) -> TimedRun:
    env = _make(env_id, contact, level)
    observation, _ = env.reset(seed=1)
    record = _identity(env, env_id, contact, level, "replay")
    budget = iter(range(steps))

    def act(seen: dict[str, Any]) -> np.ndarray | None:
        return None if next(budget, None) is None else policy(seen)

    record |= yield from timed_steps(env, act, observation, steps, contact_only=True, next_seed=2)
    env.close()
    return record


def _exploring_actions(
    shape: tuple[int, ...], low: Any, high: Any, seed: int, steps: int, env_id: str
) -> list[np.ndarray]:
    """``steps`` actions as a fresh PPO policy draws them on ``env_id`` (see the module
    docstring)."""
    rng = np.random.default_rng(seed)
    spread = exploring_spread(env_id)
    return [
        np.clip(spread * rng.standard_normal(shape), low, high).astype(np.float32)
        for _ in range(steps)
    ]


def threads_record(
    env_id: str, contact: str, level: int, n_envs: int, steps: int = THREAD_STEPS
) -> dict[str, Any]:
    """The ``threads`` phase (see the module docstring)."""
    import threading

    def run(env: Any, index: int) -> None:
        for action in _exploring_actions(shape, low, high, index, steps, env_id):
            _, _, terminated, truncated, _ = env.step(action)
            if terminated or truncated:
                env.reset()

    def fresh() -> list[Any]:
        """The environments, reset and stepped once (warm) before a clock starts."""
        built = [_make(env_id, contact, level) for _ in range(n_envs)]
        for index, env in enumerate(built):
            env.reset(seed=1 + index)
            env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        return built

    envs = fresh()
    low, high = envs[0].action_space.low, envs[0].action_space.high
    shape = low.shape
    record = _identity(envs[0], env_id, contact, level, "threads")
    tic = time.perf_counter()
    for index, env in enumerate(envs):
        run(env, index)
    sequential = time.perf_counter() - tic
    for env in envs:
        env.close()
    envs = fresh()
    workers = [threading.Thread(target=run, args=(env, i)) for i, env in enumerate(envs)]
    tic = time.perf_counter()
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    threaded = time.perf_counter() - tic
    for env in envs:
        env.close()
    return record | {
        "n_envs": n_envs,
        "cores": os.cpu_count(),
        "steps_per_env": steps,
        "sequential_s": sequential,
        "threaded_s": threaded,
        "thread_speedup": sequential / threaded,
        "load_average": list(os.getloadavg()),
    }


def _ppo_rollout(env_id: str, n_envs: int) -> int:
    """Environment steps in one of ``probegym train``'s PPO updates on ``env_id``."""
    from agents.learning.train.hyperparameters import default_hyperparameters

    return int(default_hyperparameters("ppo", env_id)["n_steps"]) * n_envs


def train_steps(algo: str, n_envs: int, env_id: str | None = None) -> int:
    """The ``train`` phase's default steps for ``algo`` (see the module docstring)."""
    if algo == "ppo":
        return PPO_UPDATES * _ppo_rollout(env_id or DEFAULT_IDS[0], n_envs)
    return SAC_STEPS


def train_record(
    env_id: str, contact: str, level: int, algo: str, n_envs: int, steps: int | None = None
) -> dict[str, Any]:
    """The ``train`` phase (see the module docstring) for one algorithm."""
    from agents.lab.bench.train_timing import TrainTiming
    from agents.learning.train.run import TrainSettings, train

    steps = steps or train_steps(algo, n_envs, env_id)
    # No evaluation inside the timed loop: PPO collects whole rollouts past the budget.
    rollout = _ppo_rollout(env_id, n_envs)
    quiet = 10 * max(steps, rollout)
    timing = TrainTiming()
    with tempfile.TemporaryDirectory(prefix="probegym-bench-train-") as out:
        settings = TrainSettings(
            env_id=env_id,
            out=Path(out),
            algo=algo,
            env_kwargs={"contact": contact, "mesh": level, "profile": "robust"},
            steps=steps,
            n_envs=n_envs,
            seed=0,
            eval_every=quiet,
            checkpoint_every=quiet,
            progress=False,
        )
        train(settings, log=lambda _: None, timing=timing)
    parts = timing.parts()
    loop_s = parts.pop("loop_s")
    vector_steps = int(parts.pop("vector_steps"))
    trained = vector_steps * n_envs
    probe = _make(env_id, contact, level)
    record = _identity(probe, env_id, contact, level, "train")
    probe.close()
    record |= {
        "algo": algo,
        "n_envs": n_envs,
        "cores": os.cpu_count(),
        "steps": trained,
        "loop_s": loop_s,
        "steps_per_s": trained / loop_s if loop_s > 0 else None,
        "parts_s": parts,
        "load_average": list(os.getloadavg()),
    }
    return record


def run_train_benchmark(
    env_ids: list[str] | None,
    methods: list[str] | None,
    level: int,
    json_path: Path,
    command: str | None = None,
    algos: list[str] | None = None,
    n_envs: int = DEFAULT_N_ENVS,
    steps: int | None = None,
    model: Path | None = None,
) -> list[dict[str, Any]]:
    """The phases for every id and method (``train`` for each of ``algos``; ``[]``: none);
    prints the tables and writes the JSON as it goes. ``steps``: the ``train`` phase's
    environment steps (default :func:`train_steps`); ``model``: a trained run whose policy
    the ``replay`` phase steps, on the id it was trained on (refused before any work when
    ``env_ids`` does not name it)."""
    ids = list(env_ids or DEFAULT_IDS)
    replayed = None if model is None else load_replayed_policy(model, ids)
    records: list[dict[str, Any]] = []
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    provenance = BenchRecord("probegym bench train: a training step's cost, by phase", command)
    for env_id in ids:
        for contact in methods or DEFAULT_METHODS:
            replaying = replayed is not None and replayed.config.get("env_id") == env_id
            phases = phase_records(env_id, contact, level, replayed if replaying else None)
            press = phases[0]
            for record in phases[1:]:
                _judge_phase(record, press)
                if record["phase"] == "replay":
                    record["model"] = str(model)
            for record in phases:
                records.append(record)
                _print(record)
            write_records(json_path, "train", started, records, threads=threading_environment())
            if n_envs > 1:
                threads = threads_record(env_id, contact, level, n_envs)
                records.append(threads)
                _print_threads(threads)
            for algo in DEFAULT_ALGOS if algos is None else algos:
                record = train_record(env_id, contact, level, algo, n_envs, steps)
                _judge_train(record, press)
                records.append(record)
                _print_train(record)
                write_records(json_path, "train", started, records, threads=threading_environment())
    provenance.write(json_path, [_table(records), _threads_table(records), _train_table(records)])
    return records


def _judge_phase(record: dict[str, Any], press: dict[str, Any]) -> None:
    """``<phase>_over_press``: an ``exploring`` or ``replay`` record's rate over the press's,
    judged against :data:`TARGET_EXPLORING_OVER_PRESS` (the training-speed work's aim for
    any step a learner takes)."""
    if not (press["steps_per_s"] and record["steps_per_s"]):
        return
    ratio = record["steps_per_s"] / press["steps_per_s"]
    record[f"{record['phase']}_over_press"] = ratio
    record[f"target_{record['phase']}_over_press"] = TARGET_EXPLORING_OVER_PRESS
    record["meets_target"] = ratio >= TARGET_EXPLORING_OVER_PRESS


def _judge_train(record: dict[str, Any], press: dict[str, Any]) -> None:
    """``train_over_press``: the end-to-end rate over (environments with a core each x the
    press's rate); PPO's verdict against :data:`TARGET_TRAIN_OVER_PRESS`."""
    rate, press_rate = record["steps_per_s"], press["steps_per_s"]
    if not (rate and press_rate):
        return
    parallel = min(record["n_envs"], record["cores"] or 1)
    record["press_steps_per_s"] = press_rate
    record["train_over_press"] = rate / (parallel * press_rate)
    if record["algo"] == "ppo":
        record["target_train_over_press"] = TARGET_TRAIN_OVER_PRESS
        record["meets_target"] = record["train_over_press"] >= TARGET_TRAIN_OVER_PRESS


#: The ``train`` record's parts, in the table's order: (key in ``parts_s``, column).
_PARTS = (
    ("env_s", "env steps"),
    ("transfer_s", "transfer"),
    ("normalisation_s", "normalisation"),
    ("inference_s", "inference"),
    ("updates_s", "updates"),
)


def _train_table(records: list[dict[str, Any]]) -> MarkdownTable:
    table = MarkdownTable(
        "probegym train end to end: environment steps per wall second of the learning loop, "
        "and the loop's parts (share of its wall time)",
        ["env", "contact", "level (tets)", "algo", "n_envs / cores", "steps", "steps/s",
         *(column for _, column in _PARTS), "tissue (of env steps)",
         "over n_envs x press (PPO target 0.75)"],
    )  # fmt: skip
    for r in records:
        if r["phase"] != "train":
            continue
        parts, loop = r["parts_s"], r["loop_s"]
        ratio = r.get("train_over_press")
        verdict = "" if ratio is None else f"{ratio:.2f}"
        if "meets_target" in r:
            verdict += f" ({'met' if r['meets_target'] else 'missed'})"
        env_s = parts["env_s"]
        table.rows.append([
            r["env_id"], r["contact"], f"{r['level']} ({r['tets']:,})", r["algo"],
            f"{r['n_envs']} / {r['cores']}", f"{r['steps']:,}",
            "-" if r["steps_per_s"] is None else f"{r['steps_per_s']:.0f}",
            *(f"{100 * parts[key] / loop:.0f} %" for key, _ in _PARTS),
            f"{100 * parts['env_tissue_s'] / env_s:.0f} %" if env_s > 0 else "-", verdict,
        ])  # fmt: skip
    return table


def _threads_table(records: list[dict[str, Any]]) -> MarkdownTable:
    table = MarkdownTable(
        "environments in threads of one process against one after another (exploring "
        "actions, wall time)",
        ["env", "contact", "level (tets)", "n_envs / cores", "steps each", "one after another",
         "in threads", "speedup (n_envs at best)"],
    )  # fmt: skip
    for r in records:
        if r["phase"] != "threads":
            continue
        table.rows.append([
            r["env_id"], r["contact"], f"{r['level']} ({r['tets']:,})",
            f"{r['n_envs']} / {r['cores']}", str(r["steps_per_env"]),
            f"{r['sequential_s']:.2f} s", f"{r['threaded_s']:.2f} s",
            f"{r['thread_speedup']:.2f}",
        ])  # fmt: skip
    return table


def _print_threads(record: dict[str, Any]) -> None:
    print(
        f"{record['env_id']} {record['contact']} level {record['level']} threads: "
        f"{record['n_envs']} envs one after another {record['sequential_s']:.2f} s, in threads "
        f"{record['threaded_s']:.2f} s, speedup {record['thread_speedup']:.2f}",
        flush=True,
    )


def _print_train(record: dict[str, Any]) -> None:
    parts, loop = record["parts_s"], record["loop_s"]
    shares = ", ".join(f"{column} {100 * parts[key] / loop:.0f} %" for key, column in _PARTS)
    ratio = record.get("train_over_press")
    print(
        f"{record['env_id']} {record['contact']} level {record['level']} train "
        f"{record['algo']} ({record['n_envs']} envs): {record['steps']:,} steps in {loop:.0f} s, "
        f"{record['steps_per_s']:.0f} steps/s ({shares})"
        + ("" if ratio is None else f"; over n_envs x press {ratio:.2f}"),
        flush=True,
    )


def _table(records: list[dict[str, Any]]) -> MarkdownTable:
    table = MarkdownTable(
        "one environment's steps per second by phase (median CPU time), robust profile",
        ["env", "contact", "level (tets)", "skin edge (mm)", "phase", "steps/s",
         "Newton iterations", "steps timed", "in contact", "over press (target 0.85)"],
    )  # fmt: skip
    for r in records:
        if r["phase"] not in ("press", "exploring", "replay"):
            continue
        edge = r["collision_edge_m"]
        ratio = r.get(f"{r['phase']}_over_press")
        verdict = (
            "" if ratio is None else f"{ratio:.2f} ({'met' if r['meets_target'] else 'missed'})"
        )
        rate = r["steps_per_s"]
        table.rows.append([
            r["env_id"], r["contact"], f"{r['level']} ({r['tets']:,})",
            "paper" if edge is None else f"{edge * 1e3:g}", r["phase"],
            "-" if rate is None else f"{rate:.0f}",
            f"{r.get('newton_iterations_mean', 0.0):.2f}",
            str(r["steps_timed"]), f"{r['contact_share'] * 100:.0f} %", verdict,
        ])  # fmt: skip
    return table


def _print(record: dict[str, Any]) -> None:
    rate = record["steps_per_s"]
    ratio = record.get(f"{record['phase']}_over_press")
    print(
        f"{record['env_id']} {record['contact']} level {record['level']} {record['phase']:9s}: "
        + ("no step timed" if rate is None else f"{rate:6.0f} steps/s")
        + f", {record.get('newton_iterations_mean', 0.0):.2f} Newton iterations, "
        f"{record['steps_timed']} steps timed, {record['contact_share'] * 100:.0f} % in contact"
        + ("" if ratio is None else f"; {record['phase']} / press {ratio:.2f}"),
        flush=True,
    )
