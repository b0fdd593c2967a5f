"""``probegym train``: a resumable SB3 run with its configuration, checkpoints, evaluations,
Monitor CSVs and TensorBoard logs; the trained policy loads back and acts; many runs on Ray
match the same runs here."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from agents.cli import main

ENV_ID = "probegym/BreastCompress-v0"
RL_EXTRA = "training needs the rl extra: pip install -e '.[rl]' (a CPU torch first)"


def _train(out: Path, *extra: str) -> int:
    return main(
        [
            "train", ENV_ID, "--mesh", "623", "--n-envs", "2", "--eval-every", "1024",
            "--eval-episodes", "2", "--checkpoint-every", "1024", "--no-progress",
            "--out", str(out), *extra,
        ]
    )  # fmt: skip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["probegym/Nope-v0"], "unknown environment 'probegym/Nope-v0'; choose one of"),
        ([ENV_ID, "--algo", "dqn"], "--algo 'dqn': choose from ppo, sac"),
        ([ENV_ID, "--seed", "1", "--seeds", "1,2"], "give --seed or --seeds, not both"),
        ([ENV_ID, "--pretrain-scripted", "-1"], "--pretrain-scripted must be a whole number"),
        ([ENV_ID, "--algo", "sac", "--pretrain-scripted", "2"], "use --algo ppo or drop"),
        ([ENV_ID, "--pretrain-scripted", "2", "--init-from", "x"], "give one"),
    ],
)
def test_bad_requests_are_named(args, message, tmp_path: Path, capsys) -> None:
    assert main(["train", *args, "--out", str(tmp_path / "run")]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("option", [["--steps", "0"], ["--steps", "lots"], ["--seeds", "a,b"]])
def test_bad_numbers_are_refused_before_any_work(option, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", ENV_ID, *option])
    assert "expected" in capsys.readouterr().err


def test_more_envs_than_cores_is_warned_with_both_numbers() -> None:
    from agents.learning.train.command import cores_warning

    assert cores_warning(2, 2) is None and cores_warning(8, None) is None
    warning = cores_warning(5, 2)
    assert warning is not None and "--n-envs 5" in warning and "2 cores" in warning


def test_an_out_that_is_a_file_is_refused(tmp_path: Path, capsys) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert main(["train", ENV_ID, "--out", str(blocker)]) == 2
    assert "is a file; give a folder" in capsys.readouterr().err


def test_hyperparameters_come_from_one_table_per_algorithm_and_task() -> None:
    """Each algorithm's defaults, a task's own entry over them (policy_kwargs merged key by
    key), and a run's own values over both; every registered task resolves."""
    import envs
    from agents.learning.train.hyperparameters import HYPERPARAMETERS, default_hyperparameters
    from agents.learning.train.run import TrainSettings

    table = {
        "ppo": {
            "default": {"n_steps": 1024, "policy_kwargs": {"net_arch": [64], "log_std_init": -1.0}},
            "probegym/ForceScan-v1": {"n_steps": 2048, "policy_kwargs": {"log_std_init": -2.0}},
        }
    }  # fmt: skip
    scan = default_hyperparameters("ppo", "probegym/ForceScan-v1", table)
    assert scan == {"n_steps": 2048, "policy_kwargs": {"net_arch": [64], "log_std_init": -2.0}}
    assert default_hyperparameters("ppo", ENV_ID, table)["n_steps"] == 1024
    scan["policy_kwargs"]["net_arch"].append(1)  # a copy: the table is unchanged
    assert table["ppo"]["default"]["policy_kwargs"]["net_arch"] == [64]
    for algo in HYPERPARAMETERS:
        for env_id in envs.ENV_IDS:
            settings = TrainSettings(env_id=env_id, out=Path("unused"), algo=algo)
            assert settings.resolved_hyperparameters() == default_hyperparameters(algo, env_id)
    own = TrainSettings(env_id=ENV_ID, out=Path("unused"), hyperparameters={"n_epochs": 3})
    resolved = own.resolved_hyperparameters()
    assert resolved["n_epochs"] == 3 and resolved["n_steps"] == 1024


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("[1]", "is not a JSON object"),
        ("{n_steps: 1}", "is not JSON"),
    ],
)
def test_bad_hyperparameters_json_is_refused(value: str, message: str, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["train", ENV_ID, "--hyperparameters", value])
    assert message in capsys.readouterr().err


