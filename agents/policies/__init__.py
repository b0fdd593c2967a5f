"""Scripted policies: controllers written by hand that solve the tasks (baselines, tests,
demonstrations)."""

from agents.policies.compression import CompressionPolicy

__all__ = ["CompressionPolicy"]
