"""``probegym bench tissue``: what each part of a tissue step costs, per mesh level.

Prints a table and writes a JSON list with one record per level. Times are medians over
repeats of the same operation in one process; compare ratios, not absolute numbers, on a
shared machine.
"""

from __future__ import annotations

import gc
import platform
import resource
import time
from pathlib import Path
from typing import Any

import numpy as np

from agents.lab.bench.report import BenchRecord, MarkdownTable
from agents.outputs import write_json
from tissue import TissueMaterials
from tissue.lab import (
    PAPER_PROBE_SPEED_M_S,
    PAPER_TISSUE_DT_S,
    ConstrainedSystem,
    DirectFactorizer,
    LinearSolver,
    LinearSolverConfig,
    SimulationConfig,
    TissueSimulator,
    breast_phantom,
    top_surface_nodes,
)

DEFAULT_LEVELS = (623, 1363, 2539, 4126, 7369, 12861, 26220)
PROBE_FACE_HALF_SIZE_M = (0.0265, 0.0065)
# Probe advance per tissue step at the paper's speed and step [m].
STEP_ADVANCE_M = PAPER_PROBE_SPEED_M_S * PAPER_TISSUE_DT_S
# The state the timings are taken in: this far into a compression.
PRELOAD_DEPTH_M = 0.004
# Surface nodes this far below the apex, under the face, move with the probe (a contact patch).
PATCH_DEPTH_M = 0.005
# The targets for a converged robust step [ms], by phantom level (4,126, 26,220 and
# 176,506 tets), in this benchmark's Newton step and in ``probegym bench contact``.
ROBUST_STEP_TARGET_MS = {4126: 20.0, 26220: 100.0, 176506: 500.0}


def robust_step_target(level: int, step_ms: float, converged: bool) -> dict[str, float | bool]:
    """The robust-step target at ``level`` and whether a robust step of ``step_ms`` [ms] meets it
    (only a ``converged`` one can): ``robust_target_step_ms`` and ``meets_robust_target``,
    or nothing at a level without a target."""
    limit = ROBUST_STEP_TARGET_MS.get(level)
    if limit is None:
        return {}
    return {"robust_target_step_ms": limit, "meets_robust_target": converged and step_ms <= limit}


def _median_ms(samples: list[float]) -> float:
    return float(np.median(samples)) * 1e3


def _press(sim: TissueSimulator, nodes: np.ndarray, depth_m: float) -> None:
    sim.prescribe(nodes, sim.rest_positions[nodes] + np.array([0.0, 0.0, -depth_m]))


