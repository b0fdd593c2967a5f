"""The simulated effects a scene calls for, and the check that a task's terms have them.

A scene simulates only the effects it calls for. Each observation term, reward term and
tissue component of a task declares the effects it needs (a task's ``TERM_EFFECTS``); a
:class:`Scene` is the frozen list of effects an environment simulates, named by a preset
(:data:`SCENES`) or given as ``gymnasium.make(..., effects=[...])``. Making an environment
whose terms need an effect its scene lacks fails at once, naming the term, the effect and
the scene (:func:`check_terms`).

The closed set (:data:`EFFECTS`), and what is skipped without each:

- ``deformation``: the FE breast steps each control step. Without it the breast is a
  rigid MuJoCo body at rest (:mod:`envs.rigid`): no tissue step at all.
- ``force_feedback``: the tissue's wrench and its stiffness act on the probe, the F/T
  sensor reads them. Without it the coupling is one-way (the tissue follows the probe):
  no reaction wrench is applied and no wrench stiffness is computed.
- ``lesion_tracking``: the target lesion located in the image plane each step.
- ``image``: the B-mode image of the slice under the probe; without it nothing is sliced.
- ``damping``: the tissue's inertia and Rayleigh damping (r_M = 0.1 /s, r_K = 0.1 s), under
  either profile: the ``paper`` profile's one linearised backward-Euler solve a step and the
  ``robust`` profile's Newton steps both integrate them (``tissue.sim``'s default, not
  quasi-static; tests/tissue/test_profile_dynamics.py).
- ``sliding``: the skin slides under the probe without friction (every contact method).
- ``gravity``: not simulated (the phantom's rest shape was segmented under gravity).
- ``stress``: not simulated (no stress field is recovered).

``damping`` and ``sliding`` are properties of the tissue model rather than switches: a scene
that deforms has both; a scene that names one without deformation is refused. ``gravity``
and ``stress`` are in the set so that a term may declare them, and a scene asking for them
is refused with the reason.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from envs.errors import EnvConfigError

#: Every effect a scene may call for, with what it means (see the module docstring).
EFFECTS: dict[str, str] = {
    "deformation": "the FE breast deforms under the probe",
    "force_feedback": "the tissue's reaction acts on the robot and its F/T sensor",
    "lesion_tracking": "the target lesion is located in the image plane",
    "image": "a B-mode ultrasound image of the slice under the probe",
    "damping": "the tissue's inertia and Rayleigh damping (either profile)",
    "sliding": "the skin slides under the probe without friction",
    "gravity": "gravity on the tissue",
    "stress": "the tissue's stress field",
}
#: Effects probegym cannot simulate, and why.
UNAVAILABLE: dict[str, str] = {
    "gravity": "the phantom's rest shape was segmented under gravity (adding it would count "
    "it twice)",
    "stress": "no stress field is recovered by the tissue",
}
#: Effects that are properties of the deforming tissue rather than switches.
TISSUE_EFFECTS = ("damping", "sliding")


@dataclass(frozen=True)
class Scene:
    """What an environment simulates.

    Attributes:
        name: the preset's name, or ``"custom"`` for a list given with ``effects=``.
        effects: the effects simulated (a subset of :data:`EFFECTS`).
        description: one line for listings.
    """

    name: str
    effects: frozenset[str]
    description: str = ""

    def has(self, effect: str) -> bool:
        """Whether the scene simulates ``effect``."""
        return effect in self.effects

    def listing(self) -> str:
        """Its effects, comma-separated, in :data:`EFFECTS`' order."""
        return ", ".join(name for name in EFFECTS if name in self.effects)


#: The named scenes (``gymnasium.make(..., scene="rigid")``). ``damping`` and ``sliding``
#: come with ``deformation`` (:func:`resolve_scene`).
SCENES: dict[str, Scene] = {
    scene.name: scene
    for scene in (
        Scene(
            "full",
            frozenset({"deformation", "force_feedback", "lesion_tracking", "sliding"}),
            "two-way coupled FE breast, lesions tracked (the default)",
        ),
        Scene(
            "imaging",
            frozenset({"deformation", "force_feedback", "lesion_tracking", "sliding", "image"}),
            "the full scene and the B-mode image",
        ),
        Scene(
            "one_way",
            frozenset({"deformation", "lesion_tracking", "sliding"}),
            "the FE breast follows the probe; the robot feels nothing",
        ),
        Scene(
            "rigid",
            frozenset({"force_feedback", "lesion_tracking"}),
            "a rigid breast (MuJoCo contact), lesions at rest: the cheapest scene",
        ),
    )
}


