"""Scripted policies: controllers written by hand that solve the tasks (baselines, tests,
demonstrations)."""

from agents.policies.compression import CompressionPolicy
from agents.policies.force_scan import ForceScanPolicy
from agents.policies.lesion_search import LesionSearchPolicy
from agents.policies.random_policy import RandomPolicy

#: Each environment's scripted policy class (``probegym evaluate ENV --policy scripted``).
SCRIPTED_POLICIES: dict[str, type] = {
    "probegym/BreastCompress-v0": CompressionPolicy,
    "probegym/LesionSearch-v0": LesionSearchPolicy,
    "probegym/ForceScan-v0": ForceScanPolicy,
}

__all__ = [
    "SCRIPTED_POLICIES",
    "CompressionPolicy",
    "ForceScanPolicy",
    "LesionSearchPolicy",
    "RandomPolicy",
]
