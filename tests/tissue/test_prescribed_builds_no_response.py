"""Prescribed displacement builds no collision response (issue: a scene simulates only the
effects it calls for): pressing with it never makes a compliance (Delassus) operator or runs
the LCP solver; under the paper profile no penalty springs exist either (the robust
profile's skin guard is a documented penalty term on the collision surface)."""

from __future__ import annotations

import pytest

import tissue
from tissue.contact import compliance
from tissue.contact.lagrange import response
from tissue.contact.penalty import PenaltyTerm


@pytest.mark.parametrize("profile", ["paper", "robust"])
def test_pressing_with_prescribed_builds_no_compliance_and_no_lcp(
    monkeypatch: pytest.MonkeyPatch, profile: str
) -> None:
    built: list[str] = []

    def refuse(name: str):  # type: ignore[no-untyped-def]
        def called(*args, **kwargs):  # type: ignore[no-untyped-def]
            built.append(name)
            raise AssertionError(f"prescribed displacement called {name}")

        return called

    monkeypatch.setattr(compliance.KeptCompliance, "__init__", refuse("KeptCompliance"))
    monkeypatch.setattr(response, "projected_gauss_seidel", refuse("projected_gauss_seidel"))
    guards = 0
    original = PenaltyTerm.__init__

    def counted(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        nonlocal guards
        guards += 1
        original(self, *args, **kwargs)

    monkeypatch.setattr(PenaltyTerm, "__init__", counted)
    t = tissue.make_tissue(mesh=623, contact="prescribed", profile=profile)
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    direction = tissue.pressing_direction(quat)
    t.reset(position, quat)
    for k in range(1, 26):  # 5 mm in
        step = t.step(position + 0.0002 * k * direction, quat)
    assert step.ok and float(-step.force_world_n @ direction) > 0.05
    assert built == []
    assert guards == (0 if profile == "paper" else 1)
