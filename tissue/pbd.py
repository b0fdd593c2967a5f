"""XPBD tetrahedral tissue with probe contact: the paper's position-based baseline, with forces.

Tagliabue et al. (2020) compare their FE strategies against a position-based dynamics (PBD)
model run in NVIDIA FleX (their ref. [10]); they note that PBD "cannot provide an estimation
of the interaction forces". This module is that baseline as a second tissue backend behind
the :class:`~tissue.contact.base.ContactModel` step interface, and it does report forces.

Model
-----
Extended PBD (XPBD; Macklin, Müller & Chentanez 2016, "XPBD: position-based simulation of
compliant constrained dynamics", MIG '16) with substepping (Macklin et al. 2019, "Small steps
in physics simulation", SCA '19): one tissue step of ``tissue_dt`` is ``substeps`` substeps
of h = tissue_dt / substeps, each a prediction x~ = x + h v, ``iterations`` Gauss-Seidel
sweeps over all constraints (multipliers reset to zero at each substep), and v = (x - x_prev)/h.

* Elasticity: the neo-Hookean constraint pair of Macklin & Müller (2021, "A constraint-based
  formulation of stable neo-Hookean materials", MIG '21) on each linear tet, with
  F = D_s D_m^-1:

      C_D = sqrt(tr(F^T F)),   alpha_D = 1 / (mu V)          (deviatoric)
      C_H = det F - gamma,     alpha_H = 1 / (lambda' V)      (hydrostatic)

  whose XPBD energy C^2 / (2 alpha) summed is the stable neo-Hookean energy of
  :mod:`tissue.fem.material` (Smith, de Goes & Kim 2018) up to a constant: lambda' = lambda + mu and
  gamma = 1 + mu / lambda', so the small-strain response is linear elasticity with the FE's
  Lamé parameters (mu, lambda) exactly, and an inverted tet (det F < 0) is pushed back. The two
  constraints of a tet are solved together as one 2 x 2 system (the coupled solve of that
  paper): at rest their forces cancel exactly, so the rest state is a fixed point of every
  sweep (no drift), which separate projections would not give. Compliances are multiplied by
  the calibrated ``deviatoric_compliance_scale`` and ``volume_compliance_scale`` (below).
* Masses: lumped, rho V / 4 per tet corner, from the region densities. Fixed nodes
  (``mesh.fixed_nodes``) get inverse mass 0 and never move.
* Damping: mass-proportional, v <- v exp(-damping_per_s h) each substep.
* Solver: Gauss-Seidel (numba), deterministic. The paper configuration sweeps the tets in mesh
  order on one thread. The robust configuration (``sweep_domains`` = 2) sweeps two
  node-disjoint domains at once, one per thread, then the one-tet layer between them (see
  :func:`two_domain_order`): a Gauss-Seidel sweep in that order, the same bits on one thread
  or two, with one parallel region per sweep (graph colouring would need a barrier per
  colour, a few dozen per sweep). The step renumbers tets and nodes so each domain's data is
  contiguous: in mesh numbering the two threads wrote to shared cache lines and the sweep
  was slower on two threads than on one (1.86 against 1.68 ms at 26,220 tets); renumbered,
  0.93 ms. The separator holds 16 % of the tets at 4,126 tets, 8 % at 26,220 and 4 % at
  176,506. Below 3,000 unknowns (4,126 tets and coarser) the step runs on one thread anyway
  (``tissue.sim.solvers.SERIAL_STEP_UNKNOWNS``): there, waking the second thread each sweep costs
  about what it saves (0.22 ms a sweep on one thread, 0.21 on two with the passive waiting
  ``tissue`` sets by default, 0.14 with spinning workers, ``OMP_WAIT_POLICY=active``, which
  slow everything else on a busy machine: see ``tissue/__init__.py``).
  The sweep kernel is compiled with fused multiply-adds and reassociated sums
  (:data:`_SWEEP_FASTMATH`; not "no NaN", so a diverging state is still caught): a sweep is 10 %
  faster (226 -> 204 us at 4,126 tets). Over 60 steps of the apex press at 4,126 and 26,220
  tets, in both configurations, the forces stay within 6e-13 of the largest and the lesions
  within 6e-13 m of the strict IEEE order's, and the same steps end ``ok`` or ``inverted``.
  The kernel is written out in scalars (no scratch arrays, no helpers taking arrays): 211-223
  -> 172-180 us a sweep at 4,126 tets, 1,450-1,480 -> 1,175-1,220 us at 26,220 (300 sweeps
  on a captured state, median of five, three runs), within 5e-16 m of the array form after
  300 sweeps; over the same 60 steps forces within 6e-13 N and lesions within 3e-13 m of it,
  the same statuses. A test holds it to the projection written with numpy's matrix operations.
  The paper configuration keeps mesh order because at 10 substeps the order moves the result
  (4,126 tets, 40 steps of ``bench contact``'s apex press: 0.729 N in mesh order, 0.900 N in
  two-domain order) and its calibration was fitted in mesh order; at 60 substeps (robust) the
  order moves that force by 0.05 %, and 0.01 % at 26,220 tets.
* Contact: the points contact acts on are the volume's free boundary nodes, plus any
  collision-surface vertex (embedded barycentrically in the volume) farther than the median
  boundary edge from every boundary node, so a coarse volume under a fine collision surface
  leaves no holes (none of the default phantom levels 623..26220 nor the published scene needs
  one). Not the collision surface itself: each of its points is embedded in one tet, often a
  small one of a finer volume, and projecting it moves that tet's 4 nodes, interior ones
  included; the boundary nodes match the FE reference, which holds those nodes (see
  Calibration). With ``contact_spacing_m`` > 0, points between the boundary nodes too,
  embedded in their boundary faces (a face point moves only that face's 3 nodes), so that
  none are farther apart than that: the coarse levels' boundary edges are 22 mm (1,363
  tets), 14 mm (4,126) and 4.7 mm (26,220) long (medians), and a 13 mm wide face pressing
  between two nodes sinks into the faces between (1,363 tets, lesions 10 x stiffer: at 20 mm
  the tissue closed over the probe, the force fell from 2.2 N to 0 and the lesion under it
  jumped 15.6 mm). Penetration is measured on these same points. Each
  substep, the probe is placed at a pose interpolated between the previous step's pose and the
  new one (linear in position, nlerp in orientation), and every point within
  ``contact_margin_m`` of it (signed distance from the probe's exact SDF, at the predicted
  positions) gets a frictionless inequality constraint on the probe's tangent plane at its
  closest point,

      C_k = n_k . (p_k - p0_k) + d0_k >= 0,   p_k = sum_i w_ki x_i,

  with its own multiplier lambda_k >= 0 (projected: clamped after each update) and compliance
  ``contact_compliance_m_per_n`` (0 = hard). The gradient with respect to node i is w_ki n_k, so
  the generalised inverse mass is sum_i w_ki^2 / m_i. Contacts are projected after the tets in
  every sweep, so the step ends with the contact constraints satisfied.
* Contact zone: after the ``iterations`` global sweeps, ``contact_zone_iterations`` more sweeps
  project only the tets incident to a contacted node, then the contacts again. A single global
  sweep leaves the contact's correction where the contact put it, and a surface sliver there
  (the published scene's mesh has boundary tets of quality 0.02 to 0.04, about 0.3 mm thick)
  is inverted by it; the local sweeps spread the correction into the neighbouring tets for
  about 5 % of a step's cost. Without them the published scene reports INVERTED from about
  2 mm past contact on tumour 1's path, with either point set.

Contact force (beyond the paper)
--------------------------------
In XPBD the constraint force over a substep of length h is f = grad C^T lambda / h^2
(Macklin et al. 2016, eq. 9 ff.), with lambda the multiplier accumulated over that substep's
iterations. Indeed every position correction is M^-1 grad C^T d lambda, so
M (x - x~) / h^2 = sum_c grad C_c^T lambda_c / h^2 holds exactly, converged or not: these are
the forces that changed the momentum. The impulse of contact k on the tissue over substep s is
therefore n_ks lambda_ks / h, and over the tissue step the impulse is the sum over substeps.
The reported force on the probe is minus the step's impulse over tissue_dt:

    f_k(probe) = -(1 / tissue_dt) sum_s n_ks lambda_ks / h
               = -(1 / substeps) sum_s n_ks lambda_ks / h^2,

the time average over the step (not the value at its end), applied at the contact point's
position at the end of the step. The same bookkeeping on the tet multipliers at the fixed nodes
gives the support force (diagnostics ``support_force_n``, the force the fixed base applies to
the tissue); by momentum balance it equals the contact force on the probe at static
equilibrium, which the tests check.

Calibration
-----------
XPBD with a few Gauss-Seidel sweeps does not converge the implicit step: the effective stiffness
and the volume preservation fall short of the material's, so the compliances carry two scales,
calibrated once by :func:`~tissue.pbd_calibration.calibrate_pbd` against the FE simulator
(``TissueSimulator``, robust mode: Newton, stable neo-Hookean) on the default phantom
(``breast_phantom(4126)``, tissue E = 2850 Pa, nu = 0.49, lesions 4 x stiffer): a 10 mm
compression of the apex along -z by the linear probe face at 0.01 m/s, then held 0.5 s. The FE side
prescribes z (frictionless) on every boundary node under the face's outline once the face reaches
it; the PBD side presses a :class:`~tissue.probe.LinearProbeFace`. The objective is the relative
mismatch of the normal reaction force plus that of the lesion landmark displacements (the norm of
the difference of the displacement vectors over the norm of the FE displacements, all lesions),
minimised by Nelder-Mead over the log scales from (1, 1). Measured with the default config (10
substeps, 1 iteration, 3 contact-zone sweeps, damping 2/s, hard contact, the boundary nodes as
contact points), 41 PBD runs, 15 s in all:

    =============================  ==========================  ==========================
    quantity                       FE (robust, prescribed)     PBD (calibrated)
    =============================  ==========================  ==========================
    scales (deviatoric, volume)    --                          0.5456, 0.5073
    reaction force at 10 mm        1.0054 N                    1.0034 N (-0.20 %)
    lesion 1 (under the probe)     (-0.11, -0.28, -7.00) mm    (-0.71, -0.61, -7.02) mm
                                                               (9.7 % of |u_FE|)
    all 10 lesions                 --                          |u_PBD - u_FE| / |u_FE|
                                                               = 30.2 %
    step time                      3.8 ms                      4.2 ms
    =============================  ==========================  ==========================

With unscaled compliances (1, 1) the same run gives -38.0 % force and 25.8 % lesion mismatch:
one sweep per substep is too soft, and the fit stiffens both constraints. (The lesion
mismatch was 10.2 % with the lesion layout before the study's flank lesions were moved
inwards; most of it is in the lesions beside the probe, which moved closer to it. With the
collision-surface vertices as contact points instead, the fit needs a volume scale of 4.7 and
still leaves 15.0 % lesion mismatch.) The slow test re-runs
:func:`~tissue.pbd_calibration.calibrate_pbd` and requires the stored scales to stay within
:data:`CALIBRATION_FORCE_BOUND` and :data:`CALIBRATION_LESION_BOUND`.

Robust configuration
--------------------
Ten substeps are what a real-time PBD engine runs, and they are not converged under large
deformation: on level 4126 every hard case but the tilted and edge presses fails (a surface
tet inverts 19-52 % into the case), and the 105k- and 176k-tet levels invert a
surface tet 6-8 mm in (one Gauss-Seidel sweep per substep moves a contact correction only a
few elements into a fine mesh). On the fine levels the 10-substep calibration is not even
stable at rest: with nothing touching, round-off grows ~4 x per substep until nodes have
moved 0.034 mm (26,220 tets, where it saturates within three steps) or 0.7 mm with a tet
inverted (105,004 tets, two steps); 12,861 tets stay at rest (1e-14 mm after 12 steps). It is
the stiffer deviatoric scale (0.5456 with volume scale 1 blows up the same way; 1 with
0.5073 grows slowly), and 20 substeps are stable; the cause is presumably the pre-stressed
|F| constraint, whose geometric stiffness one projection per substep ignores (not verified).
``PBDConfig.for_mode("robust")`` runs :data:`ROBUST_SUBSTEPS`
= 60 substeps (Macklin et al. 2019: substeps converge better than iterations), calibrated the
same way, with contact points at most :data:`ROBUST_CONTACT_SPACING_M` = 4 mm apart: the
volume compliance is the material's own (scale 1) and the deviatoric scale is fitted to the
force (``tissue.pbd_calibration.calibrate_pbd(..., fit=False)`` at 1.06, 1.08, 1.10, 1.15
and 1.16): 1.16, force -0.30 %, lesion 1 6.8 %, all lesions 9.4 % (30.2 % at 10 substeps). The
two-scale fit from (1, 1) (run with 3 ms of damping, below) landed on a softer volume (1.013 and
1.511, all lesions 9.6 %): a volume scale of 1 keeps the material's own compressibility for nearly
the same match. On the boundary nodes alone the two-scale fit gives 1.024 and
0.533 and 12.2 %. The points between nodes cure the tissue closing over the probe on the
1,363-tet level (above); with them and a volume scale of 1 the 30 mm hold there no longer
jitters (with them and the previous scales, 0.9994 and 0.946, a lateral lesion still moved
0.4-1.6 mm per step while the probe held still). Tried and left out:
Rayleigh stiffness damping as XPBD's constraint damping (Macklin et al. 2016, eq. 26,
gamma = r_K / h) of 3 ms also stopped that jitter but
inverted a tet on fine_105k at 98 %, and 10 or 30 ms softened the force at 30 mm by 27 and
46 % (with one sweep per substep the damping slows the elastic correction too); 40 substeps,
on the nodes alone, inverted a tet at 28 mm on lesion 1's path at level 4126. Cost (``probegym
bench contact --methods pbd``, two alternating runs, idle machine): 21.3-21.6 ms per step at
4,141 tets (3.2-3.3 ms at 10 substeps), 125-129 ms at 26,854, 936 ms at 173,229 (one run).
The sweeps' own kernel is two thirds of it at 4,141 tets and four fifths at 26,854
(cProfile); each substep's contact detection, prediction and velocity update run compiled
(:func:`_points_near`, :func:`_predict`, :func:`_update_velocity`; the probe's SDF too),
which took the robust step from 37.4-37.8 to those 21.3-21.6 ms at 4,141 tets, 159-162 to
125-129 ms at 26,854 and 989 to 936 ms at 173,229, bit for bit the same trajectories. A
scalar rewrite of the sweep kernel (no scratch arrays) gained 9 % a sweep (1.58 -> 1.44 ms
at 26,854 tets, the same bits) and was left out then (it came back later, below). The
two-domain sweep (``sweep_domains`` = 2, see Solver above) and the volume floor's two-thread
screen from 100,000 tets then took the
robust step (``probegym bench contact --methods pbd --modes robust``, two alternating runs each
of the code before and after, a busier machine) from 127.6 / 129.1 to 96.1 / 94.9 ms at
26,854 tets, 66.1 / 65.9 to 53.9 / 53.6 ms at 12,971, and 970 to 478 ms at 173,229 (one run
each), 38.3 / 37.4 to 36.3 / 36.8 ms at 6,966; from 4,141 tets down the step runs on one
thread and is unchanged within the noise (4,141 tets: 23.2 / 23.7 against 22.6 / 24.0 ms).
Forces and lesion displacements at 10 mm agree to 0.1 %, and the calibration's mismatch
moved from -0.27 % force, 6.8 % lesion 1 and 9.5 % all lesions to -0.22 %, 6.9 % and 9.6 %.
Then a substep's work outside the full sweep went down to six compiled calls from about
fifteen calls (start, the ball and probe-frame box of :func:`_points_near`, the exact SDF on
what they keep, the contact-zone sweeps with their contacts, the volume floor, end; bit for
bit the same) and the sweep took its floating-point
freedoms (Solver, above): robust step 21.5 / 21.7 / 23.3 -> 18.9 / 18.9 / 19.0 ms at 4,141
tets, 90.9 / 92.0 / 92.2 -> 80.0 / 81.4 / 81.7 ms at 26,854, 6.7-7.1 -> 5.3 ms at 571; the
paper configuration's 3.3-3.6 -> 2.9-3.0 ms at 4,141 and 19.1-20.0 -> 17.1-17.9 ms at 26,854
(``probegym bench contact --levels 623,4126,26220 --methods pbd``, three alternating runs
each of the code before and after; the same forces to 1e-4 N, the same step statuses; a full
``bench contact`` run on that code gave 20.06 ms at 4,141 tets). With the substep poses then
computed at once per step (bit for bit the same), three more alternating runs on a busier
machine: 22.7 / 23.4 / 24.3 -> 19.3 / 19.5 / 19.8 ms at 4,141 tets, 94.0-95.8 -> 80.6-84.0 ms
at 26,854; and with the face's SDF in one pass, three more on a busier machine still: 26.1 /
27.3 / 22.9 -> 20.8 / 21.1 / 20.4 ms at 4,141 tets: at issue 5's 20 ms line, under it in
six runs of ten. With the sweep kernel written out in scalars (Solver, above), three more
alternating runs (``--levels 623,4126,26220 --methods pbd``): robust 21.2 / 20.2 / 21.4 ->
17.2 / 18.3 / 17.7 ms at 4,141 tets, 83.4 / 83.9 / 84.8 -> 76.2 / 76.2 / 74.8 ms at 26,854,
5.6-6.2 -> 5.0-5.2 ms at 571; paper 3.2-3.3 -> 2.6-2.8 ms at 4,141 and 17.8-19.0 -> 15.0-16.0
ms at 26,854; the same forces to 1e-12 N. Under the 20 ms target at 4,141 tets in every run.

Damping: the robust configuration damps velocities at :data:`ROBUST_DAMPING_PER_S` = 30/s
(the paper configuration keeps 2/s). At 2/s the tissue rang after the sudden release (1,363
tets: a landmark still moving 2-6 mm per step, period ~2-3 steps, half a second later),
where the FE's Rayleigh stiffness damping (r_K = 0.1 s) lets the tissue creep back (a
landmark's step shrinking ~13 % per step from 2.8 mm); at 30/s the ring has died within 10
steps (< 0.5 mm per step). Mass damping removes momentum the contact must then supply, so
the force while the probe moves rises a little (deep_30mm at 4,126 tets, 6 mm in: 0.326
against 0.317 N), while the settled forces are unchanged (1.002 / 3.110 / 4.642 / 6.467 N
against 1.002 / 3.111 / 4.639 / 6.469 N at 10 / 20 / 25 / 30 mm) and the calibration's
mismatch barely moves (force -0.27 % against -0.30 %, all lesions 9.55 % against 9.38 %;
the scales were kept); the holds settle sooner (that run: 200 steps against 354).
Measured with it (``probegym hard-cases --methods pbd --config robust --level 1363`` and
``--level 4126``): every case passes at 1,363 tets, and at 4,126 all but the sliding: there
lesion 1, dragged 9 mm sideways under the sliding probe, snaps back as the probe's edge
passes over it: 3.45 mm in one step when first measured, 2.12 and then 3.12 mm in two steps
on the code of 2026-11-26 (2.12 mm already fails the check). The FE snaps there too (LM: 8.7
-> 3.5 mm over 16 steps, at most 0.78 mm in a step), slowed by its stiffness damping; mass
damping does not slow a snap like that (100/s: still 2.19 mm in one step). Nor does the FE's
own stiffness damping, tried as a velocity pass after each substep, (M + h r_K K_rest) v' =
M v with the FE's r_K = 0.1 s and rest stiffness (which leaves the projection, and so the
calibrated stiffness, alone; the constraint damping above did not): one Gauss-Seidel sweep of it a
substep gave 1.89 mm (median step 49.6 against 45.6 ms), three 1.66 mm (63 ms), ten passed
(102 ms), and the exact solve (a factorisation kept for the run) 1.23 mm at step 161 against
the bound's 1.20 (103 ms); every sixth substep with 6 h r_K, 2.35 / 1.85 / 1.36 mm for 5 and
10 sweeps and the exact solve (4,126 tets, one run each, loaded machine). So even the FE's
damping, solved exactly, leaves the PBD's snap above the FE's 0.78 mm: the FE's backward
Euler at h = 20 ms also damps that mode numerically, which 60 substeps of 0.33 ms do not;
and an exact solve a substep would be 60 triangular solve pairs a step at 176,506 tets (45
ms each). Left out, and the sliding case stays a documented failure for PBD at 4,126 tets.

Volume floor: the robust configuration keeps every tet's det F >= :data:`ROBUST_VOLUME_FLOOR`
= 0.1 (the ratio below which the FE's inversion barrier acts) with a hard one-sided
constraint projected after each substep's sweeps (:func:`_enforce_volume_floor`; the
diagnostics count its projections, ``volume_floor_projections``). Why: the study's robust
cell at 26,220 tets, lesion 8, ended INVERTED at 83 %: the level's worst-shaped tet (a sliver
of quality 0.079, 6-7 mm from the probe, no boundary node) flattened by 1-2 % per step from J =
0.63 (step 100) to below 0 (step 158) while its neighbours sat at J = 0.68-0.88, i.e. XPBD's one
sweep per substep had not converged the volume there. Projecting the floor inside the tet's
own projection did nothing (its neighbours pushed it back within the same sweep); after the
sweeps it holds the sliver at 0.1 and the cell completes (100 %), with a second tet reaching
the floor later. The tets below the floor are lifted together (one Newton step on all
their constraints, repeated while any is below): lifted one at a time, two slivers sharing a
face undid each other's lift, and the published scene's 105,004-tet re-mesh (lesion 1, pose
4) ended a step at det F = 0.086 and inverted (-0.006) the next, at 96.5 % of the
experiment; lifted together, those steps end at 0.1000 and 0.1057. It is a guard, not a
cure: a tet held at the floor is far from the FE's answer there. Where no tet reaches the
floor the results are bit-identical; the screening pass costs 3-8 % per step (measured 32.0
against 30.9 ms at 4,126 tets and 153 against 142 ms at 26,220, robust, one run each).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields
from typing import Any

import numba as nb
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from tissue.contact.base import ContactMethod, ContactModel, SurfacePoints
from tissue.errors import ConfigError, TissueInputError, check_setting_names
from tissue.fem.material import TissueMaterials
from tissue.mesh import TetMesh, boundary_faces, triangle_grid
from tissue.probe import ProbeShape, unit_quat_to_matrix
from tissue.status import StepStatus

# Calibrated compliance scales (see the module docstring and
# tissue.pbd_calibration.calibrate_pbd): the paper configuration (10 substeps, the defaults) ...
CALIBRATED_DEVIATORIC_COMPLIANCE_SCALE = 0.5456
CALIBRATED_VOLUME_COMPLIANCE_SCALE = 0.5073
# ... and the robust one (ROBUST_SUBSTEPS substeps, contact points between the boundary nodes).
ROBUST_SUBSTEPS = 60
ROBUST_CONTACT_SPACING_M = 0.004
ROBUST_DEVIATORIC_COMPLIANCE_SCALE = 1.16
ROBUST_VOLUME_COMPLIANCE_SCALE = 1.0
# Mass-proportional damping of the robust configuration [1/s] (see "Robust configuration").
ROBUST_DAMPING_PER_S = 30.0
# The robust configuration's volume floor: no tet ends a substep with det F below it (to
# first order; the FE's inversion barrier acts below the same ratio; see "Volume floor").
ROBUST_VOLUME_FLOOR = 0.1
# Rounds of the floor's joint projection per substep (each a Newton step on every tet below
# the floor; see _enforce_volume_floor), and how far above the floor it aims (relative).
_FLOOR_ROUNDS = 8
_FLOOR_MARGIN = 1e-3
# At most this many tets are lifted together (one dense solve); more are taken in blocks.
_FLOOR_BLOCK = 64
# From this many tets a step on two threads screens for the volume floor on both first: waking
# the second thread costs 70-80 us here, more than it saves below that (a screen of 26,854
# tets: 0.11 ms on one thread, 0.12 on two; 173,229 tets: 0.87 against 0.61 ms).
PARALLEL_SCREEN_TETS = 100_000

# Mismatch bounds the calibrated defaults must meet on the default phantom (measured -0.20 %
# and 30.2 %; the margin covers platform round-off in the FE reference and Nelder-Mead).
CALIBRATION_FORCE_BOUND = 0.03
CALIBRATION_LESION_BOUND = 0.32

# A deviatoric constraint whose sqrt(I_C) falls below this is skipped: its gradient F / |F| is
# undefined at F = 0 (a tet collapsed to a point), and the hydrostatic constraint restores it.
_MIN_DEVIATORIC_NORM = 1e-9
# A 2 x 2 system whose determinant is below this fraction of the product of its diagonal is
# treated as singular (both gradients parallel with zero compliance) and skipped.
_SINGULAR_FRACTION = 1e-14


@dataclass(frozen=True)
class PBDConfig:
    """Settings of the XPBD tissue (see the module docstring for the model).

    Attributes:
        tissue_dt: the tissue time step [s] (0.02 s as the paper), > 0 and <= 1.
        substeps: substeps per tissue step (>= 1); each is one prediction and ``iterations``
            Gauss-Seidel sweeps. Substeps converge far better than iterations (Macklin et al.
            2019), so keep ``iterations`` at 1 and raise this for stiffness.
        iterations: Gauss-Seidel sweeps per substep (>= 1).
        contact_zone_iterations: extra sweeps per substep over only the tets incident to a
            contacted node, each followed by the contacts (>= 0; 0 lets hard contact invert
            surface slivers, see the module docstring).
        deviatoric_compliance_scale: multiplies alpha_D = 1 / (mu V) (> 0); the calibrated
            value makes the PBD force match the FE at 10 mm on the default phantom.
        volume_compliance_scale: multiplies alpha_H = 1 / (lambda' V) (> 0); calibrated with
            the deviatoric scale on the lesion displacements.
        damping_per_s: mass-proportional velocity damping rate [1/s] (>= 0; the robust
            configuration's is :data:`ROBUST_DAMPING_PER_S`).
        contact_compliance_m_per_n: compliance of a contact constraint [m/N] (>= 0; 0 = hard,
            no penetration once converged).
        contact_margin_m: points closer to the probe than this [m] (>= 0) get a contact
            constraint for the substep; it only activates if the point would penetrate.
        friction: Coulomb friction coefficient; only 0 (frictionless, as the paper) is
            implemented.
        contact_spacing_m: the largest distance between contact points on the boundary [m]
            (>= 0): points are added between boundary nodes farther apart, embedded in their
            faces (0: the nodes only, as a particle engine; see the module docstring).
        volume_floor: the smallest volume ratio det F a tet may end a substep with, in
            [0, 1) (0 = none, as a particle engine; the robust configuration's is
            :data:`ROBUST_VOLUME_FLOOR`): a hard one-sided constraint det F >= floor,
            projected once after each substep's sweeps.
        sweep_domains: 1 sweeps the tets in mesh order on one thread; 2 sweeps them as two
            node-disjoint domains on two threads, then the layer between them (see
            :func:`two_domain_order`; the same result whatever the thread count). The robust
            configuration's is 2; the paper configuration keeps 1, the order its calibration
            was fitted with (with its 10 unconverged substeps the order moves the force).
        skin_contact: every collision-surface vertex is a contact point too (not only those
            far from the boundary nodes): on a coarse volume the finer skin bulges between
            the boundary nodes, and a probe edge pressing there would otherwise sink into it
            (2-3 mm at 623-1,303 tets when rocked 20 degrees). The front door's robust
            profile sets it.
    """

    tissue_dt: float = 0.02
    substeps: int = 10
    iterations: int = 1
    contact_zone_iterations: int = 3
    deviatoric_compliance_scale: float = CALIBRATED_DEVIATORIC_COMPLIANCE_SCALE
    volume_compliance_scale: float = CALIBRATED_VOLUME_COMPLIANCE_SCALE
    damping_per_s: float = 2.0
    contact_compliance_m_per_n: float = 0.0
    contact_margin_m: float = 0.001
    friction: float = 0.0
    contact_spacing_m: float = 0.0
    volume_floor: float = 0.0
    sweep_domains: int = 1
    skin_contact: bool = False

    def __post_init__(self) -> None:
        _check_number("tissue_dt", self.tissue_dt, "a time step in seconds in (0, 1] (paper: 0.02)")
        if not 0.0 < self.tissue_dt <= 1.0:
            raise ConfigError(
                f"tissue_dt must be a time step in seconds in (0, 1]; got {self.tissue_dt!r} "
                "(the paper uses 0.02)"
            )
        for name, smallest in (
            ("substeps", 1),
            ("iterations", 1),
            ("contact_zone_iterations", 0),
            ("sweep_domains", 1),
        ):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, np.integer))
                or value < smallest
            ):
                raise ConfigError(f"{name} must be an integer >= {smallest}; got {value!r}")
            object.__setattr__(self, name, int(value))
        if self.sweep_domains > 2:
            raise ConfigError(
                f"sweep_domains must be 1 (mesh order, one thread) or 2 (two domains on two "
                f"threads); got {self.sweep_domains!r}"
            )
        for name in ("deviatoric_compliance_scale", "volume_compliance_scale"):
            value = getattr(self, name)
            _check_number(name, value, "a positive multiplier of the material's compliance")
            if value <= 0.0:
                raise ConfigError(
                    f"{name} must be a positive multiplier of the material's compliance; "
                    f"got {value!r} (1 = the material itself)"
                )
        for name, unit in (
            ("damping_per_s", "1/s"),
            ("contact_spacing_m", "m; 0 = the boundary nodes only"),
            ("contact_compliance_m_per_n", "m/N; 0 = hard contact"),
            ("contact_margin_m", "m"),
        ):
            value = getattr(self, name)
            _check_number(name, value, f"a number >= 0 [{unit}]")
            if value < 0.0:
                raise ConfigError(f"{name} must be >= 0 [{unit}]; got {value!r}")
        _check_number("volume_floor", self.volume_floor, "a volume ratio in [0, 1)")
        if not 0.0 <= self.volume_floor < 1.0:
            raise ConfigError(
                f"volume_floor must be a volume ratio in [0, 1) (0 = none); got "
                f"{self.volume_floor!r} (the robust configuration uses {ROBUST_VOLUME_FLOOR})"
            )
        _check_number("friction", self.friction, "0 (frictionless)")
        if self.friction != 0.0:
            raise ConfigError(
                f"friction = {self.friction!r} is not supported by the PBD backend; only 0 "
                "(frictionless contact, as in the paper) is implemented"
            )

    @classmethod
    def for_mode(cls, mode: str) -> PBDConfig:
        """The calibrated settings of a study configuration: ``paper`` (the defaults, 10
        substeps, a FleX-like baseline) or ``robust`` (:data:`ROBUST_SUBSTEPS` substeps with
        their own calibrated scales; about 6 x the time per step, see the module docstring).
        """
        name = str(getattr(mode, "value", mode))
        if name == "paper":
            return cls()
        if name == "robust":
            return cls(
                substeps=ROBUST_SUBSTEPS,
                contact_spacing_m=ROBUST_CONTACT_SPACING_M,
                deviatoric_compliance_scale=ROBUST_DEVIATORIC_COMPLIANCE_SCALE,
                volume_compliance_scale=ROBUST_VOLUME_COMPLIANCE_SCALE,
                damping_per_s=ROBUST_DAMPING_PER_S,
                volume_floor=ROBUST_VOLUME_FLOOR,
                sweep_domains=2,
            )
        raise ConfigError(f"unknown PBD configuration {mode!r}; choose 'paper' or 'robust'")

    @classmethod
    def from_overrides(cls, **overrides: Any) -> PBDConfig:
        """Build from keyword overrides, rejecting unknown keys with the valid ones listed."""
        check_setting_names(overrides, (f.name for f in fields(cls)), "PBD")
        return cls(**overrides)

    @property
    def substep_dt(self) -> float:
        """The substep h = tissue_dt / substeps [s]."""
        return self.tissue_dt / self.substeps


def _check_number(name: str, value: object, expected: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        raise ConfigError(f"{name} must be {expected}; got {value!r}")
    if not math.isfinite(float(value)):
        raise ConfigError(f"{name} must be finite ({expected}); got {value!r}")


# ----------------------------------------------------------------------------------------
# Numba kernels


@nb.njit(cache=True, inline="always")
def _deformation(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    t: int,
    f: NDArray[np.float64],
    cof: NDArray[np.float64],
) -> float:
    """Fill ``f`` with tet ``t``'s deformation gradient F = Ds Dm^-1 and ``cof`` with its
    cofactor d det F / dF (both (3, 3)); return det F."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    # Ds columns are the edges from node 0.
    for a in range(3):
        e1 = x[i1, a] - x[i0, a]
        e2 = x[i2, a] - x[i0, a]
        e3 = x[i3, a] - x[i0, a]
        for b in range(3):
            f[a, b] = e1 * dm_inv[t, 0, b] + e2 * dm_inv[t, 1, b] + e3 * dm_inv[t, 2, b]
    # Column b of the cofactor is the cross product of the other two columns of F.
    for b in range(3):
        c1 = (b + 1) % 3
        c2 = (b + 2) % 3
        cof[0, b] = f[1, c1] * f[2, c2] - f[2, c1] * f[1, c2]
        cof[1, b] = f[2, c1] * f[0, c2] - f[0, c1] * f[2, c2]
        cof[2, b] = f[0, c1] * f[1, c2] - f[1, c1] * f[0, c2]
    return f[0, 0] * cof[0, 0] + f[1, 0] * cof[1, 0] + f[2, 0] * cof[2, 0]


@nb.njit(cache=True, inline="always")
def _edge_determinant(x: NDArray[np.float64], tets: NDArray[np.int64], t: int) -> float:
    """det Ds of tet ``t`` [m^3]: the triple product of its edges from node 0 (6 x its signed
    volume)."""
    i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
    a0, a1, a2 = x[i1, 0] - x[i0, 0], x[i1, 1] - x[i0, 1], x[i1, 2] - x[i0, 2]
    b0, b1, b2 = x[i2, 0] - x[i0, 0], x[i2, 1] - x[i0, 1], x[i2, 2] - x[i0, 2]
    c0, c1, c2 = x[i3, 0] - x[i0, 0], x[i3, 1] - x[i0, 1], x[i3, 2] - x[i0, 2]
    return a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)


@nb.njit(cache=True, inline="always")
def _node_gradients(
    d_dF: NDArray[np.float64],
    dm_inv: NDArray[np.float64],
    t: int,
    scale: float,
    out: NDArray[np.float64],
) -> None:
    """Node gradients of a constraint of tet ``t`` with dC/dF = scale * ``d_dF``, (4, 3):
    row j = 1..3 is (dC/dF) Dm^-T column j, row 0 minus their sum."""
    for j in range(3):
        for a in range(3):
            s = 0.0
            for b in range(3):
                s += d_dF[a, b] * dm_inv[t, j, b]
            out[j + 1, a] = s * scale
    for a in range(3):
        out[0, a] = -(out[1, a] + out[2, a] + out[3, a])


# The sweep's floating-point freedoms: fused multiply-adds and reassociated sums (and no
# signed zeros), never "no NaN" or "no Inf", so a diverging state still reaches the step's
# finiteness check. Measured on the 4,126-tet robust apex press, one full sweep: 226 -> 204
# us; positions within 4e-16 m of the strict IEEE order after a sweep.
_SWEEP_FASTMATH = {"contract", "reassoc", "nsz"}


@nb.njit(cache=True, fastmath=_SWEEP_FASTMATH)
def _project_tets(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    tet_ids: NDArray[np.int64],
) -> None:
    """One Gauss-Seidel sweep of the coupled neo-Hookean constraint pair over ``tet_ids``.

    Args:
        x: node positions [m], (node_count, 3), updated in place.
        inv_mass: inverse lumped masses [1/kg], (node_count,), 0 at fixed nodes.
        tets: (tet_count, 4). dm_inv: inverse rest edge matrices [1/m], (tet_count, 3, 3).
        alpha_dev, alpha_hyd: time-scaled compliances alpha / h^2 [1/(kg m^2)] (the
            constraints are dimensionless, alpha in 1/J), (tet_count,).
        gamma: rest offset 1 + mu / lambda' of the hydrostatic constraint, (tet_count,).
        lam_dev, lam_hyd: this substep's multipliers [kg m^2], (tet_count,), updated.
        support: per-node sum of grad C * d lambda at fixed nodes, (node_count, 3), updated;
            divided by h^2 it is the elastic force on the fixed nodes.
        tet_ids: the tets to project, in this order (all of them, or the contact zone's).
    """
    # Written out in scalars, which stay in registers: the same sweep with (4, 3) scratch
    # arrays and the helpers _deformation / _node_gradients / _apply took 211-223 against
    # 172-180 us at 4,126 tets (see the module docstring, Solver).
    for t in tet_ids:
        i0, i1, i2, i3 = tets[t, 0], tets[t, 1], tets[t, 2], tets[t, 3]
        d00, d01, d02 = dm_inv[t, 0, 0], dm_inv[t, 0, 1], dm_inv[t, 0, 2]
        d10, d11, d12 = dm_inv[t, 1, 0], dm_inv[t, 1, 1], dm_inv[t, 1, 2]
        d20, d21, d22 = dm_inv[t, 2, 0], dm_inv[t, 2, 1], dm_inv[t, 2, 2]
        # F = Ds Dm^-1, row by row (Ds's columns are the edges from node 0).
        e1, e2, e3 = x[i1, 0] - x[i0, 0], x[i2, 0] - x[i0, 0], x[i3, 0] - x[i0, 0]
        f00 = e1 * d00 + e2 * d10 + e3 * d20
        f01 = e1 * d01 + e2 * d11 + e3 * d21
        f02 = e1 * d02 + e2 * d12 + e3 * d22
        e1, e2, e3 = x[i1, 1] - x[i0, 1], x[i2, 1] - x[i0, 1], x[i3, 1] - x[i0, 1]
        f10 = e1 * d00 + e2 * d10 + e3 * d20
        f11 = e1 * d01 + e2 * d11 + e3 * d21
        f12 = e1 * d02 + e2 * d12 + e3 * d22
        e1, e2, e3 = x[i1, 2] - x[i0, 2], x[i2, 2] - x[i0, 2], x[i3, 2] - x[i0, 2]
        f20 = e1 * d00 + e2 * d10 + e3 * d20
        f21 = e1 * d01 + e2 * d11 + e3 * d21
        f22 = e1 * d02 + e2 * d12 + e3 * d22
        # The cofactor d det F / dF: column b is the cross product of F's other two columns.
        c00, c10, c20 = f11 * f22 - f21 * f12, f21 * f02 - f01 * f22, f01 * f12 - f11 * f02
        c01, c11, c21 = f12 * f20 - f22 * f10, f22 * f00 - f02 * f20, f02 * f10 - f12 * f00
        c02, c12, c22 = f10 * f21 - f20 * f11, f20 * f01 - f00 * f21, f00 * f11 - f10 * f01
        det = f00 * c00 + f10 * c10 + f20 * c20
        norm = math.sqrt(
            f00 * f00 + f01 * f01 + f02 * f02
            + f10 * f10 + f11 * f11 + f12 * f12
            + f20 * f20 + f21 * f21 + f22 * f22
        )  # fmt: skip
        has_dev = norm > _MIN_DEVIATORIC_NORM
        scale = 1.0 / norm if has_dev else 0.0
        # Node gradients of C_D = |F| (g) and C_H = det F (h): node j = 1..3 is (dC/dF) Dm^-T
        # column j, node 0 minus their sum.
        g1x = (f00 * d00 + f01 * d01 + f02 * d02) * scale
        g1y = (f10 * d00 + f11 * d01 + f12 * d02) * scale
        g1z = (f20 * d00 + f21 * d01 + f22 * d02) * scale
        g2x = (f00 * d10 + f01 * d11 + f02 * d12) * scale
        g2y = (f10 * d10 + f11 * d11 + f12 * d12) * scale
        g2z = (f20 * d10 + f21 * d11 + f22 * d12) * scale
        g3x = (f00 * d20 + f01 * d21 + f02 * d22) * scale
        g3y = (f10 * d20 + f11 * d21 + f12 * d22) * scale
        g3z = (f20 * d20 + f21 * d21 + f22 * d22) * scale
        g0x, g0y, g0z = -(g1x + g2x + g3x), -(g1y + g2y + g3y), -(g1z + g2z + g3z)
        h1x = c00 * d00 + c01 * d01 + c02 * d02
        h1y = c10 * d00 + c11 * d01 + c12 * d02
        h1z = c20 * d00 + c21 * d01 + c22 * d02
        h2x = c00 * d10 + c01 * d11 + c02 * d12
        h2y = c10 * d10 + c11 * d11 + c12 * d12
        h2z = c20 * d10 + c21 * d11 + c22 * d12
        h3x = c00 * d20 + c01 * d21 + c02 * d22
        h3y = c10 * d20 + c11 * d21 + c12 * d22
        h3z = c20 * d20 + c21 * d21 + c22 * d22
        h0x, h0y, h0z = -(h1x + h2x + h3x), -(h1y + h2y + h3y), -(h1z + h2z + h3z)
        # The 2 x 2 system's entries grad C_i M^-1 grad C_j (a fixed node has w = 0).
        w0, w1, w2, w3 = inv_mass[i0], inv_mass[i1], inv_mass[i2], inv_mass[i3]
        k_dd = (
            w0 * (g0x * g0x + g0y * g0y + g0z * g0z)
            + w1 * (g1x * g1x + g1y * g1y + g1z * g1z)
            + w2 * (g2x * g2x + g2y * g2y + g2z * g2z)
            + w3 * (g3x * g3x + g3y * g3y + g3z * g3z)
        )
        k_dh = (
            w0 * (g0x * h0x + g0y * h0y + g0z * h0z)
            + w1 * (g1x * h1x + g1y * h1y + g1z * h1z)
            + w2 * (g2x * h2x + g2y * h2y + g2z * h2z)
            + w3 * (g3x * h3x + g3y * h3y + g3z * h3z)
        )
        k_hh = (
            w0 * (h0x * h0x + h0y * h0y + h0z * h0z)
            + w1 * (h1x * h1x + h1y * h1y + h1z * h1z)
            + w2 * (h2x * h2x + h2y * h2y + h2z * h2z)
            + w3 * (h3x * h3x + h3y * h3y + h3z * h3z)
        )
        a_dd = k_dd + alpha_dev[t]
        a_hh = k_hh + alpha_hyd[t]
        rhs_h = -(det - gamma[t]) - alpha_hyd[t] * lam_hyd[t]
        if has_dev:
            rhs_d = -norm - alpha_dev[t] * lam_dev[t]
            determinant = a_dd * a_hh - k_dh * k_dh
            if determinant <= _SINGULAR_FRACTION * a_dd * a_hh:
                continue
            d_dev = (a_hh * rhs_d - k_dh * rhs_h) / determinant
            d_hyd = (a_dd * rhs_h - k_dh * rhs_d) / determinant
        else:
            if a_hh <= 0.0:
                continue
            d_dev = 0.0
            d_hyd = rhs_h / a_hh
        lam_dev[t] += d_dev
        lam_hyd[t] += d_hyd
        # Move each free node by w (g d_dev + h d_hyd); a fixed node's share goes to support.
        # (A loop over tuples: as fast as the four blocks written out, the same bits; the same
        # lines in a helper taking x and support made the whole sweep 2.4-2.7 x slower.)
        nodes = (i0, i1, i2, i3)
        masses = (w0, w1, w2, w3)
        steps = (
            (g0x * d_dev + h0x * d_hyd, g0y * d_dev + h0y * d_hyd, g0z * d_dev + h0z * d_hyd),
            (g1x * d_dev + h1x * d_hyd, g1y * d_dev + h1y * d_hyd, g1z * d_dev + h1z * d_hyd),
            (g2x * d_dev + h2x * d_hyd, g2y * d_dev + h2y * d_hyd, g2z * d_dev + h2z * d_hyd),
            (g3x * d_dev + h3x * d_hyd, g3y * d_dev + h3y * d_hyd, g3z * d_dev + h3z * d_hyd),
        )
        for local in range(4):
            node, w, step = nodes[local], masses[local], steps[local]
            for a in range(3):
                if w == 0.0:
                    support[node, a] += step[a]
                else:
                    x[node, a] += w * step[a]


@nb.njit(parallel=True, cache=True, fastmath=False)
def _project_tets_two_domains(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    order: NDArray[np.int64],
    bounds: NDArray[np.int64],
) -> None:
    """One Gauss-Seidel sweep of every tet in ``order``, its two domains on two threads.

    ``order[bounds[0]:bounds[1]]`` and ``order[bounds[1]:bounds[2]]`` share no node (see
    :func:`two_domain_order`), so projecting them at the same time is the same, bit for bit,
    as projecting one after the other; the separator ``order[bounds[2]:bounds[3]]`` follows
    on one thread. The result is that of :func:`_project_tets` over ``order`` whatever the
    thread count. Arguments as :func:`_project_tets`; ``bounds`` is (4,).
    """
    for part in nb.prange(2):
        _project_tets(
            x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd,
            support, order[bounds[part] : bounds[part + 1]],
        )  # fmt: skip
    _project_tets(
        x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd, support,
        order[bounds[2] : bounds[3]],
    )  # fmt: skip


def two_domain_order(
    nodes: NDArray[np.float64], tets: NDArray[np.int64], domains: int = 2
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """A sweep order of the tets as two node-disjoint domains and a separator.

    The tets are cut by their centroids across the mesh's longest extent: domain 0 is the
    tets below the cut, domain 1 the tets above it with no node of domain 0, and the
    separator the rest (one layer of tets along the cut). The cut is placed so the two
    domains hold as many tets as each other. Within each part the tets keep mesh order.

    Args:
        nodes: node positions [m], (node_count, 3).
        tets: (tet_count, 4) node indices.
        domains: 2, or 1 for mesh order as a single domain (bounds (0, n, n, n)).

    Returns:
        ``order`` (tet_count,), a permutation of the tets, and ``bounds`` (4,): the parts are
        ``order[bounds[i]:bounds[i + 1]]`` for domain 0, domain 1 and the separator.
    """
    count = tets.shape[0]
    if domains == 1:
        return np.arange(count, dtype=np.int64), np.array([0, count, count, count])
    centroids = nodes[tets].mean(axis=1)
    axis = int(np.argmax(np.ptp(nodes, axis=0)))
    by_axis = np.argsort(centroids[:, axis], kind="stable")

    def parts(cut: int) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        below = np.zeros(count, dtype=bool)
        below[by_axis[:cut]] = True
        touched = np.zeros(nodes.shape[0], dtype=bool)
        touched[tets[below].ravel()] = True
        shares = touched[tets].any(axis=1)
        return (
            np.flatnonzero(below),
            np.flatnonzero(~below & ~shares),
            np.flatnonzero(~below & shares),
        )

    # Domain 0 grows and domain 1 shrinks with the cut: bisect for equal sizes.
    low, high = 0, count
    while high - low > 1:
        middle = (low + high) // 2
        first, second, _ = parts(middle)
        if first.size < second.size:
            low = middle
        else:
            high = middle
    first, second, separator = parts(low)
    order = np.concatenate([first, second, separator]).astype(np.int64)
    bounds = np.cumsum([0, first.size, second.size, separator.size]).astype(np.int64)
    return order, bounds


@nb.njit(parallel=True, cache=True)
def _count_below_volume_floor(
    x: NDArray[np.float64],
    tets: NDArray[np.int64],
    inv_det_dm: NDArray[np.float64],
    volume_floor: float,
) -> int:
    """How many tets have det F < ``volume_floor``: :func:`_enforce_volume_floor`'s screen on
    two threads, run first on large meshes (from :data:`PARALLEL_SCREEN_TETS` tets), where
    no tet is below the floor in nearly every substep; it reads every tet every substep
    (0.87 ms a substep, 53 ms of a 485 ms robust step, at 173,229 tets on one thread)."""
    count = 0
    for t in nb.prange(tets.shape[0]):
        if _edge_determinant(x, tets, t) * inv_det_dm[t] < volume_floor:
            count += 1
    return count


@nb.njit(cache=True)
def _enforce_volume_floor(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    inv_det_dm: NDArray[np.float64],
    volume_floor: float,
    support: NDArray[np.float64],
) -> int:
    """Lift every tet with det F below ``volume_floor`` back to it; returns the projections.

    A hard one-sided constraint (zero compliance), run after a substep's sweeps: within a
    sweep a tet's own projection can lift it while its neighbours' push it back below, so
    the floor must come last (after the contacts too: a node it moves may end the substep a
    little inside the probe, which the next substep's contacts correct and the step's
    penetration reports). The tets below the floor are projected together, one Newton step
    on all their constraints at once (C_i = det F_i - floor, the 4-node gradients G_i,
    (G W G^T) mu = -C, W the inverse masses), repeated while any tet is below (at most
    :data:`_FLOOR_ROUNDS` rounds): projected one at a time, two slivers sharing a face undo
    each other's lift, and a single first-order pass left the published scene's 105,004-tet
    re-mesh (lesion 1, pose 4) at det F = 0.086, then inverted (-0.006) a step later; ten
    one-at-a-time passes still ended at the pass cap. ``inv_det_dm``: 1 / det Dm per tet
    [1/m^3], (tet_count,); the other arguments as :func:`_project_tets`.
    """
    f = np.empty((3, 3))
    cof = np.empty((3, 3))
    hits = 0
    for _ in range(_FLOOR_ROUNDS):
        # A cheap screen first: det F = det Ds / det Dm from the edges alone.
        active = np.empty(tets.shape[0], dtype=np.int64)
        count = 0
        for t in range(tets.shape[0]):
            if _edge_determinant(x, tets, t) * inv_det_dm[t] < volume_floor:
                active[count] = t
                count += 1
        if count == 0:
            break
        # Joint projections of up to _FLOOR_BLOCK tets at a time (a dense solve each).
        for first in range(0, count, _FLOOR_BLOCK):
            _lift_together(
                x, inv_mass, tets, dm_inv, active[first : min(first + _FLOOR_BLOCK, count)],
                volume_floor * (1.0 + _FLOOR_MARGIN), support, f, cof,
            )  # fmt: skip
        hits += count
    return hits


@nb.njit(cache=True)
def _lift_together(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    active: NDArray[np.int64],
    target: float,
    support: NDArray[np.float64],
    f: NDArray[np.float64],
    cof: NDArray[np.float64],
) -> None:
    """One Newton step of the constraints det F_i = ``target`` of the tets ``active`` at once
    (see :func:`_enforce_volume_floor`); ``f`` and ``cof`` are (3, 3) scratch."""
    count = active.shape[0]
    grads = np.empty((count, 4, 3))
    lift = np.empty(count)
    for i in range(count):
        det = _deformation(x, tets, dm_inv, active[i], f, cof)
        _node_gradients(cof, dm_inv, active[i], 1.0, grads[i])
        lift[i] = target - det
    # G W G^T: tets i and j couple through the free nodes they share.
    system = np.zeros((count, count))
    for i in range(count):
        for j in range(i, count):
            entry = 0.0
            for a in range(4):
                node = tets[active[i], a]
                w = inv_mass[node]
                if w == 0.0:
                    continue
                for b in range(4):
                    if tets[active[j], b] == node:
                        for c in range(3):
                            entry += w * grads[i, a, c] * grads[j, b, c]
            system[i, j] = entry
            system[j, i] = entry
    largest = 0.0
    for i in range(count):
        largest = max(largest, system[i, i])
    if largest == 0.0:
        return  # only fixed nodes: nothing can move
    for i in range(count):
        system[i, i] += 1e-12 * largest  # for tets whose constraints coincide
    multipliers = np.linalg.solve(system, lift)
    for i in range(count):
        _apply(x, inv_mass, tets, active[i], grads[i], 0.0, grads[i], multipliers[i], support)


@nb.njit(cache=True, inline="always")
def _apply(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    t: int,
    g: NDArray[np.float64],
    d_dev: float,
    gh: NDArray[np.float64],
    d_hyd: float,
    support: NDArray[np.float64],
) -> None:
    """Move tet ``t``'s free nodes by M^-1 (g d_dev + gh d_hyd); a fixed node's share goes to
    ``support`` (see :func:`_project_tets`)."""
    for local in range(4):
        node = tets[t, local]
        w = inv_mass[node]
        for a in range(3):
            step = g[local, a] * d_dev + gh[local, a] * d_hyd
            if w == 0.0:
                support[node, a] += step
            else:
                x[node, a] += w * step


@nb.njit(cache=True)
def _project_contacts(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    alpha: float,
    lam: NDArray[np.float64],
) -> None:
    """One Gauss-Seidel sweep of the contact inequalities n . (p - anchor) >= 0.

    Args:
        x: node positions [m], (node_count, 3), updated in place.
        inv_mass: inverse lumped masses [1/kg], (node_count,).
        point_nodes, point_weights: the contact surface's embedding, (point_count, 4).
        points: surface point index of each active contact, (contact_count,).
        normals: probe outward normal per contact, (contact_count, 3), unit.
        anchors: a point of the probe's tangent plane per contact [m], (contact_count, 3).
        alpha: time-scaled contact compliance alpha / h^2 [1/kg].
        lam: this substep's multipliers [kg m], (contact_count,), kept >= 0.
    """
    for k in range(points.shape[0]):
        p = points[k]
        gap = 0.0
        w_sum = 0.0
        for local in range(4):
            node = point_nodes[p, local]
            wt = point_weights[p, local]
            w_sum += wt * wt * inv_mass[node]
            for a in range(3):
                gap += wt * x[node, a] * normals[k, a]
        for a in range(3):
            gap -= anchors[k, a] * normals[k, a]
        denominator = w_sum + alpha
        if denominator <= 0.0:
            continue
        delta = (-gap - alpha * lam[k]) / denominator
        # Signorini: the multiplier only pushes (lambda >= 0); clamp the accumulated value.
        if lam[k] + delta < 0.0:
            delta = -lam[k]
        if delta == 0.0:
            continue
        lam[k] += delta
        for local in range(4):
            node = point_nodes[p, local]
            scale = inv_mass[node] * point_weights[p, local] * delta
            for a in range(3):
                x[node, a] += scale * normals[k, a]


@nb.njit(cache=True)
def _contact_zone_sweeps(
    x: NDArray[np.float64],
    inv_mass: NDArray[np.float64],
    tets: NDArray[np.int64],
    dm_inv: NDArray[np.float64],
    alpha_dev: NDArray[np.float64],
    alpha_hyd: NDArray[np.float64],
    gamma: NDArray[np.float64],
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    anchors: NDArray[np.float64],
    alpha: float,
    lam: NDArray[np.float64],
    node_tet_start: NDArray[np.int64],
    node_tets: NDArray[np.int64],
    order: NDArray[np.int64],
    zone_iterations: int,
) -> None:
    """A substep's contacts after its last full sweep, then ``zone_iterations`` sweeps of the
    contact zone (:func:`_contact_zone`, in ``order``) each followed by the contacts again.

    One compiled call for what were eight (each call checks its arguments' types, a few
    microseconds). The arguments are :func:`_project_tets`' (``x`` .. ``support``), then
    :func:`_project_contacts`' after its ``x`` and ``inv_mass`` (``point_nodes`` .. ``lam``),
    then :func:`_contact_zone`'s.
    """
    _project_contacts(x, inv_mass, point_nodes, point_weights, points, normals, anchors, alpha, lam)
    if zone_iterations == 0:
        return
    zone = _contact_zone(point_nodes, point_weights, points, node_tet_start, node_tets, order)
    for _ in range(zone_iterations):
        _project_tets(
            x, inv_mass, tets, dm_inv, alpha_dev, alpha_hyd, gamma, lam_dev, lam_hyd, support, zone
        )
        _project_contacts(
            x, inv_mass, point_nodes, point_weights, points, normals, anchors, alpha, lam
        )


@nb.njit(cache=True)
def _contact_zone(
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    points: NDArray[np.int64],
    node_tet_start: NDArray[np.int64],
    node_tets: NDArray[np.int64],
    order: NDArray[np.int64],
) -> NDArray[np.int64]:
    """The tets incident to a node that carries a contact point (weight != 0), in ``order``."""
    marked = np.zeros(order.shape[0], dtype=np.bool_)
    count = 0
    for k in range(points.shape[0]):
        p = points[k]
        for local in range(4):
            if point_weights[p, local] == 0.0:
                continue
            node = point_nodes[p, local]
            for j in range(node_tet_start[node], node_tet_start[node + 1]):
                t = node_tets[j]
                if not marked[t]:
                    marked[t] = True
                    count += 1
    zone = np.empty(count, dtype=np.int64)
    count = 0
    for t in order:
        if marked[t]:
            zone[count] = t
            count += 1
    return zone


@nb.njit(cache=True)
def _points_near(
    x: NDArray[np.float64],
    point_nodes: NDArray[np.int64],
    point_weights: NDArray[np.float64],
    centre: NDArray[np.float64],
    reach: float,
    rotation: NDArray[np.float64],
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    near: NDArray[np.int64],
    positions: NDArray[np.float64],
) -> int:
    """The contact points within ``reach`` [m] of ``centre`` [m] (3,) and, in the frame of
    ``rotation`` (3, 3) about ``centre`` (local = (p - centre) R), inside the box from
    ``low`` to ``high`` [m] (3,) each: writes their indices to ``near`` and their positions
    [m] to ``positions`` (both sized for every point) and returns how many.

    One pass over the embedding, no array of all points' positions: this runs every
    substep, and detection with the whole-array version (einsum, then a distance per point)
    took 0.32 ms a substep at 4,126 tets, 19 ms of a 49 ms robust step (cProfile, ``bench
    contact``'s apex press). The sums are taken in the order numpy takes them (the four
    weighted nodes in turn, then the three squared components), so the points found and
    their positions are the same to the bit. The box (the probe's local bounds grown by
    the contact margin) keeps the exact SDF off points that cannot be near the probe: at
    4,126 tets, 6 mm into the apex press, the ball about the face holds 571 of the 2,515
    points and the box 54."""
    count = 0
    reach2 = reach * reach
    for p in range(point_nodes.shape[0]):
        p0 = 0.0
        p1 = 0.0
        p2 = 0.0
        for local in range(4):
            node = point_nodes[p, local]
            wt = point_weights[p, local]
            p0 += wt * x[node, 0]
            p1 += wt * x[node, 1]
            p2 += wt * x[node, 2]
        d0 = p0 - centre[0]
        d1 = p1 - centre[1]
        d2 = p2 - centre[2]
        if d0 * d0 + d1 * d1 + d2 * d2 > reach2:
            continue
        inside = True
        for b in range(3):
            along = d0 * rotation[0, b] + d1 * rotation[1, b] + d2 * rotation[2, b]
            if along < low[b] or along > high[b]:
                inside = False
        if inside:
            near[count] = p
            positions[count, 0] = p0
            positions[count, 1] = p1
            positions[count, 2] = p2
            count += 1
    return count


@nb.njit(cache=True)
def _predict(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    damping: float,
    h: float,
) -> None:
    """A substep's prediction, in place: v <- damping v, x_previous <- x, x <- x + h v
    (shapes (node_count, 3); h [s]). One pass instead of three whole-array numpy passes and
    a copy, each substep."""
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] *= damping
            x_previous[i, a] = x[i, a]
            x[i, a] += h * v[i, a]


@nb.njit(cache=True)
def _update_velocity(
    x: NDArray[np.float64], x_previous: NDArray[np.float64], v: NDArray[np.float64], h: float
) -> None:
    """v <- (x - x_previous) / h in place [m/s], (node_count, 3)."""
    for i in range(x.shape[0]):
        for a in range(3):
            v[i, a] = (x[i, a] - x_previous[i, a]) / h


@nb.njit(cache=True)
def _start_substep(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    damping: float,
    h: float,
    lam_dev: NDArray[np.float64],
    lam_hyd: NDArray[np.float64],
    support_step: NDArray[np.float64],
) -> None:
    """A substep's start in one compiled call: :func:`_predict`, and the substep's tet
    multipliers (tet_count,) and fixed-node support (node_count, 3) set to zero."""
    _predict(x, v, x_previous, damping, h)
    lam_dev[:] = 0.0
    lam_hyd[:] = 0.0
    support_step[:] = 0.0


@nb.njit(cache=True)
def _end_substep(
    x: NDArray[np.float64],
    x_previous: NDArray[np.float64],
    v: NDArray[np.float64],
    h: float,
    support_step: NDArray[np.float64],
    support: NDArray[np.float64],
    points: NDArray[np.int64],
    normals: NDArray[np.float64],
    lam: NDArray[np.float64],
    impulse: NDArray[np.float64],
) -> int:
    """A substep's end in one compiled call (after its sweeps and volume floor): the
    velocity update (:func:`_update_velocity`), the step's support sum ``support`` +=
    ``support_step`` / h [N s] (node_count, 3), and each contact's impulse n lambda / h [N s]
    added to its point's row of ``impulse`` (point_count, 3), ``points``, ``normals`` and
    ``lam`` as :func:`_project_contacts`'. Returns how many contacts carry a force. The
    arithmetic is numpy's (``support += support_step / h``, ``np.add.at``), to the bit. Timed
    on a state of the 4,126-tet apex press (48 contacts, five repeats of 5,000 calls): the
    four calls it replaced 9.8-10.6 us, this one 5.6-5.9 us."""
    _update_velocity(x, x_previous, v, h)
    for i in range(support.shape[0]):
        for a in range(3):
            support[i, a] += support_step[i, a] / h
    pressing = 0
    for k in range(points.shape[0]):
        scale = lam[k] / h
        for a in range(3):
            impulse[points[k], a] += normals[k, a] * scale
        if lam[k] != 0.0:
            pressing += 1
    return pressing


@nb.njit(cache=True)
def _min_volume_ratio(
    x: NDArray[np.float64], tets: NDArray[np.int64], rest_volume: NDArray[np.float64]
) -> float:
    """Smallest deformed / rest signed tet volume (det F); <= 0 means an inverted tet."""
    smallest = np.inf
    for t in range(tets.shape[0]):
        ratio = _edge_determinant(x, tets, t) / 6.0 / rest_volume[t]
        if not ratio >= smallest:  # also catches NaN
            smallest = ratio
    return smallest


def _contact_points(
    mesh: TetMesh, surface: SurfacePoints, spacing_m: float = 0.0, all_skin: bool = False
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The points the PBD contact acts on, as an embedding (nodes and weights, (k, 4) each).

    Every free boundary node of the volume (weight 1 on itself). With ``spacing_m`` > 0,
    points between them too, embedded in the boundary faces' nodes, so that no two are
    farther apart than that: a boundary edge of length L gets ceil(L / spacing) - 1 evenly
    spaced points, a face the interior points of its n-grid, n = ceil(longest edge /
    spacing) (none where the boundary is already that fine, or all its nodes are fixed).
    Then each collision-surface point farther than the median boundary edge from every
    boundary node, so a coarse volume under a fine collision surface still has no gaps the
    probe can sink through (``all_skin``: every collision-surface point).
    """
    faces = boundary_faces(mesh.tets)
    boundary = np.unique(faces)
    free = boundary[~np.isin(boundary, mesh.fixed_nodes)]
    nodes = [np.repeat(free[:, None], 4, axis=1)]
    weights = [np.zeros((free.size, 4))]
    weights[0][:, 0] = 1.0
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if spacing_m > 0.0:
        fixed = np.zeros(mesh.node_count, dtype=bool)
        fixed[mesh.fixed_nodes] = True
        unique_edges = np.unique(np.sort(edges, axis=1), axis=0)
        unique_edges = unique_edges[~fixed[unique_edges].all(axis=1)]
        length = np.linalg.norm(
            mesh.nodes[unique_edges[:, 0]] - mesh.nodes[unique_edges[:, 1]], axis=1
        )
        segments = np.ceil(length / spacing_m).astype(np.int64)
        free_faces = faces[~fixed[faces].all(axis=1)]
        corners = mesh.nodes[free_faces]
        longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
        grids = np.ceil(longest / spacing_m).astype(np.int64)
        for n in np.unique(segments[segments > 1]):
            chosen = unique_edges[segments == n]
            t = np.arange(1, n) / n
            pair = np.stack([1.0 - t, t], axis=1)  # (n - 1, 2)
            nodes.append(_pad_embedding(np.repeat(chosen, t.size, axis=0)))
            weights.append(_pad_weights(np.tile(pair, (len(chosen), 1))))
        for n in np.unique(grids[grids > 2]):
            chosen = free_faces[grids == n]
            grid = triangle_grid(int(n), interior=True)
            nodes.append(_pad_embedding(np.repeat(chosen, len(grid), axis=0)))
            weights.append(_pad_weights(np.tile(grid, (len(chosen), 1))))
    if mesh.collision_surface is not None:
        spacing = float(
            np.median(np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1))
        )
        distance, _ = cKDTree(mesh.nodes[boundary]).query(surface.positions(mesh.nodes))
        extra = np.arange(distance.size) if all_skin else np.flatnonzero(distance > spacing)
        nodes.append(surface.embedding.tet_nodes[extra])
        weights.append(surface.embedding.weights[extra])
    return (
        np.ascontiguousarray(np.concatenate(nodes), dtype=np.int64),
        np.ascontiguousarray(np.concatenate(weights)),
    )


def _pad_embedding(nodes: NDArray[np.int64]) -> NDArray[np.int64]:
    """(k, m) node indices, m < 4, padded to (k, 4) by repeating the first node."""
    padded = np.repeat(nodes[:, :1], 4, axis=1)
    padded[:, : nodes.shape[1]] = nodes
    return padded


def _pad_weights(weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """(k, m) weights, m < 4, padded with zeros to (k, 4)."""
    padded = np.zeros((weights.shape[0], 4))
    padded[:, : weights.shape[1]] = weights
    return padded


# ----------------------------------------------------------------------------------------
# The backend


class PBDContact(ContactModel):
    """An XPBD tetrahedral tissue pressed by a rigid probe (the paper's PBD baseline).

    A second tissue backend behind the contact-model step interface: :meth:`step` moves the
    probe, runs ``substeps`` XPBD substeps and returns the contact wrench from the contact
    multipliers (see the module docstring for the model, the force and the calibration).

    Args:
        mesh: the tissue mesh; its fixed nodes are pinned.
        probe_shape: the rigid probe's geometry.
        materials: per-region materials (mu, lambda, density); default tissue E = 2850 Pa,
            nu = 0.49, lesions 4 x stiffer.
        config: the XPBD settings; default the calibrated :class:`PBDConfig`.

    Limitations:
        Not converged per step: XPBD with a few sweeps is softer than the material and only
        approaches the FE through the calibrated compliance scales, which hold for the
        calibration's mesh resolution, substep count and loading; other meshes or settings
        need :func:`~tissue.pbd_calibration.calibrate_pbd` again (at level 4126, 15 and 20
        substeps give +14 % and +22 % force with the same scales). Too few substeps let the hard
        contact crush the surface tets: at level 4126, 5 substeps end INVERTED (-31 % force).
        Contact acts on the volume's boundary nodes, so a collision surface that bulges between them
        (or lies outside the volume) is not held: 6 mm into level 4126 its deepest vertex is 1.2 mm
        inside the linear probe, where the FE strategies contacting it give about 0. Contact
        planes are taken once per substep from the exact SDF at the predicted positions, so
        the probe must move less than about half its thickness per substep (1.3 mm for the
        linear face, i.e. about 0.6 m/s at the defaults) or points can tunnel through it.
        Frictionless only. Forces are time averages over the step and include inertia during
        fast motion. Stresses are not reported. About 3 ms per step at 4.1k tets with the
        defaults (one thread); the robust configuration's sweep uses two threads.
    """

    method = ContactMethod.PBD

    def __init__(
        self,
        mesh: TetMesh,
        probe_shape: ProbeShape,
        materials: TissueMaterials | None = None,
        config: PBDConfig | None = None,
    ) -> None:
        if not isinstance(mesh, TetMesh):
            raise TissueInputError(
                f"mesh must be a tissue.TetMesh; got {type(mesh).__name__} "
                "(load files with tissue.load_tet_mesh)"
            )
        if config is not None and not isinstance(config, PBDConfig):
            raise ConfigError(f"config must be a PBDConfig; got {type(config).__name__}")
        super().__init__(mesh, probe_shape)
        self.materials = materials or TissueMaterials()
        self.config = config or PBDConfig()
        cfg = self.config

        # The step runs in its own numbering (see two_domain_order): the tets in sweep order,
        # two node-disjoint domains and their separator, and the nodes in the order the tets
        # first use them, so that the two threads sweeping the domains write to separate
        # memory. (In mesh numbering their nodes and multipliers share cache lines: the
        # two-thread sweep was slower than one thread, 1.86 against 1.68 ms at 26,220 tets.)
        # The state (_x, _v) and everything public stay in mesh numbering.
        order, self._sweep_bounds = two_domain_order(mesh.nodes, mesh.tets, cfg.sweep_domains)
        first_use = np.unique(mesh.tets[order].ravel(), return_index=True)
        used_in_order = first_use[0][np.argsort(first_use[1])]
        unused = np.setdiff1d(np.arange(mesh.node_count), used_in_order)
        self._node_order = np.concatenate([used_in_order, unused]).astype(np.int64)
        self._step_node_of_mesh = np.empty(mesh.node_count, dtype=np.int64)
        self._step_node_of_mesh[self._node_order] = np.arange(mesh.node_count)
        nodes = mesh.nodes[self._node_order]
        tets = np.ascontiguousarray(self._step_node_of_mesh[mesh.tets[order]])
        self._tets = tets

        edges = np.stack([nodes[tets[:, k]] - nodes[tets[:, 0]] for k in (1, 2, 3)], axis=2)
        self._dm_inv = np.ascontiguousarray(np.linalg.inv(edges))
        self._inv_det_dm = 1.0 / np.linalg.det(edges)
        self._rest_volume = mesh.tet_volumes()[order]
        mu, lam, rho = self.materials.per_tet(mesh.region[order])
        lam_stable = lam + mu
        mass = np.bincount(
            tets.ravel(),
            weights=np.repeat(rho * self._rest_volume / 4.0, 4),
            minlength=mesh.node_count,
        )
        self.lumped_mass = mass[self._step_node_of_mesh]  # mesh numbering
        inv_mass = np.zeros(mesh.node_count)
        free = mass > 0.0
        inv_mass[free] = 1.0 / mass[free]
        inv_mass[self._step_node_of_mesh[mesh.fixed_nodes]] = 0.0
        self._inv_mass = inv_mass
        h = cfg.substep_dt
        mu_model = mu / cfg.deviatoric_compliance_scale
        lam_model = lam_stable / cfg.volume_compliance_scale
        self._alpha_dev = 1.0 / (mu_model * self._rest_volume) / h**2
        self._alpha_hyd = 1.0 / (lam_model * self._rest_volume) / h**2
        # The rest offset must use the scaled moduli too: only then do the two constraints'
        # forces cancel at rest (mu I + lambda' (1 - gamma) I = 0).
        self._gamma = 1.0 + mu_model / lam_model
        self._contact_alpha = cfg.contact_compliance_m_per_n / h**2
        point_nodes, self._point_weights = _contact_points(
            mesh, self.surface, cfg.contact_spacing_m, cfg.skin_contact
        )
        self._point_nodes = point_nodes  # mesh numbering, for the public positions
        self._step_point_nodes = np.ascontiguousarray(self._step_node_of_mesh[point_nodes])
        self._lam_dev = np.zeros(mesh.tet_count)
        self._lam_hyd = np.zeros(mesh.tet_count)
        self._all_tets = np.arange(mesh.tet_count, dtype=np.int64)
        # Node -> incident tets (CSR, step numbering), for the contact zone.
        self._node_tets = np.argsort(tets.ravel(), kind="stable").astype(np.int64) // 4
        self._node_tet_start = np.concatenate(
            [[0], np.cumsum(np.bincount(tets.ravel(), minlength=mesh.node_count))]
        ).astype(np.int64)
        self._reset_tissue()
        self._load_kernels()

    def _load_kernels(self) -> None:
        """Call every compiled kernel of a step once, on scratch arrays of the types the step
        passes, so that the one-time work of a process's first call (numba loading the
        kernel from its cache, OpenMP starting the sweep's second thread; the probe shape's
        cached bounds) is done here, when the model is built, as the FE methods' integrator
        does in ``prepare``. Measured in fresh processes (apex press), first step against the
        next ones: without it 198 against 2.5-2.8 ms (4,126 tets, paper configuration), 261
        against 18 (4,126, robust) and 308 against 74-78 (26,220, robust); with it 2.9, 17
        and 73 ms, as the steps after. ``bench contact``'s slowest robust step at 6,966 tets,
        the first level swept on two threads, was 654 ms against a median of 28. Nothing of
        the model's state is touched."""
        cfg = self.config
        x = self._x[self._node_order]
        v, x_previous, support_step, support = (np.zeros_like(x) for _ in range(4))
        lam_dev, lam_hyd = np.zeros_like(self._lam_dev), np.zeros_like(self._lam_hyd)
        h = cfg.substep_dt
        _start_substep(x, v, x_previous, 1.0, h, lam_dev, lam_hyd, support_step)
        points = self._point_nodes.shape[0]
        near, near_positions = np.empty(points, dtype=np.int64), np.empty((points, 3))
        origin, rotation = np.zeros(3), np.eye(3)
        _points_near(
            x, self._step_point_nodes, self._point_weights, origin, 0.0, rotation, origin,
            origin, near, near_positions,
        )  # fmt: skip
        self.probe.shape.signed_distance(np.zeros((1, 3)))
        self.probe.shape.local_bounds_m()  # cached on the shape (built from its surface)
        tissue_args = (
            x, self._inv_mass, self._tets, self._dm_inv, self._alpha_dev, self._alpha_hyd,
            self._gamma, lam_dev, lam_hyd, support_step,
        )  # fmt: skip
        no_tets = self._all_tets[:0]
        _project_tets(*tissue_args, no_tets)
        _project_tets_two_domains(*tissue_args, no_tets, np.zeros(4, dtype=np.int64))
        no_contacts = np.zeros(0, dtype=np.int64)
        contact_args = (
            self._step_point_nodes, self._point_weights, no_contacts, np.zeros((0, 3)),
            np.zeros((0, 3)), self._contact_alpha, np.zeros(0),
        )  # fmt: skip
        _project_contacts(x, self._inv_mass, *contact_args)
        _contact_zone_sweeps(
            *tissue_args, *contact_args, self._node_tet_start, self._node_tets, self._all_tets,
            cfg.contact_zone_iterations,
        )  # fmt: skip
        _count_below_volume_floor(x, self._tets, self._inv_det_dm, cfg.volume_floor)
        _enforce_volume_floor(
            x, self._inv_mass, self._tets, self._dm_inv, self._inv_det_dm, 0.0, support_step
        )
        _end_substep(
            x, x_previous, v, h, support_step, support, no_contacts, np.zeros((0, 3)),
            np.zeros(0), np.zeros((points, 3)),
        )  # fmt: skip
        _min_volume_ratio(x, self._tets, self._rest_volume)

    # ------------------------------------------------------------------ interface

    def contact_points_world(self) -> NDArray[np.float64]:
        """The points PBD contact acts on [m], (k, 3) (see :func:`_contact_points`)."""
        return np.einsum("kj,kjd->kd", self._point_weights, self._x[self._point_nodes])

    @property
    def node_positions(self) -> NDArray[np.float64]:
        """Current node positions [m], (node_count, 3) (a read-only view)."""
        view = self._x.view()
        view.flags.writeable = False
        return view

    @property
    def node_velocities(self) -> NDArray[np.float64]:
        """Current node velocities [m/s], (node_count, 3) (a read-only view)."""
        view = self._v.view()
        view.flags.writeable = False
        return view

    @property
    def dt(self) -> float:
        return self.config.tissue_dt

    def _reset_tissue(self) -> None:
        self._x = self.mesh.nodes.copy()
        self._v = np.zeros_like(self._x)
        self._previous_pose: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def kinetic_energy_j(self) -> float:
        """Kinetic energy of the tissue now [J]."""
        return 0.5 * float(np.sum(self.lumped_mass[:, None] * self._v**2))

    def _snapshot_tissue(self) -> dict[str, Any]:
        before = self._previous_pose
        return {
            "x": self._x.copy(),
            "v": self._v.copy(),
            "previous_pose": None if before is None else (before[0].copy(), before[1].copy()),
            "lam_dev": self._lam_dev.copy(),
            "lam_hyd": self._lam_hyd.copy(),
        }

    def _restore_tissue(self, snapshot: dict[str, Any]) -> None:
        self._x = np.array(snapshot["x"], dtype=np.float64)
        self._v = np.array(snapshot["v"], dtype=np.float64)
        before = snapshot["previous_pose"]
        self._previous_pose = None if before is None else (before[0].copy(), before[1].copy())
        self._lam_dev[:] = snapshot["lam_dev"]
        self._lam_hyd[:] = snapshot["lam_hyd"]

    def _advance(
        self, step_s: float
    ) -> tuple[StepStatus, NDArray[np.float64], NDArray[np.float64], dict[str, Any]]:
        cfg = self.config
        h = step_s / cfg.substeps
        # The compliances were divided by the nominal substep squared when the model was
        # built; a shorter step (a sub-motion, see ContactModel.step) rescales them.
        scale = 1.0 if step_s == cfg.tissue_dt else (cfg.substep_dt / h) ** 2
        alpha_dev = self._alpha_dev if scale == 1.0 else self._alpha_dev * scale
        alpha_hyd = self._alpha_hyd if scale == 1.0 else self._alpha_hyd * scale
        contact_alpha = self._contact_alpha * scale
        end_position = self.probe.position_world.copy()
        end_quat = self.probe.quat_wxyz.copy()
        start_position, start_quat = self._previous_pose or (end_position, end_quat)
        if float(np.dot(start_quat, end_quat)) < 0.0:
            start_quat = -start_quat  # the short way round for nlerp
        x = self._x[self._node_order]  # step numbering (a copy)
        v = self._v[self._node_order]
        x_previous = np.empty_like(x)
        point_count = self._point_nodes.shape[0]
        near = np.empty(point_count, dtype=np.int64)
        near_positions = np.empty((point_count, 3))
        damping = math.exp(-cfg.damping_per_s * h)
        impulse = np.zeros((point_count, 3))  # sum over substeps of n lambda / h [N s]
        support = np.zeros((self.mesh.node_count, 3))
        support_step = np.zeros_like(support)
        shape = self.probe.shape
        reach = shape.bounding_radius_m + cfg.contact_margin_m
        bounds = shape.local_bounds_m()
        low = bounds[0] - cfg.contact_margin_m
        high = bounds[1] + cfg.contact_margin_m
        max_contacts = 0
        detect_s = 0.0
        floor_hits = 0
        # The two-domain sweep is the one-thread sweep in the same order, bit for bit; on one
        # thread the plain kernel skips the parallel launch.
        two_threads = cfg.sweep_domains == 2 and nb.get_num_threads() > 1
        screen_first = two_threads and self.mesh.tet_count >= PARALLEL_SCREEN_TETS
        tissue_args = (
            x, self._inv_mass, self._tets, self._dm_inv, alpha_dev, alpha_hyd,
            self._gamma, self._lam_dev, self._lam_hyd, support_step,
        )  # fmt: skip
        # The probe's pose at each substep's end, all at once (nlerp, each quaternion
        # normalised as quat_to_matrix does): 7 us a substep one at a time at 4,126 tets.
        # The norms stay one 4-vector at a time: np.linalg.norm over rows rounds differently
        # (12 % of 200,000 random quaternions differed in the last bit).
        fractions = np.arange(1, cfg.substeps + 1) / cfg.substeps
        positions = (1.0 - fractions)[:, None] * start_position + fractions[:, None] * end_position
        quats = (1.0 - fractions)[:, None] * start_quat + fractions[:, None] * end_quat
        norms = np.array([np.linalg.norm(quat) for quat in quats])
        rotations = np.ascontiguousarray(unit_quat_to_matrix(quats / norms[:, None]))
        for substep in range(cfg.substeps):
            position, rotation = positions[substep], rotations[substep]
            _start_substep(x, v, x_previous, damping, h, self._lam_dev, self._lam_hyd, support_step)
            tic = time.perf_counter()
            contact_points, normals, anchors = self._detect(
                x, position, rotation, shape, (reach, low, high), near, near_positions
            )
            detect_s += time.perf_counter() - tic
            lam_contact = np.zeros(contact_points.shape[0])
            contact_args = (
                self._step_point_nodes, self._point_weights, contact_points, normals, anchors,
                contact_alpha, lam_contact,
            )  # fmt: skip
            for sweep in range(cfg.iterations):
                if two_threads:
                    _project_tets_two_domains(*tissue_args, self._all_tets, self._sweep_bounds)
                else:
                    _project_tets(*tissue_args, self._all_tets)
                if sweep < cfg.iterations - 1 and contact_points.size:
                    _project_contacts(x, self._inv_mass, *contact_args)
            if contact_points.size:
                # The last full sweep's contacts, then the zone's sweeps and contacts.
                _contact_zone_sweeps(
                    *tissue_args, *contact_args, self._node_tet_start, self._node_tets,
                    self._all_tets, cfg.contact_zone_iterations,
                )  # fmt: skip
            if cfg.volume_floor > 0.0 and not (
                screen_first
                and _count_below_volume_floor(x, self._tets, self._inv_det_dm, cfg.volume_floor)
                == 0
            ):
                floor_hits += _enforce_volume_floor(
                    x,
                    self._inv_mass,
                    self._tets,
                    self._dm_inv,
                    self._inv_det_dm,
                    cfg.volume_floor,
                    support_step,
                )
            pressing = _end_substep(
                x, x_previous, v, h, support_step, support, contact_points, normals,
                lam_contact, impulse,
            )  # fmt: skip
            max_contacts = max(max_contacts, pressing)

        diagnostics: dict[str, Any] = {
            "substeps": cfg.substeps,
            "iterations": cfg.iterations,
            "active_contacts_max": max_contacts,
            "contact_detection_ms": 1e3 * detect_s,
            "volume_floor_projections": floor_hits,
        }
        self._previous_pose = (end_position, end_quat)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            diagnostics["support_force_n"] = np.full(3, np.nan)
            # Nothing non-finite is stored: the state before the step stays.
            return StepStatus.DIVERGED, np.zeros((0, 3)), np.zeros((0, 3)), diagnostics
        min_ratio = float(_min_volume_ratio(x, self._tets, self._rest_volume))
        self._x = x[self._step_node_of_mesh]  # back to mesh numbering
        self._v = v[self._step_node_of_mesh]
        diagnostics["min_volume_ratio"] = min_ratio
        # Force of the base on the tissue: minus the elastic constraint forces at fixed nodes,
        # averaged over the step (impulse / tissue_dt).
        diagnostics["support_force_n"] = -support.sum(axis=0) / step_s
        in_contact = np.flatnonzero(np.any(impulse != 0.0, axis=1))
        points_world = self._positions(self._x)[in_contact]
        forces = -impulse[in_contact] / step_s
        status = StepStatus.INVERTED if not min_ratio > 0.0 else StepStatus.OK
        return status, points_world, forces, diagnostics

    @property
    def contact_point_positions(self) -> NDArray[np.float64]:
        """Current positions of the points the PBD contact acts on [m], (k, 3)."""
        return self._positions(self._x)

    def _positions(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.einsum("pk,pka->pa", self._point_weights, x[self._point_nodes])

    def _detect(
        self,
        x: NDArray[np.float64],
        position: NDArray[np.float64],
        rotation: NDArray[np.float64],
        shape: ProbeShape,
        broad_phase: tuple[float, NDArray[np.float64], NDArray[np.float64]],
        near: NDArray[np.int64],
        near_positions: NDArray[np.float64],
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """Contact candidates at predicted positions, for a probe at (position, rotation).

        ``broad_phase``: :func:`_points_near`'s reach [m] and probe-frame box (low, high
        [m], (3,) each), both grown by the contact margin. ``near`` (point_count,) and
        ``near_positions`` (point_count, 3) are scratch for :func:`_points_near`, allocated
        once per step.

        Returns:
            surface point indices (k,), probe outward normals (k, 3) and tangent-plane anchor
            points [m] (k, 3) (the closest probe surface points), world frame.
        """
        reach, low, high = broad_phase
        count = _points_near(
            x, self._step_point_nodes, self._point_weights, position, reach, rotation, low, high,
            near, near_positions,
        )  # fmt: skip
        if count == 0:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        points = near_positions[:count]
        local = (points - position) @ rotation
        distance, normal_local = shape.signed_distance(local)
        close = distance < self.config.contact_margin_m
        normals = np.ascontiguousarray(normal_local[close] @ rotation.T)
        anchors = points[close] - distance[close, None] * normals
        return near[:count][close], normals, np.ascontiguousarray(anchors)
