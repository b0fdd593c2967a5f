"""The tasks: one module each, registered in :mod:`envs` as ``probegym/<Task>-v<N>``."""
