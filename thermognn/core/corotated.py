"""The linearised FE solid corotated per cell: a physics baseline for large rotations.

The solid linearised at rest (``thermognn.core.linear``) reads a rotation as strain. Corotated,
each P1 cell e measures its linear force in its rotated frame, R_e from the polar decomposition
F_e = R_e U_e (``thermognn.core.kinematics``)::

    f_int(x) = Σ_e R_e K_e (R_eᵀ x_e − X_e)          [N]      (K_e: the cell's linear stiffness)

with a viscous solid's Prony internal forces kept per cell in the rotated frame, relaxed as
``LinearSolid`` relaxes them. A rigid rotation carries no force; small strains and rotations give
the linearised solid. The step is the data's Newmark rule (the trapezoidal rule, β = 1/4, γ = 1/2,
with the scene's Rayleigh damping), implicit in the rotations: each step solves

    (c0 (1 + αM γ dt) M + Σ_e R_e (K_dt,e + c K_e) R_eᵀ) u1 = f1 + M pred − (what R, X and the history give)

with R_e at the latest iterate of u1, repeated (fixed-point sweeps) until u1 moves by less than
``tol`` of the step's increment (plus 1e-13 of the mesh's size: round-off, where a step hardly
moves) or ``max_sweeps`` are done. Rotations frozen at the step's start
(one sweep) lag them by a step, and that lag is what fails where the rotations move fast: on the
shell's snap-through (docs/accuracy.md, session 42) the one-sweep form is 60 % off in v over
whole rollouts, two sweeps 8.5 %, more sweeps the same (σ 4.7 %). The Rayleigh stiffness term
damps the change of the corotated elastic force, c (f_el(x1) − f_el(x0)), c = βK/dt, so a rigid
rotation is not damped. The stress is the corotated linear stress per cell
(``linear_cell_stress(corotated=True, volume_from_det=False)``), node-averaged as the dataset
stores it: with the volume change tr ε̃ of the strain the force measures, so that it is the
stress the rollout balances. (J − 1 maps the *true* positions to the FE's stress better, and
``generate``'s rotation report uses it, but on this model's own positions it is off: the bent
block of ``tests/test_fe_modes.py`` at 1 N, ν = 0.45, σ 36 % off with J − 1, 8 % with tr ε̃.)

K_e is built from the Lamé moduli at rest (λ, μ [Pa]) that ``generate`` stores with ``/linear``
(``LinearSolid.shear_modulus``, ``bulk_modulus``): over P1 cells the assembled K_e are the stored
K (``tests/test_fe_modes.py``); with every R_e held at I this is the linearised model exactly.
One sparse LU a sweep. Numpy and scipy only (no torch, no dolfinx).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .kinematics import (P1Cells, deformation_gradients, linear_cell_stress, node_average, polar_rotations,
                         shape_gradients)
from .linear import LinearSolid, free_rows

#: fixed-point sweeps per step at most, and the relative change of u1 at which they stop
MAX_SWEEPS, TOL = 20, 1e-5


def element_stiffness(X: np.ndarray, tets: np.ndarray, lam: float, mu: float) -> tuple[np.ndarray, np.ndarray]:
    """K_e [T, 12, 12] N/m (DOFs node-major: 3 a + c) of σ = λ tr ε I + 2 μ ε on P1 cells ``tets``
    [T, 4] of nodes X [N, 3] [m], and its isochoric part (λ = −2μ/3), the part a Prony series relaxes."""
    grad, vol = shape_gradients(X, tets)                              # [T, 4, 3] 1/m, [T] m³
    B = np.zeros((len(tets), 6, 12))                                  # strain (Voigt, engineering shear) per DOF
    for a in range(4):
        for c in range(3):
            B[:, c, 3 * a + c] = grad[:, a, c]                         # ε_cc
        B[:, 3, 3 * a + 0], B[:, 3, 3 * a + 1] = grad[:, a, 1], grad[:, a, 0]   # γ_12
        B[:, 4, 3 * a + 0], B[:, 4, 3 * a + 2] = grad[:, a, 2], grad[:, a, 0]   # γ_13
        B[:, 5, 3 * a + 1], B[:, 5, 3 * a + 2] = grad[:, a, 2], grad[:, a, 1]   # γ_23

    def elasticity(l: float, m: float) -> np.ndarray:                # [6, 6] Pa
        d = np.zeros((6, 6))
        d[:3, :3] = l
        d[np.arange(3), np.arange(3)] += 2 * m
        d[np.arange(3, 6), np.arange(3, 6)] = m
        return d

    def stiffness(d: np.ndarray) -> np.ndarray:
        return np.einsum("t,tri,rs,tsj->tij", vol, B, d, B)

    return stiffness(elasticity(lam, mu)), stiffness(elasticity(-2.0 * mu / 3.0, mu))


@dataclasses.dataclass
class SweepCount:
    """Fixed-point sweeps taken by the rollouts so far: steps, sweeps in all, the most in one step,
    and the steps that stopped at ``max_sweeps`` without meeting ``tol``."""

    steps: int = 0
    sweeps: int = 0
    most: int = 0
    unconverged: int = 0

    @property
    def mean(self) -> float:
        return self.sweeps / max(self.steps, 1)


class CorotatedSolid(P1Cells):
    """The linearised solid ``lin`` (its mass, free DOFs, Rayleigh damping, Newmark β, γ, body
    force and Prony terms) corotated per P1 cell (module docstring), for nodes X [N, 3] [m], cells
    ``tets`` [T, 4] and Lamé moduli at rest λ, μ [Pa]. ``frozen``: every R_e = I (the linearised
    model, a check)."""

    def __init__(self, lin: LinearSolid, X: np.ndarray, tets: np.ndarray, lam: float, mu: float,
                 max_sweeps: int = MAX_SWEEPS, tol: float = TOL, frozen: bool = False) -> None:
        if lin.integrator != "newmark":
            raise ValueError(f"corotated FE: integrator {lin.integrator!r} is not reproduced (expected newmark)")
        self.lin, self.frozen = lin, frozen
        if np.ndim(tets) != 2 or np.shape(tets)[1] != 4:
            raise ValueError(f"corotated FE: cells of {np.shape(tets)[-1]} nodes, expected P1 tets (4)")
        super().__init__(X, tets, lin.free)
        self.lam, self.mu = float(lam), float(mu)
        self.max_sweeps, self.tol = int(max_sweeps), float(tol)
        self.K, self.K_iso = element_stiffness(self.X, self.tets, lam, mu)   # [T, 12, 12] N/m
        self.Xe = self.X[self.tets].reshape(len(self.tets), 12)              # [T, 12] m
        self.count = SweepCount()
        self._floor = 1e-13 * float(np.linalg.norm(self.X))               # [m]: round-off; a step that hardly moves stops

    @classmethod
    def of(cls, lin: LinearSolid, X: np.ndarray, tets: np.ndarray, **options) -> "CorotatedSolid":
        """From the moduli ``lin`` carries (``LinearSolid.lame``; ValueError where it carries none)."""
        return cls(lin, X, tets, *lin.lame(), **options)

    def first_inversion(self, q: np.ndarray) -> tuple[int, int] | None:
        """(step, cells) where positions q [S, N, 3] m first turn a cell inside out (det F ≤ 0),
        and how many it turns then; None where none is. The corotated solid's linear stress does
        not stiffen as a cell is crushed (a neo-Hookean one does), so a strong point load can push
        a cell through itself, after which its rollout is meaningless."""
        for s, x in enumerate(np.asarray(q, dtype=float)):
            bad = int((np.linalg.det(deformation_gradients(x, self.tets, self.grad)) <= 0.0).sum())
            if bad:
                return s, bad
        return None

    # -- per cell ------------------------------------------------------------------------------
    def rotations(self, x: np.ndarray) -> np.ndarray:
        """R_e [T, 3, 3] at positions x [N, 3] m (I when frozen)."""
        if self.frozen:
            return np.broadcast_to(np.eye(3), (len(self.tets), 3, 3))
        return polar_rotations(deformation_gradients(x, self.tets, self.grad))

    def local(self, R: np.ndarray, x: np.ndarray) -> np.ndarray:
        """R_eᵀ x_e − X_e [T, 12] m: each cell's displacement in its rotated frame."""
        xe = x[self.tets]                                                 # [T, 4, 3]
        return np.einsum("tji,taj->tai", R, xe).reshape(len(self.tets), 12) - self.Xe

    def rotate(self, R: np.ndarray, fe: np.ndarray) -> np.ndarray:
        """R_e applied to each node's 3-vector of cell vectors fe [T, 12] -> [T, 12]."""
        return np.einsum("tij,taj->tai", R, fe.reshape(-1, 4, 3)).reshape(-1, 12)

    def rotated_matrix(self, R: np.ndarray, Ke: np.ndarray) -> sp.csc_matrix:
        """Σ_e R_e K_e R_eᵀ over the free DOFs [n, n] (sparse), R_e block-diagonal per node."""
        T = len(self.tets)
        KR = np.einsum("tij,tajbk,tlk->taibl", R, Ke.reshape(T, 4, 3, 4, 3), R).reshape(T, 144)
        n = int(self.free.sum())
        return sp.coo_matrix((KR.ravel()[self._keep], (self._rows, self._cols)), shape=(n, n)).tocsc()

    def elastic_force(self, R: np.ndarray, x: np.ndarray) -> np.ndarray:
        """Σ_e R_e K_e (R_eᵀ x_e − X_e) over the free DOFs [n] N (unrelaxed)."""
        return self.scatter(self.rotate(R, np.einsum("tij,tj->ti", self.K, self.local(R, x))))

    # -- rollouts ------------------------------------------------------------------------------
    def rollout(self, u0: np.ndarray, v0: np.ndarray, forces: np.ndarray,
                dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Displacements U [S, n] m and velocities V [S, n] m/s over the free DOFs from u0 [n],
        v0 [n] under the free-DOF forces [S, n] N (forces[s] at t_s), as ``LinearSolid.rollout``
        with the corotated internal force (module docstring)."""
        lin = self.lin
        M = lin.mass
        F = np.asarray(forces, dtype=float)
        if lin.body_force is not None:
            F = F + np.asarray(lin.body_force, dtype=float)[None]
        alpha_m, beta_k = (float(r) for r in lin.rayleigh)
        b, g = float(lin.beta), float(lin.gamma)
        c0, c1, c = 1.0 / (b * dt**2), 1.0 / (2.0 * b) - 1.0, beta_k / dt
        terms = lin.relaxation(dt)
        shrink = sum(gi * (1.0 - w) for gi, _, w in terms)
        K_dt = self.K - shrink * self.K_iso if terms else self.K          # [T, 12, 12]: f_int,new = K_dt d_new + ...
        mass = sp.csc_matrix(c0 * (1.0 + alpha_m * g * dt) * M)
        solve_m = sla.factorized(sp.csc_matrix(M))

        u, v = np.array(u0, dtype=float), np.array(v0, dtype=float)
        x = self.positions(u)
        R = self.rotations(x)
        d = self.local(R, x)
        h = [np.einsum("tij,tj->ti", self.K_iso, d) for _ in terms]       # Prony internal forces, cell frames [T, 12] N
        f_el = self.elastic_force(R, x)
        a = solve_m(F[0] - f_el - alpha_m * (M @ v))
        U, V = [u], [v]
        for s in range(1, F.shape[0]):
            pred = c0 * (u + dt * v) + c1 * a                             # a1 = c0 u1 − pred
            rhs = F[s] + M @ pred + c * f_el + alpha_m * (M @ (g * dt * pred - v - dt * (1 - g) * a))
            u_it, sweeps = u, 0
            while True:                          # R: the rotations of u_it (the step's start: the last step's end)
                if sweeps > 0:
                    R = self.rotations(self.positions(u_it))
                d_old = self.local(R, x)
                hist = sum((gi * (decay * hi - w * np.einsum("tij,tj->ti", self.K_iso, d_old))
                            for (gi, decay, w), hi in zip(terms, h)), np.zeros_like(d_old))
                # f_int(u1) + c f_el(u1) = (K_R,dt + c K_R) u1 + Σ R ((K_dt + c K)(Rᵀ X − X) + hist)
                rot_X = self.local(R, self.X)                             # R_eᵀ X_e − X_e
                offset = self.scatter(self.rotate(R, np.einsum("tij,tj->ti", K_dt + c * self.K, rot_X) + hist))
                A = mass + self.rotated_matrix(R, K_dt + c * self.K)
                u_new = sla.spsolve(sp.csc_matrix(A), rhs - offset)
                sweeps += 1
                change = np.linalg.norm(u_new - u_it)
                u_it = u_new
                if self.frozen or change <= self.tol * np.linalg.norm(u_new - u) + self._floor:
                    break
                if sweeps >= self.max_sweeps:
                    self.count.unconverged += 1
                    break
            self.count.steps += 1
            self.count.sweeps += sweeps
            self.count.most = max(self.count.most, sweeps)
            a_new = c0 * u_new - pred
            v = v + dt * ((1 - g) * a + g * a_new)
            x_new = self.positions(u_new)
            R = self.rotations(x_new)                                     # the rotations u1 ends with
            d_new = self.local(R, x_new)
            h = [decay * hi + w * np.einsum("tij,tj->ti", self.K_iso, d_new - self.local(R, x))
                 for (_, decay, w), hi in zip(terms, h)]
            f_el = self.elastic_force(R, x_new)
            u, x, a = u_new, x_new, a_new
            U.append(u)
            V.append(v)
        return np.asarray(U), np.asarray(V)

    def rollout_states(self, z: np.ndarray, forces: np.ndarray, X: np.ndarray, layout,
                       dt: float) -> np.ndarray:
        """The corotated model's states [S, N, D] from the first of the data states z [S, N, D]
        under the stored nodal forces [S, N, 3] N, as ``LinearSolid.rollout_states``: q = X + u [m],
        v [m/s], σ the corotated linear stress node-averaged [Pa]; any other column held at z[0]."""
        z = np.asarray(z, dtype=float)
        S, N = z.shape[0], z.shape[1]
        if "v" not in layout.names:
            raise ValueError("corotated FE: the state has no velocity (quasi-static data)")
        sv = layout.slice("v")
        U, V = self.rollout(free_rows(z[:1, :, 0:3] - X[None], self.free)[0],
                            free_rows(z[:1, :, sv], self.free)[0], free_rows(forces, self.free), dt)
        out = np.repeat(z[:1], S, axis=0)                                 # [S, N, D]
        out[..., 0:3] = X[None] + self.nodal(U)
        out[..., sv] = self.nodal(V)
        if "sigma" in layout.names:
            cell = linear_cell_stress(out[..., 0:3], self.X, self.tets, self.lam, self.mu, self.lin.prony, dt,
                                      corotated=not self.frozen, volume_from_det=False)
            out[..., layout.slice("sigma")] = node_average(cell, self.tets, self.volume, N)
        return out
