"""XPBD tetrahedral tissue with probe contact: the paper's position-based baseline, with forces.

Tagliabue et al. (2020) compare their FE strategies against a position-based dynamics (PBD)
model run in NVIDIA FleX (their ref. [10]) and note that PBD "cannot provide an estimation of
the interaction forces". This package is that baseline as the fourth contact method
(:class:`PBDContact`, registered as ``"pbd"``) behind the
:class:`~tissue.contact.base.ContactModel` step interface, and it does report forces.

Model
-----
Extended PBD (XPBD; Macklin, Mueller & Chentanez 2016, "XPBD: position-based simulation of
compliant constrained dynamics", MIG '16) with substepping (Macklin et al. 2019, "Small steps
in physics simulation", SCA '19): a tissue step of ``tissue_dt`` is ``substeps`` substeps of
h = tissue_dt / substeps, each a prediction x~ = x + h v, ``iterations`` Gauss-Seidel sweeps
over all constraints (multipliers reset at each substep), and v = (x - x_prev) / h.

* Elasticity: the neo-Hookean constraint pair of Macklin & Mueller (2021, "A constraint-based
  formulation of stable neo-Hookean materials", MIG '21) on each linear tet, F = D_s D_m^-1,

      C_D = sqrt(tr(F^T F)),   alpha_D = 1 / (mu V)          (deviatoric)
      C_H = det F - gamma,     alpha_H = 1 / (lambda' V)      (hydrostatic)

  with lambda' = lambda + mu and gamma = 1 + mu / lambda': the stable neo-Hookean energy of
  :mod:`tissue.fem.material` (Smith, de Goes & Kim 2018) up to a constant, linear elasticity
  with the FE's Lame parameters at small strain. The pair is solved together as one 2 x 2
  system, so the rest state is a fixed point of every sweep. The compliances are multiplied by
  the calibrated ``deviatoric_compliance_scale`` and ``volume_compliance_scale``.
* Masses lumped (rho V / 4 per tet corner); fixed nodes have inverse mass 0. Damping is
  mass-proportional, v <- v exp(-damping_per_s h) each substep.
* Solver: deterministic Gauss-Seidel (numba). ``sweep_domains`` = 1 sweeps the tets in mesh
  order on one thread; 2 sweeps two node-disjoint domains on two threads, then the layer
  between them (:func:`two_domain_order`), the same bits on one thread or two.
* Contact: frictionless inequality constraints C_k = n_k . (p_k - p0_k) + d0_k >= 0 on the
  probe's tangent plane at the closest point of its exact SDF, for every contact point within
  ``contact_margin_m`` of the probe at its pose interpolated to the substep, each with its own
  multiplier lambda_k >= 0 and compliance ``contact_compliance_m_per_n`` (0 = hard). The
  points are the volume's free boundary nodes, points embedded in the boundary faces at most
  ``contact_spacing_m`` apart, and collision-surface vertices far from every boundary node
  (all of them with ``skin_contact``). After the global sweeps, ``contact_zone_iterations``
  sweeps of the tets around the contacted nodes spread the contact's correction so it does not
  invert a surface sliver.
* Force: every correction is M^-1 grad C^T d lambda, so over a substep the constraint force is
  grad C^T lambda / h^2 exactly (Macklin et al. 2016). The force reported on the probe is the
  step's average, f_k = -(1 / substeps) sum_s n_ks lambda_ks / h^2, at the contact point's
  end-of-step position; the same sums at the fixed nodes give ``PBDContact.support_force_n``, which
  equals the contact force at static equilibrium.

Profiles
--------
``paper`` (``PBDConfig()``, what a real-time engine runs): 10 substeps, 1 iteration, 3
contact-zone sweeps, damping 2/s, hard contact on the boundary nodes, mesh-order sweep.
``robust`` (``PBDConfig.for_profile("robust")``): 60 substeps (:data:`ROBUST_SUBSTEPS`), contact
points at most 4 mm apart, damping 30/s, the two-domain sweep, and a volume floor: no tet
ends a substep with det F below 0.1 (:data:`ROBUST_VOLUME_FLOOR`), the tets below it lifted
together by a hard one-sided constraint (diagnostics ``volume_floor_projections``). The front
door's robust profile also sets ``skin_contact`` (contact on every skin vertex).

Calibration
-----------
A few sweeps do not converge the implicit step, so the compliance scales are fitted by
:func:`~tissue.pbd.calibration.calibrate_pbd` against the FE simulator (robust, Newton,
stable neo-Hookean) on ``breast_phantom(4126)`` (E = 2850 Pa, nu = 0.49, lesions 4 x
stiffer): a 10 mm compression of the apex by the linear probe face at 0.01 m/s, then held
0.5 s; the objective is the relative force mismatch plus the lesion-displacement mismatch.
Paper profile: scales 0.5456 / 0.5073, force -0.20 %, lesion under the probe 9.7 %, all
lesions 30.2 % (unscaled: -38 % force). Robust profile: the volume scale is the material's
own (1.0) and the deviatoric scale is fitted to the force (1.16): force within 0.3 %, lesion
under the probe about 7 %, all lesions about 10 %. Scales hold for the mesh they were fitted
on: the front door (:mod:`tissue.spec`) refits the deviatoric scale for each mesh it runs
(:func:`~tissue.pbd.calibration.calibrated_pbd_config`, against robust LM, cached on disk).

Limitations
-----------
Not converged per step: outside the calibration's mesh, substeps and loading the scales need
refitting. The paper profile inverts surface tets under large deformation and on fine
meshes, and from about 26k tets it is not even stable at rest (round-off grows each substep);
20 substeps and more are. At 4,126 tets the robust profile fails the sliding hard case: the
lesion dragged under the probe snaps back faster than the FE's (which its backward Euler and
stiffness damping slow). The volume floor is a guard, not a cure. Frictionless only; forces
are step averages and include inertia; the probe must move less than about half its
thickness per substep or points tunnel; no stresses. See :class:`PBDContact`.

Modules: :mod:`~tissue.pbd.config` (settings), :mod:`~tissue.pbd.sweep` (the elastic sweep),
:mod:`~tissue.pbd.contact` (contact points and constraints), :mod:`~tissue.pbd.volume`
(volume floor and inversion check), :mod:`~tissue.pbd.substep` (a substep's start and end),
:mod:`~tissue.pbd.model` (:class:`PBDContact` and its :class:`SweepArrays`).

Kernels: the compiled kernels a step calls are public names of those modules (the package's
kernel API, each tested against a reference in numpy), called with a model's
:attr:`PBDContact.arrays`, e.g. ``sweep.project_tets``, ``contact.project_contacts``,
``volume.enforce_volume_floor``, ``substep.start_substep``. A step looks
``project_tets`` and ``project_tets_two_domains`` up on :mod:`tissue.pbd.sweep` each time it
runs, so replacing them there (``monkeypatch.setattr(tissue.pbd.sweep, "project_tets", f)``)
reaches a model already built.
"""

