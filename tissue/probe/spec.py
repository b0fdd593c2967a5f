"""The command line's probe spec: ``face``, ``sphere:R``, ``box:LX,LY,LZ``,
``cylinder:R,H`` (metres) or a mesh file path, parsed into a :class:`ProbeShape`."""

from __future__ import annotations

import math
from pathlib import Path

from tissue.errors import ConfigError
from tissue.probe.analytic import BoxProbe, CylinderProbe, SphereProbe, linear_probe
from tissue.probe.mesh import load_probe_mesh
from tissue.probe.shape import LARGEST_PLAUSIBLE_SIZE_M, PROBE_SPEC_FORMS, ProbeShape

_MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb", ".gltf")


def _parse_numbers(spec: str, body: str, count: int) -> list[float]:
    """Exactly ``count`` comma-separated numbers from a spec body, or a ConfigError."""
    parts = [part.strip() for part in body.split(",")]
    try:
        values = [float(part) for part in parts]
    except ValueError:
        values = []
    if len(values) != count or len(parts) != count:
        raise ConfigError(_spec_message(spec, f"expected {count} number(s) after the colon"))
    for value in values:
        if not math.isfinite(value) or value <= 0.0:
            raise ConfigError(_spec_message(spec, "sizes must be positive, finite metres"))
        if value > LARGEST_PLAUSIBLE_SIZE_M:
            raise ConfigError(
                _spec_message(spec, "sizes are in metres (did you give millimetres?)")
            )
    return values


def _spec_message(spec: str, problem: str) -> str:
    """An error message naming the spec, the problem and every valid form."""
    forms = "; ".join(PROBE_SPEC_FORMS)
    return f"probe spec {spec!r}: {problem}. Valid forms (metres): {forms}"


def parse_probe_spec(spec: str) -> ProbeShape:
    """A probe shape from a command-line spec.

    Args:
        spec: one of ``face``, ``sphere:RADIUS``, ``box:LX,LY,LZ``,
            ``cylinder:RADIUS,HEIGHT`` (sizes in metres), or a path to a closed mesh file
            in the probe frame, in metres.

    Returns:
        the shape.

    Raises:
        ConfigError: an unknown form, a wrong count of numbers, or a zero, negative,
            non-numeric or implausibly large size; the message lists the valid forms.
        MeshError: a mesh file that is not a closed triangle mesh.
    """
    if not isinstance(spec, str) or not spec.strip():
        raise ConfigError(_spec_message(str(spec), "empty"))
    text = spec.strip()
    kind, colon, body = text.partition(":")
    kind = kind.strip().lower()
    if kind == "face" and not colon:
        return linear_probe()
    if kind in ("sphere", "box", "cylinder") and colon:
        if kind == "sphere":
            return SphereProbe(*_parse_numbers(spec, body, 1))
        if kind == "box":
            return BoxProbe(_parse_numbers(spec, body, 3))
        return CylinderProbe(*_parse_numbers(spec, body, 2))
    # Check files after the named forms, but before rejecting, so "C:\probe.stl" works.
    path = Path(text).expanduser()
    if path.is_file():
        return load_probe_mesh(path)
    if path.suffix.lower() in _MESH_SUFFIXES:
        raise ConfigError(_spec_message(spec, f"mesh file {str(path)!r} does not exist"))
    if kind in ("face", "sphere", "box", "cylinder"):
        raise ConfigError(_spec_message(spec, f"malformed {kind!r} spec"))
    raise ConfigError(_spec_message(spec, "unknown probe shape"))
