"""``probegym train``: stable-baselines3 on a probegym environment, resumable.

One run: ``n_envs`` environments in worker processes (SB3's ``SubprocVecEnv``, started with
``forkserver``: numba's OpenMP layer makes ``fork`` fatal once a tissue is built; one env runs
in-process), each under a ``Monitor`` (its CSV in ``monitor/``, success included), the
observations normalised (``VecNormalize``, the image left alone) unless asked otherwise, an
evaluation every ``eval_every`` steps on its own envs and seeds, ``n_envs`` workers like the
training's (SB3's ``EvalCallback``: mean return and success rate, ``eval/evaluations.npz``,
the best model), checkpoints with their normalisation statistics every ``checkpoint_every``
steps, TensorBoard event files in ``tb/`` and a progress bar. ``config.json`` records
everything the run was made from (see :mod:`agents.learning.train.artifacts` for the
folder's layout).

Rerun with the same ``--out`` and it resumes from the latest checkpoint (a different
configuration in that folder is refused: choose another folder). Before the workers start,
the environment is built and stepped once in this process, so that the compiled kernels,
the phantom mesh and PBD's calibration are on disk and each worker loads them (each would
otherwise compile for about 20 s).
"""

from __future__ import annotations

import json
import platform
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from agents.learning.train.artifacts import (
    BEST_NORMALIZE_FILE,
    CHECKPOINT_PREFIX,
    CHECKPOINTS,
    CONFIG_FILE,
    MODEL_FILE,
    NORMALIZE_FILE,
    checkpoint_normalization,
    latest_checkpoint,
    normalization_of,
    read_config,
    training_folder,
)
from agents.learning.train.hyperparameters import default_hyperparameters
from agents.learning.train.workers import (
    PIPE_ERRORS,
    WorkerDiedError,
    dead_worker_report,
    dead_workers,
    stop_workers,
)
from agents.outputs import write_json
from tissue import ConfigError

#: Algorithms ``--algo`` takes.
ALGORITHMS = ("ppo", "sac")


class TrainError(ConfigError):
    """A training request that cannot run: the message names the value and the fix."""


def _check_hyperparameters(algorithm: Any, settings: TrainSettings) -> None:
    """Refuse a hyper-parameter the algorithm does not take, naming the ones it does."""
    import inspect

    own = {"self", "policy", "env", "seed", "device", "verbose", "tensorboard_log"}
    accepted = {
        name for name in inspect.signature(algorithm.__init__).parameters
        if name not in own and not name.startswith("_")
    }  # fmt: skip
    unknown = sorted(set(settings.hyperparameters) - accepted)
    if unknown:
        raise TrainError(
            f"--hyperparameters: {settings.algo} takes no {', '.join(map(repr, unknown))}; "
            f"it takes {', '.join(sorted(accepted))} (probegym train sets seed, device, "
            "verbose and tensorboard_log itself)"
        )