from tissue.pbd.config import (
    CALIBRATED_DEVIATORIC_COMPLIANCE_SCALE,
    CALIBRATED_VOLUME_COMPLIANCE_SCALE,
    CALIBRATION_FORCE_BOUND,
    CALIBRATION_LESION_BOUND,
    ROBUST_CONTACT_SPACING_M,
    ROBUST_DAMPING_PER_S,
    ROBUST_DEVIATORIC_COMPLIANCE_SCALE,
    ROBUST_SUBSTEPS,
    ROBUST_VOLUME_COMPLIANCE_SCALE,
    ROBUST_VOLUME_FLOOR,
    PBDConfig,
)
from tissue.pbd.model import PBDContact, SweepArrays
from tissue.pbd.sweep import two_domain_order
from tissue.pbd.volume import PARALLEL_SCREEN_TETS

__all__ = [
    "CALIBRATED_DEVIATORIC_COMPLIANCE_SCALE",
    "CALIBRATED_VOLUME_COMPLIANCE_SCALE",
    "CALIBRATION_FORCE_BOUND",
    "CALIBRATION_LESION_BOUND",
    "PARALLEL_SCREEN_TETS",
    "ROBUST_CONTACT_SPACING_M",
    "ROBUST_DAMPING_PER_S",
    "ROBUST_DEVIATORIC_COMPLIANCE_SCALE",
    "ROBUST_SUBSTEPS",
    "ROBUST_VOLUME_COMPLIANCE_SCALE",
    "ROBUST_VOLUME_FLOOR",
    "PBDConfig",
    "PBDContact",
    "SweepArrays",
    "two_domain_order",
]
