"""Scripted policies: controllers written by hand that solve the tasks (baselines, tests,
demonstrations)."""

from agents.policies.compression import CompressionPolicy
from agents.policies.force_scan import ForceScanPolicy
from agents.policies.lesion_search import LesionSearchPolicy

__all__ = ["CompressionPolicy", "ForceScanPolicy", "LesionSearchPolicy"]