def benchmark_level(level: int, repeats: int) -> dict[str, float | int | str]:
    """Measure one level; returns the JSON record."""
    mesh = breast_phantom(level)
    materials = TissueMaterials()
    center = (mesh.nodes[:, :2].min(axis=0) + mesh.nodes[:, :2].max(axis=0)) / 2
    probe_nodes = top_surface_nodes(
        mesh, (center[0], center[1]), PROBE_FACE_HALF_SIZE_M, depth_m=PATCH_DEPTH_M
    )

    # A robust simulator brought to a preloaded, converged state that all timings start from.
    robust = TissueSimulator(mesh, materials, SimulationConfig(mode="robust"))
    depth = 0.0
    while depth < PRELOAD_DEPTH_M - 1e-12:
        depth += STEP_ADVANCE_M
        _press(robust, probe_nodes, depth)
        robust.step()
    loaded_positions = robust.positions.copy()
    loaded_velocities = robust.velocities.copy()
    elasticity = robust.elasticity

    # Forces + tangent (assembly), unprojected as in paper mode.
    elasticity.evaluate(loaded_positions, tangent=True)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        elasticity.evaluate(loaded_positions, tangent=True)
        samples.append(time.perf_counter() - start)
    assembly_ms = _median_ms(samples)

    # Newton (robust) steps continuing the compression: converged steps, reusing factorisations.
    samples, iterations, factorizations, statuses, residuals = [], [], [], [], []
    for _ in range(repeats):
        depth += STEP_ADVANCE_M
        _press(robust, probe_nodes, depth)
        result = robust.step()
        samples.append(result.compute_ms / 1e3)
        iterations.append(result.newton_iterations)
        factorizations.append(result.factorizations)
        statuses.append(result.status.value)
        residuals.append(result.newton_residual)
    newton_step_ms = _median_ms(samples)
    converged = statuses.count("ok") == len(statuses) and max(residuals) <= (
        robust.config.newton_tolerance
    )

    # One simulator (and one factorisation) alive at a time: peak memory is per level.
    del robust, elasticity
    gc.collect()

    # Paper-mode steps (assembly + 25 CG iterations + update) from the same loaded state.
    paper = TissueSimulator(mesh, materials, SimulationConfig(mode="paper"))
    paper.set_state(loaded_positions, loaded_velocities)
    paper_depth = PRELOAD_DEPTH_M
    samples = []
    for _ in range(repeats):
        paper_depth += STEP_ADVANCE_M
        _press(paper, probe_nodes, paper_depth)
        samples.append(paper.step().compute_ms / 1e3)
    paper_step_ms = _median_ms(samples)

    # Direct factorisation of the paper's system matrix, and how far 25 CG iterations are
    # from its exact solution in the energy norm.
    system = _paper_system(paper, probe_nodes, paper_depth + STEP_ADVANCE_M)
    factorizer = DirectFactorizer()
    factorizer.factorize(system.matrix, system.constrained)
    samples = []
    for _ in range(max(3, repeats // 3)):
        start = time.perf_counter()
        factorization, _ = factorizer.factorize(system.matrix, system.constrained)
        samples.append(time.perf_counter() - start)
    direct_factor_ms = _median_ms(samples)
    exact = factorization.solve(system.rhs)
    capped, report = LinearSolver(
        LinearSolverConfig(kind="cg", cg_max_iterations=25, cg_tolerance=1e-12)
    ).solve(system)
    error = capped - exact
    cg25_energy_error = float(
        np.sqrt(error @ (system.matrix @ error) / (exact @ (system.matrix @ exact)))
    )

    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {
        "level": level,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "assembly_ms": assembly_ms,
        "paper_step_ms": paper_step_ms,
        "direct_factor_ms": direct_factor_ms,
        "newton_step_ms": newton_step_ms,
        "newton_iterations_median": float(np.median(iterations)),
        "newton_factorizations_per_step": float(np.mean(factorizations)),
        "newton_status": max(set(statuses), key=statuses.count),
        # The largest relative Newton residual a timed step ended with (the tolerance is 1e-4).
        "newton_residual_max": float(np.max(residuals)),
        "cg25_energy_error": cg25_energy_error,
        "cg25_relative_residual": report.relative_residual,
        "peak_rss_mb": peak_mb,
        "repeats": repeats,
        **robust_step_target(level, newton_step_ms, converged),
    }


def _paper_system(sim: TissueSimulator, nodes: np.ndarray, depth_m: float) -> ConstrainedSystem:
    """The constrained linear system of the paper's eq. (5) at the simulator's state."""
    _press(sim, nodes, depth_m)
    dofs, targets = sim.constraints()
    linear = sim.integrator.paper_system(
        sim.positions, sim.velocities, sim.config.tissue_dt, dofs, targets
    )
    return linear.system


def run_tissue_benchmark(
    levels: list[int] | None, repeats: int, json_path: Path, command: str | None = None
) -> list[dict[str, float | int | str]]:
    """Benchmark ``levels`` (default 623 to 26,220 tets); print a table; write JSON."""
    levels = list(levels or DEFAULT_LEVELS)
    records = []
    header = (
        f"{'tets':>8} {'nodes':>7} {'assembly':>9} {'paper step':>11} {'factor':>8} "
        f"{'newton step':>12} {'newton it':>9} {'CG25 err':>9} {'peak MB':>8}"
    )
    print(
        f"probegym bench tissue — medians of {repeats} repeats, times in ms "
        f"({platform.processor() or platform.machine()})"
    )
    print(header)
    provenance = BenchRecord(f"probegym bench tissue: medians of {repeats} repeats", command)
    for level in levels:
        record = benchmark_level(level, repeats)
        records.append(record)
        print(
            f"{record['tets']:>8} {record['nodes']:>7} {record['assembly_ms']:>9.2f} "
            f"{record['paper_step_ms']:>11.2f} {record['direct_factor_ms']:>8.2f} "
            f"{record['newton_step_ms']:>12.2f} {record['newton_iterations_median']:>9.1f} "
            f"{record['cg25_energy_error']:>9.1%} {record['peak_rss_mb']:>8.0f}",
            flush=True,
        )
        json_path.parent.mkdir(parents=True, exist_ok=True)
        write_json(records, json_path, indent=2)  # keep what is measured so far
    print_robust_targets(records, "newton_step_ms", "Newton step")
    markdown = provenance.write(json_path, [_table(records)])
    print(f"written: {json_path}, {markdown}")
    return records


def _table(records: list[dict[str, Any]]) -> MarkdownTable:
    """The printed table as Markdown, with the robust step's target where a level has one."""
    table = MarkdownTable(
        "per level, times in ms",
        ["tets", "nodes", "assembly", "paper step", "factorisation", "Newton step",
         "Newton iterations", "CG25 energy error", "peak MB", "robust step target"],
    )  # fmt: skip
    for r in records:
        target = (
            f"{r['robust_target_step_ms']:.0f} ({'met' if r['meets_robust_target'] else 'missed'})"
            if "robust_target_step_ms" in r
            else ""
        )
        table.rows.append([
            f"{r['tets']:,}", f"{r['nodes']:,}", f"{r['assembly_ms']:.2f}",
            f"{r['paper_step_ms']:.2f}", f"{r['direct_factor_ms']:.2f}",
            f"{r['newton_step_ms']:.2f}", f"{r['newton_iterations_median']:.1f}",
            f"{r['cg25_energy_error']:.1%}", f"{r['peak_rss_mb']:.0f}", target,
        ])  # fmt: skip
    return table


def print_robust_targets(records: list, key: str, what: str) -> None:
    """Print the robust-step target lines for the ``records`` that carry one."""
    marked = [r for r in records if "robust_target_step_ms" in r]
    if not marked:
        return
    print("\ntargets: a converged robust step")
    for record in marked:
        verdict = "meets" if record["meets_robust_target"] else "MISSES"
        label = f"{record['method']:>10} " if "method" in record else ""
        print(
            f"  {label}{what} {record['tets']:>6} tets: {record[key]:8.2f} ms <= "
            f"{record['robust_target_step_ms']:.0f} ms? {verdict}"
        )
