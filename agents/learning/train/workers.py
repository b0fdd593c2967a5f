"""A training run's worker processes that die: which environment, on which episode.

SB3's ``SubprocVecEnv`` sees a dead worker only as a broken pipe (``EOFError``,
``ConnectionResetError``, ``BrokenPipeError``) in the learner. :func:`dead_worker_report`
turns that into what a user can act on: the environment's index, the seed it was made
with, the episode it was on (from its Monitor CSV), the process's exit code, and the
checkpoints kept, from which a rerun of the same command resumes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: What the learner raises when a worker's end of the pipe is gone.
PIPE_ERRORS = (EOFError, ConnectionResetError, BrokenPipeError)


class WorkerDiedError(RuntimeError):
    """A worker process died during training; the message says which and how to resume."""


def subprocess_env(venv: Any) -> Any | None:
    """The ``SubprocVecEnv`` under ``venv``'s wrappers (VecNormalize, ...), None if none."""
    while venv is not None:
        if hasattr(venv, "processes"):
            return venv
        venv = getattr(venv, "venv", None)
    return None


def dead_workers(venv: Any) -> list[tuple[int, int | None]]:
    """(environment index, exit code) of each worker process of ``venv`` that has ended."""
    workers = subprocess_env(venv)
    if workers is None:
        return []
    return [
        (index, process.exitcode)
        for index, process in enumerate(workers.processes)
        if not process.is_alive()
    ]


def stop_workers(*venvs: Any) -> None:
    """End every worker process of ``venvs`` still running (after one died: the learner
    cannot go on, and a survivor left behind would print a broken pipe of its own)."""
    for venv in venvs:
        workers = subprocess_env(venv)
        for process in [] if workers is None else workers.processes:
            if process.is_alive():
                process.terminate()
                process.join(5)


def episodes_finished(monitor_dir: Path, index: int) -> int:
    """Episodes environment ``index`` has finished, from its Monitor CSV (0 if none)."""
    path = monitor_dir / f"{index}.monitor.csv"
    if not path.is_file():
        return 0
    lines = path.read_text().splitlines()
    # SB3's Monitor writes a JSON comment line and a header before one row per episode.
    return max(0, len([line for line in lines if line and not line.startswith("#")]) - 1)


def dead_worker_report(
    dead: list[tuple[int, int | None]], seed: int, out: Path, kept_steps: int | None
) -> str:
    """The message for workers that died: each one's environment index, the seed it was
    made with (``seed + index``), the episode it was on, its exit code; then what is kept."""
    parts = []
    for index, code in dead:
        episode = episodes_finished(out / "monitor", index) + 1
        parts.append(
            f"environment {index} (made with seed {seed + index}) died on its episode "
            f"{episode}, exit code {code}"
        )
    kept = (
        "no checkpoint was written yet"
        if kept_steps is None
        else f"the checkpoints up to {kept_steps:,} steps are kept in {out / 'checkpoints'}"
    )
    return (
        f"a worker process died: {'; '.join(parts)}; {kept}: rerun the same command to "
        "resume (a negative exit code is the signal that killed it: -9 is often the "
        "out-of-memory killer)"
    )