def test_a_hyperparameter_the_algorithm_does_not_take_is_refused_before_any_work(
    tmp_path: Path, capsys
) -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    out = tmp_path / "run"
    assert _train(out, "--hyperparameters", '{"n_step": 2048}') == 2
    error = capsys.readouterr().err
    assert "ppo takes no 'n_step'" in error and "n_steps" in error
    assert _train(out, "--algo", "sac", "--hyperparameters", '{"seed": 1}') == 2
    assert "sets seed" in capsys.readouterr().err
    assert not out.exists()


def test_a_dead_worker_is_named_with_its_environment_and_episode(tmp_path: Path) -> None:
    """A worker process killed under a SubprocVecEnv is found (its index and the signal's
    exit code) and reported with the seed it was made with and the episode it was on."""
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    import os
    import signal

    import gymnasium as gym
    from stable_baselines3.common.vec_env import SubprocVecEnv, VecNormalize

    from agents.learning.train.workers import dead_worker_report, dead_workers

    venv = VecNormalize(
        SubprocVecEnv([lambda: gym.make("CartPole-v1")] * 2, start_method="forkserver")
    )
    try:
        assert dead_workers(venv) == []
        process = venv.venv.processes[1]
        os.kill(process.pid, signal.SIGKILL)
        process.join(10)
        assert dead_workers(venv) == [(1, -9)]
    finally:
        for process in venv.venv.processes:
            process.kill()
    monitor = tmp_path / "monitor"
    monitor.mkdir()
    (monitor / "1.monitor.csv").write_text('#{"t_start": 0}\nr,l,t\n1,2,3\n4,5,6\n')
    report = dead_worker_report([(1, -9)], 7, tmp_path, 2048)
    assert "environment 1 (made with seed 8) died on its episode 3, exit code -9" in report
    assert "checkpoints up to 2,048 steps are kept" in report and "rerun the same" in report
    assert "no checkpoint was written yet" in dead_worker_report([(0, 1)], 0, tmp_path, None)


