"""Scripted policies, training, evaluation, benchmarks and the ``probegym`` command line."""
