"""A new contact strategy is one module plus one registration: a toy strategy defined and
registered here runs through ``compress``, the study and an environment without any other
file knowing of it."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401 - registers the environments
import tissue
from agents.lab.study.runner import run_study
from agents.lab.study.spec import StudySpec
from tissue.contact import PenaltyContact, PenaltyParams, register_contact, unregister_contact
from tissue.contact.penalty import PenaltyTerm
from tissue.errors import ConfigError
from tissue.mesh import TetMesh


@dataclass(frozen=True)
class StiffeningParams(PenaltyParams):
    """Penalty's settings plus the toy's own: springs ``stiffness_factor`` times stiffer
    than the given (or default) stiffness."""

    stiffness_factor: float = 3.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.stiffness_factor > 0:
            raise ConfigError(f"stiffness_factor must be > 0; got {self.stiffness_factor!r}")


class StiffeningPenalty(PenaltyContact):
    """Penalty contact with stiffer springs, so it leaves less penetration than penalty."""

    name = "toy_stiff"
    label = "ToyStiff"
    colour = "tab:purple"
    params_type = StiffeningParams
    params: StiffeningParams
    penetration_bound_m = 0.001

    def __init__(self, mesh: TetMesh, probe_shape: Any, **kwargs: Any) -> None:
        super().__init__(mesh, probe_shape, **kwargs)
        self.stiffness_n_per_m *= self.params.stiffness_factor
        self.term = PenaltyTerm(
            self.surface, self.probe, self.stiffness_n_per_m, self.params.contact_distance_m
        )


@pytest.fixture
def toy():
    register_contact(StiffeningPenalty)
    try:
        yield StiffeningPenalty.name
    finally:
        unregister_contact(StiffeningPenalty.name)


def test_the_toy_is_a_contact_method_while_registered(toy: str) -> None:
    assert toy in tissue.contact_methods()
    spec = tissue.TissueSpec(mesh=623, contact="TOY_STIFF", profile="robust")
    assert spec.contact == toy
    with pytest.raises(ConfigError, match="takes contact_params of type StiffeningParams"):
        tissue.TissueSpec(mesh=623, contact=toy, contact_params=PenaltyParams())
    with pytest.raises(ConfigError, match="already registered"):

        class Impostor(StiffeningPenalty):
            pass

        register_contact(Impostor)


def test_an_unregistered_toy_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match="unknown contact method 'toy_stiff'; choose one of"):
        tissue.TissueSpec(mesh=623, contact="toy_stiff")
    with pytest.raises(ConfigError, match="lowercase identifier"):

        class Nameless(PenaltyContact):
            name = "Not A Name"

        register_contact(Nameless)


def test_the_toy_presses_stiffer_than_penalty_through_the_front_door(toy: str) -> None:
    """Built from a spec, it steps like any method, and its own parameter acts: stiffer
    springs leave less penetration than penalty's at the same press."""
    deepest = {}
    for method in ("penalty", toy):
        t = tissue.make_tissue(tissue.TissueSpec(mesh=623, contact=method, profile="paper"))
        position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
        t.reset(position, quat)
        for k in range(1, 26):
            step = t.step(position + 0.0004 * k * tissue.pressing_direction(quat), quat)
            assert step.status is tissue.StepStatus.OK, (method, k, step.status)
        deepest[method] = step.diagnostics.details["skin_vertex_penetration_m"]
        assert step.force_world_n @ tissue.pressing_direction(quat) < -0.1
    assert 0.0 < deepest[toy] < 0.6 * deepest["penalty"]


def test_the_toy_runs_through_compress(toy: str, tmp_path: Path) -> None:
    """``probegym compress --contact toy_stiff`` takes it by name."""
    import json

    from agents.cli import main

    out = tmp_path / "toy.json"
    argv = ["compress", "--mesh", "623", "--contact", toy, "--mode", "paper"]
    assert main([*argv, "--depths", "0.002,0.004", "--settle-steps", "2", "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["config"]["method"] == toy
    assert [d["status"] for d in record["depths"]] == ["ok", "ok"]
    assert record["depths"][-1]["force_normal_n"] > 0.05


def test_the_toy_runs_through_the_study(toy: str, tmp_path: Path) -> None:
    """The study takes it by name, its stability uses its bound, and the report names it by
    its label."""
    spec = StudySpec(
        methods=(toy,), configs=("paper",), levels=(623,), lesions=(1,),
        reference_level=623, depths_m=(0.002, 0.004),
    )  # fmt: skip
    result = run_study(spec, tmp_path, progress=False, log=lambda *_: None)
    (record,) = result.records
    assert record["method"] == toy and record["stability_percent"] == 100.0
    assert "ToyStiff" in (tmp_path / "stability.md").read_text()


def test_the_toy_runs_in_an_environment(toy: str) -> None:
    env = gym.make("probegym/BreastCompress-v0", contact=toy, mesh=623)
    try:
        env.reset(seed=0)
        for _ in range(5):
            _, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert np.isfinite(reward)
            if terminated or truncated:
                break
        assert env.unwrapped.tissue.contact == toy
    finally:
        env.close()


def test_a_spec_names_its_contact_once_and_the_build_goes_one_way(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The method is validated where the spec is made (its class kept as ``contact_type``),
    and resolving the spec and building the model look nothing up again."""
    import tissue.contact.registry as registry

    looked_up: list[object] = []
    lookup = registry.contact_method

    def counted(value: object) -> str:
        looked_up.append(value)
        return lookup(value)

    monkeypatch.setattr(registry, "contact_method", counted)
    spec = tissue.TissueSpec(mesh=623, contact="LM")
    assert looked_up == ["LM"]
    assert (spec.contact, spec.contact_type) == ("lm", tissue.contact.LagrangeContact)
    built = tissue.make_tissue(spec)
    assert looked_up == ["LM"]  # resolved and built from spec.contact_type
    assert built.resolved.contact_type is tissue.contact.LagrangeContact
    assert (built.resolved.method, built.contact) == ("lm", "lm")
    by_class = tissue.TissueSpec(mesh=623, contact=tissue.contact.PenaltyContact)
    assert (by_class.contact, by_class.contact_type) == ("penalty", tissue.contact.PenaltyContact)
    with pytest.raises(ConfigError, match="unknown contact method"):
        tissue.TissueSpec(mesh=623, contact=StiffeningPenalty)  # a class not registered
