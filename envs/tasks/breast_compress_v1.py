"""``probegym/BreastCompress-v1``: v0's compression task, every episode possible under the
safety force.

With the skin at the probe's scale, v0 asks the two shallowest target lesions (1 and 4,
15-18.5 mm under the probe at the start) to move 5-7 mm up the image: up to 47 % of the
tissue above them. In
9 of 50 held-out episodes (seeds 1000-1049) its scripted policy then needs more than the
5 N under which success must hold (6.2-9.2 N on reaching the depth band in 7 of them), so
no policy can succeed there and a learner's success is capped near 82 %. v1 asks at most
28 % of the lesion's depth at the start (lesion 1: 4.2 mm, lesion 4: 4.9-5.2 mm, lesion 6:
5.0-6.2 mm; lesions 7 and 10 keep v0's 5-7 mm): its scripted policy succeeds in 50 of 50
held-out episodes (docs/baselines.md). Everything else is v0's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from envs.tasks.breast_compress import BreastCompressConfig, BreastCompressEnv

#: The largest share of the lesion's depth v1 asks to compress: the deepest share v0's
#: scripted policy reaches under the safety force on every held-out episode.
MAX_COMPRESSION_STRAIN = 0.28


@dataclass(frozen=True)
class BreastCompressV1Config(BreastCompressConfig):
    """BreastCompress-v1's settings: v0's (:class:`BreastCompressConfig`), the compression
    asked capped at :data:`MAX_COMPRESSION_STRAIN` of the lesion's depth by default."""

    max_compression_strain: float | None = MAX_COMPRESSION_STRAIN


def _v1_spec(v0: str) -> str:
    """v0's spec with v1's starting state and version history."""
    start = "the compression asked is drawn from 5-7 mm."
    if start not in v0 or "## Version history" not in v0:
        raise RuntimeError("BreastCompress-v0's docstring changed: rewrite v1's spec")
    text = v0.replace(
        start,
        "the compression asked is drawn from 5-7 mm and capped at 28 % of the lesion's\n"
        "    depth under the probe (``max_compression_strain``; lesion 1: 4.2 mm).",
    )
    text = text.replace('"probegym/BreastCompress-v0"', '"probegym/BreastCompress-v1"')
    return (
        text.rstrip()
        + "\n    - v1: the compression asked at most 28 % of the lesion's depth, so that every\n"
        "      episode can succeed under the safety force (v0 asked the shallow lesions for\n"
        "      up to 47 %, which took 6-9 N); the rest is v0's.\n    "
    )


class BreastCompressV1Env(BreastCompressEnv):
    task_config_type: ClassVar[type] = BreastCompressV1Config
    task_config: BreastCompressV1Config


BreastCompressV1Env.__doc__ = _v1_spec(BreastCompressEnv.__doc__ or "")
