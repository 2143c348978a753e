"""The FE solid linearised at its rest state: the physics baseline a learned model must beat.

Linearised about the undeformed rest state, the discrete solid obeys::

    M ü + C u̇ + K u = f(t),    K = ∂f_int/∂u at u = 0 [N/m],   M = ∫ ρ N_i N_j dX [kg],
    σ(u) ≈ Σ u                 (nodal Cauchy stress [Pa], Voigt 11 22 33 12 13 23)

A viscous solid relaxes the isochoric part of its stress by a Prony series
g_R(t) = 1 − Σ ḡ_i (1 − exp(−t/τ_i)) (``thermognn/generate/solid.py``); linearised, the isochoric
parts K_iso of K and Σ_iso of Σ relax the same way (the volumetric parts K − K_iso, Σ − Σ_iso
do not)::

    f_int(t) = (K − K_iso) u + (1 − Σ ḡ_i) K_iso u + Σ ḡ_i h_i,   h_i(t) = ∫ exp(−(t−s)/τ_i) K_iso u̇(s) ds

with h_i [N] updated over a step Δt as the FE updates its own (exact for u linear within the
step): h_i ← exp(−Δt/τ_i) h_i + τ_i/Δt (1 − exp(−Δt/τ_i)) K_iso (u_new − u_old); the stress alike.

over the free (not clamped) DOFs, node-blocked (node i, component c at 3 i + c). ``generate``
assembles K, M and Σ from its own solid (``thermognn/generate/modes.py``) and stores them in the
dataset (``/linear``, ``thermognn/core/schema.py``); :class:`LinearSolid` steps them with the
data's own time integrator, so that ``evaluate`` can report, beside every learned model, what
the linearised FE model scores on the same trajectories (no training, one sparse LU solve a step).

numpy only (no torch, no dolfinx): the FE side and the learning side both use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: integrators :meth:`LinearSolid.rollout` reproduces (generalized-α: not yet)
INTEGRATORS = ("newmark", "quasi_static")


def free_rows(a: np.ndarray, free: np.ndarray) -> np.ndarray:
    """[S, N, 3] nodal vectors -> [S, n] over the DOFs where ``free`` [3N] is True."""
    a = np.asarray(a, dtype=float)
    return a.reshape(a.shape[0], -1)[:, free]


def lu_solver(A):
    """x = solve(b) for a dense or scipy.sparse square matrix A (LU, factorised once)."""
    import scipy.sparse as sp

    if sp.issparse(A):
        import scipy.sparse.linalg as sla

        return sla.splu(A.tocsc()).solve
    import scipy.linalg as sl

    lu = sl.lu_factor(A)
    return lambda b: sl.lu_solve(lu, b)


@dataclass
class LinearSolid:
    """Linearised FE operators over the n free DOFs of an N-node mesh.

    stiffness [n, n] N/m and mass [n, n] kg (symmetric; numpy or scipy.sparse), free [3N] bool
    (the DOFs they act on), stress [6N, n] Pa/m (nodal Cauchy stress of a free-DOF displacement,
    numpy or scipy.sparse; None if not available),
    rayleigh (αM [1/s], βK [s]) damping written as the FE solid writes it, integrator
    ('newmark' | 'quasi_static' | another name, which :meth:`rollout` refuses), Newmark β, γ,
    body_force [n] N (gravity, or None); for a viscous solid its Prony terms prony ((ḡ_i, τ_i [s]),
    ...) with the isochoric parts stiffness_iso [n, n] N/m and stress_iso [6N, n] Pa/m of K and Σ
    (module docstring; () and None for an elastic one); the law's shear and bulk moduli at rest
    μ0, K0 [Pa] (None where unknown: the corotated baseline, ``thermognn.core.corotated``, needs them)."""

    stiffness: np.ndarray
    mass: np.ndarray
    free: np.ndarray
    stress: np.ndarray | None = None
    rayleigh: tuple[float, float] = (0.0, 0.0)
    integrator: str = "newmark"
    beta: float = 0.25
    gamma: float = 0.5
    body_force: np.ndarray | None = None
    prony: tuple[tuple[float, float], ...] = ()
    stiffness_iso: np.ndarray | None = None
    stress_iso: np.ndarray | None = None
    shear_modulus: float | None = None
    bulk_modulus: float | None = None
    #: LU factorisations by (integrator, dt) (and of K, "instantaneous"), made on the first rollout that needs them
    _factors: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def lame(self) -> tuple[float, float]:
        """The Lamé moduli at rest (λ = K0 − 2 μ0 / 3, μ0) [Pa]; ValueError where the moduli are
        unknown (a dataset written before ``generate`` stored them with ``/linear``)."""
        if self.shear_modulus is None or self.bulk_modulus is None:
            raise ValueError("the dataset's /linear holds no moduli at rest (regenerate it to add them)")
        mu = float(self.shear_modulus)
        return float(self.bulk_modulus) - 2.0 * mu / 3.0, mu

    @property
    def viscous(self) -> bool:
        return bool(self.prony) and self.stiffness_iso is not None

    def relaxation(self, dt: float) -> list[tuple[float, float, float]]:
        """Per Prony term (ḡ_i, exp(−dt/τ_i), τ_i/dt (1 − exp(−dt/τ_i))): its weight, and the decay and
        the increment's weight of its internal variable over a step dt (none for an elastic solid)."""
        if not self.viscous:
            return []
        return [(float(g), math.exp(-dt / tau), -math.expm1(-dt / tau) / (dt / tau)) for g, tau in self.prony]

    def step_stiffness(self, dt: float):
        """K_dt [n, n] N/m: f_int at a step's end is K_dt u_new plus what the internal variables
        and u_old give (:meth:`relaxation`); K for an elastic solid."""
        terms = self.relaxation(dt)
        if not terms:
            return self.stiffness
        return self.stiffness - sum(g * (1.0 - c) for g, _, c in terms) * self.stiffness_iso

    def _solvers(self, dt: float, alpha_m: float, beta_k: float):
        """(solve with the step's effective stiffness, solve with M) for newmark; (solve with the
        step's stiffness, None) for quasi-static; factorised once per integrator and dt."""
        key = (self.integrator, float(dt), alpha_m, beta_k, float(self.beta), float(self.gamma))
        if key not in self._factors:
            K, M = self.step_stiffness(dt), self.mass
            if self.integrator == "quasi_static":
                self._factors[key] = (lu_solver(K), None)
            else:
                c0 = 1.0 / (self.beta * dt**2)
                self._factors[key] = (lu_solver(c0 * (1.0 + alpha_m * self.gamma * dt) * M + K
                                                + beta_k / dt * self.stiffness), lu_solver(M))
        return self._factors[key]

    def _relaxed(self, A, A_iso, U: np.ndarray, dt: float) -> np.ndarray:
        """A u [S, m] along displacements U [S, n] with A's isochoric part A_iso relaxed (module
        docstring; the internal variables start as if U[0] were applied at once); A U if elastic."""
        out = np.asarray(A @ U.T).T
        terms = self.relaxation(dt)
        if not terms or A_iso is None:
            return out
        iso = np.asarray(A_iso @ U.T).T                                # [S, m]
        for g, decay, weight in terms:
            h = iso[0].copy()
            for s in range(1, U.shape[0]):
                h = decay * h + weight * (iso[s] - iso[s - 1])
                out[s] += g * (h - iso[s])
        return out

    @property
    def n_free(self) -> int:
        return int(self.stiffness.shape[0])

    def free_rows(self, a: np.ndarray) -> np.ndarray:
        """[S, N, 3] nodal vectors -> [S, n] over the free DOFs."""
        return free_rows(a, self.free)

    def rollout(self, u0: np.ndarray, v0: np.ndarray | None, forces: np.ndarray,
                dt: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Displacements U [S, n] [m] and velocities V [S, n] [m/s] (None for quasi-static) from
        u0 [n], v0 [n] under the free-DOF forces [S, n] [N] (forces[s] acts at t_s, s = 0 the
        start), with the data's own integrator applied to the linear system:

        * ``newmark``: M a_{n+1} + αM M v_{n+1} + βK K (u_{n+1} − u_n)/dt + f_int,{n+1} = f_{n+1}
          with Newmark (β, γ), and M a_0 = f_0 − K u_0 − αM M v_0 (balance at the start; the
          FE's stiffness damping takes the unrelaxed elastic stress's rate, hence K);
        * ``quasi_static``: f_int,s = f_s at every snapshot;

        f_int = K u for an elastic solid, relaxed as in the module docstring for a viscous one.
        """
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"linearised FE: integrator {self.integrator!r} is not reproduced "
                             f"(expected {' or '.join(INTEGRATORS)})")
        K, M = self.stiffness, self.mass
        F = np.asarray(forces, dtype=float)                            # [S, n]
        if self.body_force is not None:
            F = F + np.asarray(self.body_force, dtype=float)[None]
        alpha_m, beta_k = (float(r) for r in self.rayleigh)
        solve, solve_m = self._solvers(dt, alpha_m, beta_k)
        terms = self.relaxation(dt)
        u = np.array(u0, dtype=float)
        h = [self.stiffness_iso @ u for _ in terms]                   # Prony internal forces [N]

        def history(u_old):                 # f_int,new − K_dt u_new: what u_old and the h_i give [N]
            if not terms:
                return np.zeros_like(u_old)
            iso = self.stiffness_iso @ u_old
            return sum((g * (decay * hi - weight * iso) for (g, decay, weight), hi in zip(terms, h)),
                       np.zeros_like(u_old))

        def relax(u_old, u_new):
            if not terms:
                return []
            iso = self.stiffness_iso @ (u_new - u_old)
            return [decay * hi + weight * iso for (_, decay, weight), hi in zip(terms, h)]

        if self.integrator == "quasi_static":
            if not terms:
                return np.stack([solve(f) for f in F]), None
            if "instantaneous" not in self._factors:
                self._factors["instantaneous"] = lu_solver(K)
            u = self._factors["instantaneous"](F[0])                   # the instantaneous response to f_0
            h = [self.stiffness_iso @ u for _ in terms]
            U = [u]
            for f in F[1:]:
                u_new = solve(f - history(u))
                h, u = relax(u, u_new), u_new
                U.append(u)
            return np.stack(U), None
        if v0 is None:
            raise ValueError("linearised FE: newmark needs the velocity v0")
        b, g = float(self.beta), float(self.gamma)
        c0, c1, c = 1.0 / (b * dt**2), 1.0 / (2.0 * b) - 1.0, beta_k / dt
        v = np.array(v0, dtype=float)
        a = solve_m(F[0] - K @ u - alpha_m * (M @ v))
        U, V = [u], [v]
        for s in range(1, F.shape[0]):
            pred = c0 * (u + dt * v) + c1 * a                          # a_{n+1} = c0 u_{n+1} − pred
            rhs = (F[s] + M @ pred + c * (K @ u) - history(u)
                   + alpha_m * (M @ (g * dt * pred - v - dt * (1 - g) * a)))
            u_new = solve(rhs)
            a_new = c0 * u_new - pred
            v = v + dt * ((1 - g) * a + g * a_new)
            h, u, a = relax(u, u_new), u_new, a_new
            U.append(u)
            V.append(v)
        return np.asarray(U), np.asarray(V)

    def rollout_states(self, z: np.ndarray, forces: np.ndarray, X: np.ndarray, layout,
                       dt: float) -> np.ndarray:
        """The linearised model's states [S, N, D] from the first of the data states z [S, N, D]
        under the stored nodal forces [S, N, 3] [N]: q = X + u [m], v [m/s] (with inertia),
        sigma = Σ u [Pa] when the stress operator is known; clamped entries and any other
        column (e.g. Prony internal variables) are held at z[0]. X: reference positions [N, 3]."""
        z = np.asarray(z, dtype=float)
        S, N = z.shape[0], z.shape[1]
        X = np.asarray(X, dtype=float)
        has_v = "v" in layout.names and self.integrator == "newmark"
        u0 = self.free_rows(z[:1, :, 0:3] - X[None])[0]
        v0 = self.free_rows(z[:1, :, layout.slice("v")])[0] if has_v else None
        U, V = self.rollout(u0, v0, self.free_rows(forces), dt)
        out = np.repeat(z[:1], S, axis=0)                              # [S, N, D]
        u_all = np.zeros((S, 3 * N))
        u_all[:, self.free] = U
        out[..., 0:3] = X[None] + u_all.reshape(S, N, 3)
        if V is not None:
            v_all = np.zeros((S, 3 * N))
            v_all[:, self.free] = V
            out[..., layout.slice("v")] = v_all.reshape(S, N, 3)
        if self.stress is not None and "sigma" in layout.names:
            out[..., layout.slice("sigma")] = self._relaxed(self.stress, self.stress_iso, U, dt).reshape(S, N, 6)
        return out