@pytest.mark.train
def test_a_run_whose_worker_dies_says_which_and_keeps_its_checkpoints(tmp_path: Path) -> None:
    """probegym train's own loop: a worker killed after the first checkpoint ends the run
    with the error naming it, and the checkpoint is kept (from which a rerun resumes, as
    test_train_saves_everything_loads_back_and_resumes shows)."""
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    import os
    import signal

    from stable_baselines3.common.callbacks import BaseCallback

    from agents.learning.train.run import TrainSettings, train
    from agents.learning.train.workers import WorkerDiedError

    class KillWorker(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.venv: object = None

        def _on_step(self) -> bool:
            if self.num_timesteps >= 1100 and self.venv is not None:
                processes = self.venv.processes  # type: ignore[attr-defined]
                os.kill(processes[1].pid, signal.SIGKILL)
                processes[1].join(10)
                self.venv = None
            return True

    class Hooks:
        """train()'s benchmark hooks, used here to reach the worker processes."""

        def __init__(self) -> None:
            self.callback = KillWorker()
            self.env_wrapper = None

        def inner(self, venv: object) -> object:
            self.callback.venv = venv
            return venv

        def outer(self, venv: object) -> object:
            return venv

        def mirror(self, venv: object) -> object:
            return venv

    out = tmp_path / "run"
    settings = TrainSettings(
        env_id=ENV_ID, out=out, env_kwargs={"mesh": 623}, steps=4096, n_envs=2,
        eval_every=100_000, checkpoint_every=1024, progress=False,
    )  # fmt: skip
    with pytest.raises(WorkerDiedError, match=r"environment 1 \(made with seed 1\) died"):
        train(settings, log=lambda _: None, timing=Hooks())
    assert (out / "checkpoints" / "model_1024_steps.zip").is_file()


def test_a_path_that_is_no_model_is_refused(tmp_path: Path) -> None:
    from agents.learning.train import TrainedPolicyError, load_policy

    with pytest.raises(TrainedPolicyError, match="holds no model.zip and no checkpoint"):
        load_policy(tmp_path)
    with pytest.raises(TrainedPolicyError, match="neither a probegym train folder"):
        load_policy(tmp_path / "missing.zip")


def test_cloning_fits_the_scripted_policy_s_actions() -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from agents.learning.train.hyperparameters import default_hyperparameters
    from agents.learning.train.imitation import clone_into, scripted_demonstrations

    torch.set_num_threads(1)
    kwargs = {"contact": "lm", "mesh": 623}
    demos = scripted_demonstrations(ENV_ID, kwargs, episodes=2, seed=0)
    assert demos.episodes == 2 and demos.samples == len(demos.observations["wrench"]) > 20
    assert np.all(np.abs(demos.actions) <= 1.0)
    venv = make_vec_env(f"envs:{ENV_ID}", n_envs=1, seed=0, env_kwargs=kwargs,
                        vec_env_cls=DummyVecEnv)  # fmt: skip
    venv = VecNormalize(venv, norm_obs_keys=list(venv.observation_space.spaces))  # type: ignore[attr-defined]
    model = PPO("MultiInputPolicy", venv, seed=0, device="cpu", **default_hyperparameters("ppo"))

    def action_error() -> float:
        observed = venv.normalize_obs(demos.observations)
        acted, _ = model.predict(observed, deterministic=True)
        return float(np.mean((acted - demos.actions) ** 2))

    counted = venv.obs_rms["wrench"].count
    losses = clone_into(model, demos, venv, epochs=20)
    # The normalisation learnt the demonstrations' statistics first.
    assert venv.obs_rms["wrench"].count == pytest.approx(counted + demos.samples)
    before = losses[0]
    # Fitted: the error falls by 10 x or more over the epochs (measured about 100 x), and
    # the trained policy's deterministic actions match the demonstrations that closely.
    assert losses[-1] < 0.1 * before
    assert action_error() < 0.2 * before


@pytest.mark.train
def test_train_saves_everything_loads_back_and_resumes(tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    import gymnasium as gym

    import envs  # noqa: F401 - registers the ids
    from agents.learning.train import load_policy

    out = tmp_path / "run"
    assert _train(out, "--steps", "2048") == 0
    config = json.loads((out / "config.json").read_text())
    assert config["env_id"] == ENV_ID and config["algo"] == "ppo"
    assert config["env_kwargs"] == {"contact": "lm", "mesh": 623, "profile": "robust"}
    assert config["hyperparameters"]["n_steps"] == 1024 and config["revision"]
    assert {"stable_baselines3", "torch", "mujoco", "gymnasium"} <= set(config["versions"])
    for name in (
        "model.zip", "vecnormalize.pkl", "eval/evaluations.npz", "eval/best_model.zip",
        "eval/best_vecnormalize.pkl",
    ):  # fmt: skip
        assert (out / name).is_file(), name
    assert load_policy(out / "eval" / "best_model.zip").normalizer is not None
    assert (out / "checkpoints" / "model_2048_steps.zip").is_file()
    assert (out / "checkpoints" / "model_vecnormalize_2048_steps.pkl").is_file()
    assert list((out / "tb").rglob("events.out.tfevents.*"))
    with (out / "monitor" / "0.monitor.csv").open() as handle:
        handle.readline()  # SB3's JSON header line
        rows = list(csv.DictReader(handle))
    assert rows and {"r", "l", "t", "is_success"} <= set(rows[0])
    # The policy loads back with its normalisation and acts in a fresh env.
    policy = load_policy(out)
    assert policy.normalizer is not None and not policy.normalizer.training
    env = gym.make(ENV_ID, mesh=623)
    observation, _ = env.reset(seed=3)
    for _ in range(5):
        action = policy(observation)
        assert action.shape == (6,) and np.all(np.abs(action) <= 1.0)
        observation, *_ = env.step(action)
    env.close()
    # probegym evaluate takes the folder: the env it was trained on, its normalisation.
    evaluated = tmp_path / "evaluated"
    assert (
        main(["evaluate", ENV_ID, "--policy", str(out), "--episodes", "2", "--out", str(evaluated)])
        == 0
    )
    summary = json.loads((evaluated / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["env_kwargs"]["mesh"] == 623
    # Rerun with a larger budget (PPO collects whole rollouts: 1,024 steps x 2 envs): it
    # resumes, and the learning curve keeps its start.
    assert _train(out, "--steps", "4096") == 0
    log = np.load(out / "eval" / "evaluations.npz")
    assert log["timesteps"].tolist() == [1024, 2048, 3072, 4096]
    assert "successes" in log
    assert (out / "checkpoints" / "model_4096_steps.zip").is_file()
    # Other settings in the same folder are refused.
    assert _train(out, "--steps", "6144", "--contact", "penalty") == 2
    # A curriculum's next stage starts from this model and its statistics, in new settings.
    import pickle

    stage = tmp_path / "stage2"
    kwargs = '{"hold_steps": 10}'
    assert _train(stage, "--steps", "2048", "--env-kwargs", kwargs, "--init-from", str(out)) == 0
    config = json.loads((stage / "config.json").read_text())
    assert config["identity"]["init_from"] == str(out)
    assert config["env_kwargs"]["hold_steps"] == 10
    with (out / "vecnormalize.pkl").open("rb") as handle:
        before = pickle.load(handle).obs_rms["wrench"].count
    with (stage / "vecnormalize.pkl").open("rb") as handle:
        after = pickle.load(handle).obs_rms["wrench"].count
    assert after > before > 0  # the statistics learnt on from the first stage's
    assert _train(tmp_path / "other", "--algo", "sac", "--init-from", str(out)) == 2
    # A run that first clones the scripted policy says so; resumed, it does not clone again.
    cloned = tmp_path / "cloned"
    assert _train(cloned, "--steps", "2048", "--pretrain-scripted", "2") == 0
    record = json.loads((cloned / "pretrain.json").read_text())
    assert record["episodes"] == 2 and record["samples"] > 20
    assert record["last_epoch_mse"] < record["first_epoch_mse"]
    config = json.loads((cloned / "config.json").read_text())
    assert config["identity"]["pretrain_episodes"] == 2
    written = (cloned / "pretrain.json").stat().st_mtime_ns
    assert _train(cloned, "--steps", "4096", "--pretrain-scripted", "2") == 0
    assert (cloned / "pretrain.json").stat().st_mtime_ns == written


@pytest.mark.train
def test_runs_on_ray_match_the_same_runs_here(tmp_path: Path) -> None:
    pytest.importorskip("stable_baselines3", reason=RL_EXTRA)
    pytest.importorskip("ray", reason="--ray needs the ray extra: pip install -e '.[ray]'")
    import ray
    from stable_baselines3 import PPO

    common = [
        "train", ENV_ID, "--mesh", "623", "--n-envs", "1", "--steps", "512", "--eval-every",
        "512", "--eval-episodes", "1", "--checkpoint-every", "512", "--no-progress",
    ]  # fmt: skip
    try:
        assert (
            main([*common, "--seeds", "0,1", "--ray", "local", "--out", str(tmp_path / "ray")]) == 0
        )
    finally:
        ray.shutdown()
    summary = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert [(run["seed"], run["contact"]) for run in summary["runs"]] == [(0, "lm"), (1, "lm")]
    for seed in (0, 1):
        assert main([*common, "--seed", str(seed), "--out", str(tmp_path / f"here{seed}")]) == 0
        there = PPO.load(tmp_path / "ray" / f"ppo-lm-seed{seed}" / "model.zip", device="cpu")
        here = PPO.load(tmp_path / f"here{seed}" / "model.zip", device="cpu")
        for name, value in here.policy.state_dict().items():
            assert np.array_equal(value.numpy(), there.policy.state_dict()[name].numpy()), name
    # Two seeds learn two different policies.
    a = PPO.load(tmp_path / "here0" / "model.zip", device="cpu").policy.state_dict()
    b = PPO.load(tmp_path / "here1" / "model.zip", device="cpu").policy.state_dict()
    assert any(not np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)