@dataclass(frozen=True)
class TrainSettings:
    """One training run.

    Attributes:
        env_id: a registered probegym environment.
        out: the run's folder.
        algo: ``ppo`` or ``sac``.
        env_kwargs: keyword arguments of ``gymnasium.make`` (contact, mesh, profile, ...).
        steps: environment steps to train for, in all envs together.
        n_envs: environments stepping in parallel (worker processes when > 1).
        seed: seeds the algorithm and the training envs (env i: seed + i); evaluation uses
            seeds from seed + 10,000.
        eval_every: environment steps between evaluations.
        eval_episodes: episodes per evaluation.
        checkpoint_every: environment steps between checkpoints.
        normalize: normalise observations (running mean and variance, the image excepted)
            and, for PPO's training, rewards (by the running spread of the discounted return:
            a failure's large penalty then does not swamp the value function); evaluations
            report raw returns.
        hyperparameters: this run's own, over the task's defaults
            (:mod:`agents.learning.train.hyperparameters`); checked against the algorithm's
            keyword arguments before any environment is built.
        progress: show a progress bar.
        init_from: start from a trained model instead of a new one (a ``probegym train``
            folder or a model ``.zip`` in one, with its normalisation statistics): the
            next stage of a curriculum. Same env id, algorithm and normalisation; its own
            hyper-parameters are kept.
        pretrain_episodes: before training a new PPO model, clone the task's scripted
            policy from this many of its episodes (:mod:`agents.learning.train.imitation`; seeds
            from seed + 20,000); 0: none. Written to ``pretrain.json``.
    """

    env_id: str
    out: Path
    algo: str = "ppo"
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    steps: int = 300_000
    n_envs: int = 2
    seed: int = 0
    eval_every: int = 10_000
    eval_episodes: int = 20
    checkpoint_every: int = 20_000
    normalize: bool = True
    hyperparameters: dict[str, Any] = field(default_factory=dict)
    progress: bool = True
    init_from: Path | None = None
    pretrain_episodes: int = 0

    def __post_init__(self) -> None:
        import envs

        if self.env_id not in envs.ENV_IDS:
            raise TrainError(
                f"unknown environment {self.env_id!r}; choose one of {', '.join(envs.ENV_IDS)}"
            )
        if self.algo not in ALGORITHMS:
            raise TrainError(f"unknown --algo {self.algo!r}; choose one of {', '.join(ALGORITHMS)}")
        for name in ("steps", "n_envs", "eval_every", "eval_episodes", "checkpoint_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise TrainError(f"{name} must be a whole number >= 1; got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise TrainError(f"seed must be a whole number >= 0; got {self.seed!r}")
        episodes = self.pretrain_episodes
        if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 0:
            raise TrainError(
                f"--pretrain-scripted must be a whole number of episodes >= 0; got {episodes!r}"
            )
        if episodes and self.algo != "ppo":
            raise TrainError(
                f"--pretrain-scripted clones into PPO's Gaussian policy; got --algo {self.algo}: "
                "use --algo ppo or drop --pretrain-scripted"
            )
        if episodes and self.init_from is not None:
            raise TrainError(
                "--pretrain-scripted starts a new model and --init-from a trained one; give one"
            )
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise TrainError(f"--out {self.out} is a file; give a folder")
        if not isinstance(self.hyperparameters, dict):
            raise TrainError(
                f"--hyperparameters must be a JSON object of SB3 keyword arguments; got "
                f"{self.hyperparameters!r}"
            )

    def resolved_hyperparameters(self) -> dict[str, Any]:
        """The algorithm's hyper-parameters: the task's defaults, then this run's."""
        merged = default_hyperparameters(self.algo, self.env_id)
        merged.update(self.hyperparameters)
        if self.algo == "ppo":
            # A minibatch no larger than one update's rollout.
            rollout = int(merged["n_steps"]) * self.n_envs
            merged["batch_size"] = min(int(merged["batch_size"]), rollout)
        return merged

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the folder's (the step budget may grow)."""
        identity = {
            "env_id": self.env_id,
            "algo": self.algo,
            "env_kwargs": _plain(self.env_kwargs),
            "n_envs": self.n_envs,
            "seed": self.seed,
            "normalize": self.normalize,
            "hyperparameters": _plain(self.resolved_hyperparameters()),
        }
        if self.init_from is not None:
            identity["init_from"] = str(self.init_from)
        if self.pretrain_episodes:
            identity["pretrain_episodes"] = self.pretrain_episodes
        return identity


def train(
    settings: TrainSettings, command: str | None = None, log: Any = print, timing: Any = None
) -> Path:
    """Train (or resume) and save; returns the final model's path.

    ``timing``: a benchmark's clocks (:class:`agents.lab.bench.train_timing.TrainTiming`): each
    worker's env wrapped in its ``env_wrapper``, the vector env in its ``inner`` (below the
    normalisation) and ``outer`` (above it) wrappers, the evaluation's in its ``mirror`` at
    both places, its ``callback`` added; None: none."""
    import torch
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecNormalize

    # One thread for the networks: the env workers have the cores, and the same updates
    # come out in any process (a Ray worker, here) whatever its thread count.
    torch.set_num_threads(1)
    _check_hyperparameters({"ppo": PPO, "sac": SAC}[settings.algo], settings)
    out = Path(settings.out)
    out.mkdir(parents=True, exist_ok=True)
    previous = _previous_identity(out)
    if previous is not None and previous != settings.identity():
        changed = sorted(k for k in previous if previous[k] != settings.identity().get(k))
        raise TrainError(
            f"{out} holds a run with other settings ({', '.join(changed)} differ): resume it "
            "with the same options, or choose another --out"
        )
    resume = latest_checkpoint(out)
    final = out / MODEL_FILE
    if resume is not None and resume[1] >= settings.steps and final.is_file():
        log(f"{out} already holds a model trained for {resume[1]:,} steps; nothing to do")
        return final

    # The env once in this process: kernels compiled and mesh / calibration cached on disk
    # before any worker starts.
    eval_env = make_vec_env(
        f"envs:{settings.env_id}",
        n_envs=1,
        seed=settings.seed + 10_000,
        env_kwargs=settings.env_kwargs,
        vec_env_cls=DummyVecEnv,
    )
    eval_env.reset()
    eval_env.step(np.zeros((1, 6), dtype=np.float32))
    vec_cls = SubprocVecEnv if settings.n_envs > 1 else DummyVecEnv
    vec_kwargs = {"start_method": "forkserver"} if settings.n_envs > 1 else None
    if settings.n_envs > 1:
        # The evaluations on as many workers as the training (env i: seed + 10,000 + i; SB3
        # shares the episodes among them): the training's workers wait while it runs, and
        # on one env in this process it took one core of n.
        eval_env.close()
        eval_env = make_vec_env(
            f"envs:{settings.env_id}",
            n_envs=settings.n_envs,
            seed=settings.seed + 10_000,
            env_kwargs=settings.env_kwargs,
            vec_env_cls=vec_cls,
            vec_env_kwargs=vec_kwargs,
        )
    venv = make_vec_env(
        f"envs:{settings.env_id}",
        n_envs=settings.n_envs,
        seed=settings.seed,
        env_kwargs=settings.env_kwargs,
        monitor_dir=str(out / "monitor"),
        monitor_kwargs={"info_keywords": ("is_success",)},
        wrapper_class=None if timing is None else timing.env_wrapper,
        vec_env_cls=vec_cls,
        vec_env_kwargs=vec_kwargs,
    )
    if timing is not None:
        venv = timing.inner(venv)
        eval_env = timing.mirror(eval_env)
    start = None if resume is not None else _starting_model(settings)
    if settings.normalize:
        keys = [k for k in venv.observation_space.spaces if k != "image"]  # type: ignore[attr-defined]
        if resume is not None:
            venv = VecNormalize.load(str(checkpoint_normalization(out, resume[1])), venv)
        elif start is not None and start[1] is not None:
            venv = VecNormalize.load(str(start[1]), venv)  # the statistics learn on
            venv.training = True
        else:
            # Rewards too for PPO (on-policy); SAC's replay buffer would keep stale scales.
            on_policy = settings.algo == "ppo"
            venv = VecNormalize(venv, norm_obs=True, norm_reward=on_policy, norm_obs_keys=keys)
        eval_env = VecNormalize(
            eval_env, norm_obs=True, norm_reward=False, norm_obs_keys=keys, training=False
        )
    if timing is not None:
        venv = timing.outer(venv)
        eval_env = timing.mirror(eval_env)
    algorithm: Any = {"ppo": PPO, "sac": SAC}[settings.algo]
    hyper = settings.resolved_hyperparameters()
    if resume is not None:
        log(f"resuming {out} from its checkpoint at {resume[1]:,} steps")
        model = algorithm.load(resume[0], env=venv, device="cpu", tensorboard_log=str(out / "tb"))
    elif start is not None:
        log(f"starting from {start[0]}")
        model = algorithm.load(start[0], env=venv, device="cpu", tensorboard_log=str(out / "tb"))
        model.set_random_seed(settings.seed)
    else:
        model = algorithm(
            "MultiInputPolicy",
            venv,
            seed=settings.seed,
            device="cpu",
            verbose=0,
            tensorboard_log=str(out / "tb"),
            **hyper,
        )
        if settings.pretrain_episodes:
            _pretrain(model, venv if settings.normalize else None, settings, out, log)
    _write_config(out, settings, command)
    per_env = max(1, settings.n_envs)
    callbacks = CallbackList(
        [
            CheckpointCallback(
                save_freq=max(1, settings.checkpoint_every // per_env),
                save_path=str(out / CHECKPOINTS),
                name_prefix=CHECKPOINT_PREFIX,
                save_vecnormalize=settings.normalize,
            ),
            EvalCallback(
                eval_env,
                n_eval_episodes=settings.eval_episodes,
                eval_freq=max(1, settings.eval_every // per_env),
                log_path=str(out / "eval"),
                best_model_save_path=str(out / "eval"),
                callback_on_new_best=_best_normalization_saver(out) if settings.normalize else None,
                deterministic=True,
                verbose=0,
            ),
            *([] if timing is None else [timing.callback]),
        ]
    )
    if resume is not None:
        log_file = out / "eval" / "evaluations.npz"
        _continue_evaluation_log(callbacks.callbacks[1], log_file, resume[1])
    remaining = settings.steps - (0 if resume is None else resume[1])
    started = time.perf_counter()
    try:
        model.learn(
            total_timesteps=remaining,
            callback=callbacks,
            progress_bar=settings.progress and _progress_bar_available(),
            reset_num_timesteps=resume is None,
            tb_log_name=settings.algo,
        )
    except PIPE_ERRORS as error:
        dead = dead_workers(venv) or dead_workers(eval_env)
        if not dead:
            raise
        stop_workers(venv, eval_env)
        kept = latest_checkpoint(out)
        raise WorkerDiedError(
            dead_worker_report(dead, settings.seed, out, None if kept is None else kept[1])
        ) from error
    model.save(final)
    if settings.normalize:
        venv.save(str(out / NORMALIZE_FILE))  # type: ignore[attr-defined]
    # The last checkpoint too, so that a rerun knows the budget was reached.
    model.save(out / CHECKPOINTS / f"{CHECKPOINT_PREFIX}_{model.num_timesteps}_steps.zip")
    if settings.normalize:
        stats = checkpoint_normalization(out, model.num_timesteps)
        venv.save(str(stats))  # type: ignore[attr-defined]
    venv.close()
    eval_env.close()
    log(
        f"trained {settings.env_id} with {settings.algo} for {model.num_timesteps:,} steps in "
        f"{time.perf_counter() - started:.0f} s: {final}"
    )
    return final


def _pretrain(
    model: Any, normalization: Any | None, settings: TrainSettings, out: Path, log: Any
) -> None:
    """Clone the scripted policy into the new ``model``; ``pretrain.json`` says how."""
    from agents.learning.train.imitation import clone_into, scripted_demonstrations

    started = time.perf_counter()
    demonstrations = scripted_demonstrations(
        settings.env_id, settings.env_kwargs, settings.pretrain_episodes, settings.seed + 20_000
    )
    losses = clone_into(model, demonstrations, normalization, seed=settings.seed)
    record = {
        "episodes": demonstrations.episodes,
        "successes": demonstrations.successes,
        "samples": demonstrations.samples,
        "epochs": len(losses),
        "first_epoch_mse": losses[0],
        "last_epoch_mse": losses[-1],
        "wall_s": time.perf_counter() - started,
    }
    (out / "pretrain.json").write_text(json.dumps(record, indent=2) + "\n")
    log(
        f"cloned the scripted policy from {demonstrations.episodes} episodes "
        f"({demonstrations.successes} succeeded, {demonstrations.samples} steps): action MSE "
        f"{losses[0]:.4f} -> {losses[-1]:.4f}"
    )


def _starting_model(settings: TrainSettings) -> tuple[Path, Path | None] | None:
    """``init_from``'s model and normalisation statistics (None without ``init_from``).

    Raises:
        TrainError: it names another environment, algorithm or normalisation.
    """
    if settings.init_from is None:
        return None
    folder, model_path = training_folder(settings.init_from)
    config = read_config(folder)
    theirs = (config.get("env_id"), config.get("algo"), bool(config.get("normalize")))
    ours = (settings.env_id, settings.algo, settings.normalize)
    if theirs != ours:
        raise TrainError(
            f"--init-from {settings.init_from}: that run trained {theirs[0]} with {theirs[1]} "
            f"(normalised: {theirs[2]}); this one is {ours[0]} with {ours[1]} (normalised: "
            f"{ours[2]}): start from a run of the same env, algorithm and normalisation"
        )
    return model_path, normalization_of(folder, model_path, config)


def _best_normalization_saver(out: Path) -> Any:
    """A callback saving the normalisation statistics beside ``eval/best_model.zip`` each time
    the evaluation finds a new best (the model is useless without the statistics it saw)."""
    from stable_baselines3.common.callbacks import BaseCallback

    class SaveNormalization(BaseCallback):
        def _on_step(self) -> bool:
            normalizer = self.model.get_vec_normalize_env()
            if normalizer is not None:
                normalizer.save(str(out / "eval" / BEST_NORMALIZE_FILE))
            return True

    return SaveNormalization()


def _continue_evaluation_log(callback: Any, log: Path, up_to: int) -> None:
    """Give a resumed run's EvalCallback the evaluations made up to its checkpoint, so that
    ``evaluations.npz`` keeps the whole learning curve (SB3 starts it afresh)."""
    if not log.is_file():
        return
    data = np.load(log)
    keep = [i for i, steps in enumerate(data["timesteps"]) if steps <= up_to]
    callback.evaluations_timesteps = [int(data["timesteps"][i]) for i in keep]
    callback.evaluations_results = [list(data["results"][i]) for i in keep]
    callback.evaluations_length = [list(data["ep_lengths"][i]) for i in keep]
    if "successes" in data:
        callback.evaluations_successes = [list(data["successes"][i]) for i in keep]


def _progress_bar_available() -> bool:
    try:
        import rich  # noqa: F401
        import tqdm  # noqa: F401
    except ImportError:
        return False
    return True


def _previous_identity(out: Path) -> dict[str, Any] | None:
    path = out / CONFIG_FILE
    if not path.is_file():
        return None
    stored = json.loads(path.read_text())
    identity = stored.get("identity")
    return identity if isinstance(identity, dict) else None


def _write_config(out: Path, settings: TrainSettings, command: str | None) -> None:
    """``config.json``: the identity a resumed run must match, and everything else."""
    import gymnasium
    import mujoco
    import stable_baselines3
    import torch

    from agents.lab.bench.report import code_revision

    try:
        from importlib.metadata import version

        probegym_version = version("probegym")
    except Exception:  # noqa: BLE001 - not installed as a distribution
        probegym_version = "unknown"
    payload = {
        **settings.identity(),
        "steps": settings.steps,
        "eval_every": settings.eval_every,
        "eval_episodes": settings.eval_episodes,
        "eval_seed": settings.seed + 10_000,
        "checkpoint_every": settings.checkpoint_every,
        "identity": settings.identity(),
        "versions": {
            "probegym": probegym_version,
            "python": platform.python_version(),
            "stable_baselines3": stable_baselines3.__version__,
            "torch": torch.__version__,
            "gymnasium": gymnasium.__version__,
            "mujoco": mujoco.__version__,
            "numpy": np.__version__,
        },
        "revision": code_revision(),
        "command": command or "python " + " ".join(sys.argv),
        "written": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "settings": _plain(asdict(settings)),
    }
    write_json(payload, out / CONFIG_FILE, indent=1)


def _plain(value: Any) -> Any:
    """JSON-ready: paths as strings, tuples as lists, dataclasses as dicts."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "__dataclass_fields__"):
        return _plain(asdict(value))
    return value
