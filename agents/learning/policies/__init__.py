"""Scripted policies: controllers written by hand that solve the tasks (baselines, tests,
demonstrations)."""

from collections.abc import Callable
from typing import Any

from agents.learning.policies.compression import CompressionPolicy, compression_v2_policy
from agents.learning.policies.force_scan import ForceScanPolicy, force_scan_v1_policy
from agents.learning.policies.lesion_search import LesionSearchPolicy, lesion_search_v1_policy
from agents.learning.policies.random_policy import RandomPolicy

#: Each environment's scripted policy: a class or function that makes one (``probegym
#: evaluate ENV --policy scripted``).
SCRIPTED_POLICIES: dict[str, Callable[[], Any]] = {
    "probegym/BreastCompress-v0": CompressionPolicy,
    "probegym/LesionSearch-v0": LesionSearchPolicy,
    "probegym/ForceScan-v0": ForceScanPolicy,
    "probegym/LesionSearch-v1": lesion_search_v1_policy,
    "probegym/ForceScan-v1": force_scan_v1_policy,
    "probegym/BreastCompress-v1": CompressionPolicy,
    "probegym/BreastCompress-v2": compression_v2_policy,
}

__all__ = [
    "SCRIPTED_POLICIES",
    "CompressionPolicy",
    "ForceScanPolicy",
    "LesionSearchPolicy",
    "RandomPolicy",
]
