"""Path following through limit points: arc-length (Riks/Crisfield) continuation of a quasi-static solid.

Solves f_int(u) = λ f̂ for the path (u(s), λ(s)), with the cylindrical arc-length constraint
‖Δu‖ = Δs on each increment (Crisfield 1981): the load factor λ is an unknown, so the path can pass a
limit point where the load falls while the deflection grows (snap-through), which load control
cannot. Each corrector iteration solves K δu_r = −G and K δu_f = f̂ with one LU factorisation and
picks δλ from the quadratic constraint (root closest to the previous direction). The step length
adapts to the Newton iteration count and is halved on failure, down to ``min_ds``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from .solid import Solid


@dataclass
class ArcLengthPath:
    """Load factor λ (× f̂ [N]) and a monitored displacement [m] per converged increment."""

    load_factor: list = field(default_factory=lambda: [0.0])
    displacement: list = field(default_factory=lambda: [0.0])
    ok: bool = True
    reason: str = ""


def arc_length(solid: Solid, f_hat: np.ndarray, monitor, ds: float, n_increments: int,
               max_load_factor: float = math.inf, max_displacement: float = math.inf,
               tol: float = 1e-8, max_iterations: int = 20, target_iterations: int = 5,
               min_ds: float | None = None) -> ArcLengthPath:
    """Trace f_int(u) = λ f̂ from the current state (λ = 0) with arc-length increments.

    f_hat: reference nodal load (N, 3) [N]; monitor(u (N, 3)) -> float the path records
    (e.g. a crown deflection [m]); ds: initial arc length [m] (displacement norm of an increment).
    Stops after n_increments, or when λ or the monitored value passes its maximum.
    """
    if solid.inertia:
        raise ValueError("arc-length continuation is quasi-static: build the solid without inertia")
    min_ds = min_ds if min_ds is not None else ds / 1024
    fhat_vec = solid.b.duplicate()
    fhat_vec.array[:] = np.asarray(f_hat, dtype=float).ravel()
    fem_petsc.set_bc(fhat_vec, solid.bcs, scale=0.0)
    du_r, du_f = solid.b.duplicate(), solid.b.duplicate()
    path = ArcLengthPath()
    lam = 0.0
    u0 = solid.u.x.array.copy()
    prev = None  # previous converged increment (Δu, Δλ) for the direction of the predictor

    def factor_and_solve(rhs, out) -> bool:
        try:
            solid.ksp.solve(rhs, out)
        except PETSc.Error:
            return False
        return solid.ksp.getConvergedReason() >= 0 and np.all(np.isfinite(out.array))

    def assemble_tangent() -> None:
        solid.A.zeroEntries()
        fem_petsc.assemble_matrix(solid.A, solid.jacobian_form, bcs=solid.bcs)
        solid.A.assemble()

    def residual(load: float) -> float:
        solid.set_nodal_force(load * np.asarray(f_hat))
        return solid._assemble_residual()

    for _ in range(n_increments):
        while True:
            # predictor along the tangent K δu_f = f̂, direction continuing the previous increment
            solid.u.x.array[:] = u0
            residual(lam)
            assemble_tangent()
            if not factor_and_solve(fhat_vec, du_f):
                path.ok, path.reason = False, "singular tangent at the predictor"
                return path
            t = du_f.array.copy()
            dlam = ds / np.linalg.norm(t)
            if prev is not None and float(np.dot(t, prev[0]) + 0.0) < 0:
                dlam = -dlam
            Du = dlam * t
            converged, its = False, 0
            for its in range(1, max_iterations + 1):
                solid.u.x.array[:] = u0 + Du
                norm = residual(lam + dlam)
                if not math.isfinite(norm):
                    break
                if norm <= tol * max(1.0, np.linalg.norm(f_hat) * abs(lam + dlam)):
                    converged = True
                    break
                assemble_tangent()
                solid.b.scale(-1.0)
                if not (factor_and_solve(solid.b, du_r) and factor_and_solve(fhat_vec, du_f)):
                    break
                r, f = du_r.array, du_f.array
                a = float(f @ f)
                b = 2.0 * float(f @ (Du + r))
                c = float((Du + r) @ (Du + r)) - ds**2
                disc = b * b - 4 * a * c
                if disc < 0:
                    break
                roots = [(-b + s * math.sqrt(disc)) / (2 * a) for s in (1.0, -1.0)]
                # the root keeping the increment closest to its current direction
                dl = max(roots, key=lambda x: float((Du + r + x * f) @ Du))
                Du = Du + r + dl * f
                dlam += dl
            if converged:
                break
            ds *= 0.5
            if ds < min_ds:
                path.ok, path.reason = False, f"arc length cut below {min_ds:.3g} m without convergence"
                solid.u.x.array[:] = u0
                return path
        u0 = solid.u.x.array.copy()
        lam += dlam
        prev = (Du, dlam)
        path.load_factor.append(lam)
        path.displacement.append(float(monitor(u0.reshape(-1, 3))))
        ds *= min(2.0, math.sqrt(target_iterations / max(its, 1)))
        if lam > max_load_factor or path.displacement[-1] > max_displacement:
            break
    return path