def parse_effects(effects: object) -> frozenset[str]:
    """``effects=`` as a set of names.

    Raises:
        EnvConfigError: not a list of strings, or a name outside :data:`EFFECTS` (the
            message lists the valid ones).
    """
    if isinstance(effects, str) or not isinstance(effects, Iterable):
        raise EnvConfigError(
            f"effects must be a list of effect names; got {effects!r} (valid names: "
            f"{', '.join(EFFECTS)})"
        )
    names = list(effects)
    unknown = [name for name in names if name not in EFFECTS]
    if unknown:
        raise EnvConfigError(f"unknown effect(s) {unknown!r}; valid names: {', '.join(EFFECTS)}")
    return frozenset(names)


def resolve_scene(
    scene: str | Scene | None,
    effects: object,
    image: bool,
) -> Scene:
    """The scene an environment simulates, from ``scene=`` (a preset name or a
    :class:`Scene`) or ``effects=`` (a list), with the tissue's own effects filled in.

    ``image=True`` adds ``image`` to a preset; ``damping`` and ``sliding`` are added whenever
    the breast deforms (under either profile).

    Raises:
        EnvConfigError: both ``scene`` and ``effects`` given; an unknown preset or effect;
            an effect the tissue cannot simulate (``gravity``, ``stress``); ``image``,
            ``sliding`` or ``damping`` without deformation.
    """
    if scene is not None and effects is not None:
        raise EnvConfigError("give scene= (a preset) or effects= (a list), not both")
    if effects is not None:
        chosen = Scene("custom", parse_effects(effects), "effects given by name")
    elif scene is None:
        chosen = SCENES["full"]
    elif isinstance(scene, Scene):
        chosen = Scene(scene.name, parse_effects(scene.effects), scene.description)
    elif isinstance(scene, str) and scene in SCENES:
        chosen = SCENES[scene]
    else:
        raise EnvConfigError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}")
    wanted = set(chosen.effects)
    if image:
        wanted.add("image")
    for name in sorted(wanted & set(UNAVAILABLE)):
        raise EnvConfigError(
            f"scene {chosen.name!r} calls for {name!r}, which probegym does not simulate: "
            f"{UNAVAILABLE[name]}; leave it out"
        )
    deforms = "deformation" in wanted
    for name in ("image", "sliding", "damping"):
        if name in wanted and not deforms:
            raise EnvConfigError(
                f"scene {chosen.name!r} calls for {name!r} without 'deformation' (a rigid "
                f"breast has no {name}); add 'deformation' or leave {name!r} out"
            )
    if deforms:
        wanted.update(TISSUE_EFFECTS)
    return Scene(chosen.name, frozenset(wanted), chosen.description)


def check_terms(env_name: str, scene: Scene, term_effects: Mapping[str, tuple[str, ...]]) -> None:
    """Refuse a scene that lacks an effect one of the task's terms needs.

    Raises:
        EnvConfigError: naming the first such term, the missing effect and the scene.
    """
    for term, needs in term_effects.items():
        for effect in needs:
            if effect not in scene.effects:
                raise EnvConfigError(
                    f"{env_name}'s term {term!r} needs the effect {effect!r}, which scene "
                    f"{scene.name!r} ({scene.listing() or 'no effects'}) lacks; add it "
                    f"(effects=[...]) or choose a scene that has it: "
                    f"{', '.join(_scenes_with(effect)) or 'none'}"
                )


def _scenes_with(effect: str) -> list[str]:
    return [name for name, scene in SCENES.items() if effect in scene.effects]


def needed_effects(term_effects: Mapping[str, tuple[str, ...]]) -> frozenset[str]:
    """Every effect some term needs."""
    return frozenset(effect for needs in term_effects.values() for effect in needs)
