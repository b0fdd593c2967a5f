"""What a transfer study is: the tasks, the configurations trained on and evaluated on, the
reference, the budgets (:class:`TransferSpec`), validated before any training."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import tissue
from tissue.lab import PHANTOM_LEVELS

#: ``--quick``: BreastCompress and one scanning task, trained on the four methods at the two
#: coarsest environment meshes, evaluated on those and on the reference; one seed.
QUICK_ENV_IDS = ("probegym/BreastCompress-v2", "probegym/LesionSearch-v1")
QUICK_CONFIGURATIONS = tuple(
    f"{method}@{level}"
    for level in (623, 1363)
    for method in ("lm", "penalty", "prescribed", "pbd")
)
#: The accurate model every policy is judged on: LM contact (exact forces) on 4,126 tets.
REFERENCE = "lm@4126"
#: Environment steps per training run, per task: the quick study's, sized so that the whole
#: study (16 training runs, 144 cells of 20 episodes) finishes in about two hours on 2 cores
#: (docs/study.md: 2 h 22 min, measured). With them every configuration reaches 85-100 % on
#: BreastCompress-v2 and 75-95 % on LesionSearch-v1 on its own configuration; LesionSearch's
#: PPO seeds pass 80 % at 20k-60k on LM at 1,303 tets (docs/baselines.md), so its quick
#: budget trains some configurations short.
QUICK_STEPS = {"probegym/BreastCompress-v2": 10_240, "probegym/LesionSearch-v1": 24_576}
#: And the full study's (the baselines' budgets).
FULL_STEPS = {
    "probegym/BreastCompress-v2": 50_000,
    "probegym/LesionSearch-v1": 100_000,
    "probegym/ForceScan-v1": 200_000,
}
#: Held-out episodes per cell: the quick study's, and the default.
QUICK_EPISODES = 20
EPISODES = 50
#: The first held-out episode's seed (training uses S + i, its evaluations S + 10,000 + i).
HELD_OUT_SEED = 1000


class TransferError(tissue.ConfigError):
    """A transfer study that cannot be run as asked (the message says why and what is valid)."""


@dataclass(frozen=True, order=True)
class Configuration:
    """A contact method on a phantom level (robust profile): ``lm@1363``.

    Attributes:
        method: a registered contact method (:func:`tissue.contact_methods`).
        level: a phantom level (:data:`tissue.lab.PHANTOM_LEVELS`).
    """

    method: str
    level: int

    @classmethod
    def parse(cls, text: str, option: str) -> Configuration:
        """``METHOD@LEVEL``; a :class:`TransferError` naming ``option``, the value and the
        valid choices otherwise."""
        methods = tissue.contact_methods()
        levels = ", ".join(str(level) for level in PHANTOM_LEVELS)
        method, at, level = str(text).strip().partition("@")
        if not at or not level.isdigit():
            raise TransferError(
                f"{option}: {text!r} is not METHOD@LEVEL (e.g. lm@1363): a contact method of "
                f"{', '.join(methods)} and a phantom level of {levels}"
            )
        if method.lower() not in methods:
            raise TransferError(
                f"{option}: {text!r} names the contact method {method!r}; choose one of "
                f"{', '.join(methods)}"
            )
        if int(level) not in PHANTOM_LEVELS:
            raise TransferError(
                f"{option}: {text!r} names the level {level}; choose one of {levels}"
            )
        return cls(method.lower(), int(level))

    @property
    def label(self) -> str:
        return f"{self.method}@{self.level}"

    def env_kwargs(self) -> dict[str, Any]:
        """Its ``gymnasium.make`` arguments."""
        return {"contact": self.method, "mesh": self.level, "profile": "robust"}


@dataclass(frozen=True)
class TransferSpec:
    """A transfer study: train a policy per (task, training configuration, seed), evaluate
    each on every evaluation configuration and on the reference.

    Attributes:
        env_ids: the tasks (registered probegym ids).
        train: the configurations trained on.
        evaluate: the configurations evaluated on (the reference is added where missing).
        reference: the accurate configuration every policy is judged on.
        algo: ``ppo`` or ``sac``.
        steps: environment steps per training run, per task.
        seeds: training seeds.
        episodes: held-out episodes per cell (seeds from :data:`HELD_OUT_SEED`).
        n_envs: environments per training run.
    """

    env_ids: tuple[str, ...]
    train: tuple[Configuration, ...]
    evaluate: tuple[Configuration, ...]
    reference: Configuration
    algo: str = "ppo"
    steps: dict[str, int] = field(default_factory=dict)
    seeds: tuple[int, ...] = (0,)
    episodes: int = EPISODES
    n_envs: int = 2

    def __post_init__(self) -> None:
        check_env_ids(self.env_ids)
        if not self.env_ids or not self.train:
            raise TransferError("a transfer study needs at least one --env and one --train")
        if self.algo not in ("ppo", "sac"):
            raise TransferError(f"--algo {self.algo!r}: choose ppo or sac")
        for env_id in self.env_ids:
            steps = self.steps.get(env_id)
            if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
                raise TransferError(
                    f"no training budget for {env_id}: give --steps N (a whole number >= 1)"
                )
        for name, value in (("--episodes", self.episodes), ("--n-envs", self.n_envs)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise TransferError(f"{name} must be a whole number >= 1; got {value!r}")
        if not self.seeds or any(isinstance(s, bool) or int(s) != s or s < 0 for s in self.seeds):
            raise TransferError(f"--seeds must be whole numbers >= 0; got {self.seeds!r}")
        if self.reference not in self.evaluate:
            object.__setattr__(self, "evaluate", (*self.evaluate, self.reference))

    def runs(self) -> list[tuple[str, Configuration, int]]:
        """Every training run: (task, configuration, seed)."""
        return [(e, c, s) for e in self.env_ids for c in self.train for s in self.seeds]


def check_env_ids(env_ids: tuple[str, ...]) -> None:
    """A :class:`TransferError` naming the first id that is not a probegym environment."""
    import envs

    for env_id in env_ids:
        if env_id not in envs.ENV_IDS:
            raise TransferError(
                f"--env {env_id!r} is not a probegym environment; choose from "
                f"{', '.join(envs.ENV_IDS)}"
            )


def configurations(
    text: str | None, default: tuple[str, ...], option: str
) -> tuple[Configuration, ...]:
    """A comma-separated list of ``METHOD@LEVEL`` (``default`` where None), without repeats."""
    items = default if text is None else tuple(p for p in text.split(",") if p.strip())
    if not items:
        raise TransferError(f"{option} needs at least one METHOD@LEVEL")
    parsed: list[Configuration] = []
    for item in items:
        config = Configuration.parse(item, option)
        if config not in parsed:
            parsed.append(config)
    return tuple(parsed)


def short_name(env_id: str) -> str:
    """``probegym/BreastCompress-v2`` -> ``BreastCompress-v2`` (a folder name)."""
    return env_id.split("/")[-1]
