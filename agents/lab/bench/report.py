"""Benchmark tables as Markdown, written by the benchmarks themselves beside their JSON.

Every ``probegym bench ...`` run writes ``<json path>.md`` next to its JSON: the command that
made it, the code revision, the date, the machine, its cores and its load average when the
run started and ended, then the run's tables. The speed page (``docs/speed.md``) links the
files a run wrote into ``docs/speed/``, so the published figures are a benchmark's output,
never typed by hand.
"""

from __future__ import annotations

import os
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents.outputs import readable, write_json

ROOT = Path(__file__).resolve().parents[2]


def code_revision() -> str:
    """The checkout's short commit hash, ``+dirty`` with uncommitted changes to tracked
    files; ``unknown`` outside a git checkout."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=ROOT, capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=ROOT, capture_output=True, text=True, check=True, timeout=10,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return commit + ("+dirty" if dirty else "")


def load_average() -> tuple[float, float, float] | None:
    """The 1, 5 and 15 minute load averages (None where the OS has none)."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:
        return None
    return (one, five, fifteen)


@dataclass
class MarkdownTable:
    """One table: a caption, a header row and rows of already formatted cells."""

    caption: str
    header: Sequence[str]
    rows: list[Sequence[str]] = field(default_factory=list)

    def text(self) -> str:
        lines = [f"**{self.caption}**", "", "| " + " | ".join(self.header) + " |"]
        lines.append("|" + "|".join(" --- " for _ in self.header) + "|")
        lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in self.rows]
        return "\n".join(lines) + "\n"


class BenchRecord:
    """The provenance of one benchmark run, taken when it starts (see the module docstring)."""

    def __init__(self, title: str, command: str | None = None) -> None:
        self.title = title
        self.command = command or "python " + shlex.join(sys.argv)
        self.revision = code_revision()
        self.started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
        self.machine = f"{platform.node()} ({platform.processor() or platform.machine()})"
        self.cores = os.cpu_count()
        self.load_at_start = load_average()

    def write(self, json_path: Path, tables: Sequence[MarkdownTable], notes: str = "") -> Path:
        """Write ``json_path`` with the suffix ``.md``: the provenance, then the tables."""
        path = Path(json_path).with_suffix(".md")
        path.parent.mkdir(parents=True, exist_ok=True)
        end = load_average()

        def words(load: tuple[float, float, float] | None) -> str:
            return "unknown" if load is None else " / ".join(f"{v:.2f}" for v in load)

        head = [
            f"# {self.title}",
            "",
            f"Written by `{self.command}` on revision `{self.revision}`, started "
            f"{self.started}, on {self.machine} with {self.cores} cores; load average (1 / 5 / "
            f"15 min) {words(self.load_at_start)} at the start, {words(end)} at the end. "
            "Compare ratios within this run, not absolute times across runs.",
            "",
        ]
        body = "\n".join(table.text() for table in tables)
        path.write_text("\n".join(head) + "\n" + body + (f"\n{notes}\n" if notes else ""))
        readable(path)
        return path


def write_records(
    path: Path, benchmark: str, started: str, records: list[Any], **extra: Any
) -> None:
    """A benchmark's JSON: its name, start, machine, revision and cores, ``extra`` and the
    records so far (rewritten as a run goes, so an interrupted run keeps what it measured)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "benchmark": benchmark,
        "started": started,
        "machine": platform.node(),
        "revision": code_revision(),
        "cpu_count": os.cpu_count(),
        **extra,
        "records": records,
    }
    write_json(payload, path, indent=1)
