"""The environments' keyword arguments: routed to the configs they belong to, and the
display settings checked, each bad one named with what was expected."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import fields
from typing import Any

from envs.errors import EnvConfigError


def route_kwargs(
    env_name: str, kwargs: dict[str, Any], configs: dict[str, type], own: Iterable[str]
) -> dict[str, dict[str, Any]]:
    """Each config's keyword arguments (``configs``: name -> a dataclass type).

    Raises:
        EnvConfigError: an argument that is neither a config's field nor one of ``own``
            (the environment's named arguments); the message lists the valid ones.
    """
    routed: dict[str, dict[str, Any]] = {name: {} for name in configs}
    rest = dict(kwargs)
    for name, config_type in configs.items():
        for f in fields(config_type):
            if f.name in rest:
                routed[name][f.name] = rest.pop(f.name)
    if rest:
        valid = sorted(set(own) | {f.name for config in configs.values() for f in fields(config)})
        raise EnvConfigError(
            f"unknown keyword argument(s) {sorted(rest)} for {env_name}; "
            f"valid ones: {', '.join(valid)}"
        )
    return routed


def check_display(
    render_mode: str | None,
    render_modes: Sequence[str],
    camera_name: str,
    cameras: Iterable[str],
    width: object,
    height: object,
) -> None:
    """Refuse an unknown render mode or camera, or a frame size outside [16, 4096] pixels."""
    if render_mode is not None and render_mode not in render_modes:
        raise EnvConfigError(
            f"unknown render_mode {render_mode!r}; choose one of {', '.join(render_modes)} or None"
        )
    names = tuple(cameras)
    if camera_name not in names:
        raise EnvConfigError(
            f"unknown camera_name {camera_name!r}; choose one of {', '.join(names)}"
        )
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, int) or not 16 <= value <= 4096:
            raise EnvConfigError(
                f"{name} must be a whole number of pixels in [16, 4096]; got {value!r}"
            )
