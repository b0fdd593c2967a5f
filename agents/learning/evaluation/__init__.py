"""``probegym evaluate``: run a policy (scripted or trained) for N seeded episodes of one
environment and write what happened: per-episode JSON and CSV, a Markdown summary and
plots.

Library use::

    from agents.learning.evaluation import evaluate

    records = evaluate("probegym/LesionSearch-v0", "scripted", episodes=5, seed=0,
                       env_kwargs={"mesh": 623}, out=Path("probegym-out/evaluate/mine"))

Command line (``agents.cli`` wires it)::

    probegym evaluate probegym/LesionSearch-v0 --policy scripted --episodes 5 --seed 0

See ``docs/evaluate.md``. Episode k is reset with seed S + k; the same seed gives the same
numbers, all but the timings (the ``timing_*`` fields, kept apart and labelled).
"""

from agents.learning.evaluation.command import add_evaluate_parser, run_evaluate
from agents.learning.evaluation.records import CSV_COLUMNS, OUTPUT_FILES, TIMING_PREFIX
from agents.learning.evaluation.run import default_out, evaluate, without_timings

__all__ = [
    "CSV_COLUMNS",
    "OUTPUT_FILES",
    "TIMING_PREFIX",
    "add_evaluate_parser",
    "default_out",
    "evaluate",
    "run_evaluate",
    "without_timings",
]
