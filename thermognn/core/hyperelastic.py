"""The data's own hyperelastic law on P1 cells, stepped with a fixed Newton budget: the FE model
itself, without dolfinx, and what it costs at each accuracy.

``generate`` solves each time step of a scene to a tight residual (docs/accuracy.md, session 49:
about 3 Newton iterations a step on the bunny, 10 with its step cuts). A real-time FE solver
takes a fixed budget instead; one iteration from the predictor u_n + Δt v_n is the linearly
implicit step. ``benchmarks/newton_budget.py`` measures that budget with dolfinx; this module is
the same solid in numpy and scipy (no dolfinx, no torch), so that ``train``'s side can step it.

On a P1 cell the deformation gradient is constant, F_e = Σ_a x_a ⊗ Grad φ_a, so the FE's
integrals are exact one-point sums. The decoupled neo-Hookean law of the scenes
(``thermognn.generate.materials``), in the second Piola–Kirchhoff stress::

    Ψ = C10 (J^(-2/3) I1 − 3) + (J − 1)² / D1                          [Pa]
    S_iso = 2 C10 J^(-2/3) (I − I1/3 C⁻¹),   S_vol = (2/D1) (J − 1) J C⁻¹

and the Prony series on S_iso with the FE's internal variables per cell (h_i, and S_iso at the
step's start), exactly as ``Solid`` updates them::

    h_i,n+1 = e^(−Δt/τ_i) h_i,n + (τ_i/Δt)(1 − e^(−Δt/τ_i)) (S_iso,n+1 − S_iso,n)
    S = S_vol + g∞ S_iso + Σ_i ḡ_i h_i,         g∞ = 1 − Σ ḡ_i

The balance is the data's Newmark rule (β, γ; generalized-α is not reproduced) with the stored
mass M, body force and Rayleigh damping (αM M v, and βK (P_el(F) − P_el(F_n)) / Δt, the elastic
stress rate, as ``Solid`` writes it), residual over the free DOFs::

    R(u) = M a(u) + αM M v(u) + Σ_e V_e P(F_e) Grad φ + βK-term − f_ext − f_body

each Newton iteration one sparse LU of its exact tangent (∂P/∂F per cell from the directional
derivative of P = F S along the nine unit directions). The Cauchy stress σ = J⁻¹ F S Fᵀ per cell,
node-averaged by volume, is the dataset's. The liver's Ogden law (``Ogden``) takes its isochoric
stress from the FE's own regularised eigenvalue expression by complex-step differentiation and
its tangent by central differences.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .kinematics import P1Cells, deformation_gradients, node_average
from .linear import LinearSolid, free_rows

#: Newton's stopping rule when the budget is not the limit: ‖R‖ ≤ max(ATOL, RTOL ‖R0‖) (the scenes')
RTOL, ATOL = 1e-8, 1e-10
#: iterations a step at most without a budget
MAX_ITERATIONS = 50


class NeoHookean:
    """The decoupled neo-Hookean law Ψ = C10 (J^(-2/3) I1 − 3) + (J − 1)²/D1 (C10 [Pa], D1 [1/Pa]),
    its stresses and tangent in closed form."""

    def __init__(self, c10: float, d1: float) -> None:
        self.c10, self.d1 = float(c10), float(d1)

    def pk2(self, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S_iso, S_vol) [..., 3, 3] Pa of deformation gradients F [..., 3, 3]."""
        C = np.swapaxes(F, -1, -2) @ F
        Ci = np.linalg.inv(C)
        J = np.linalg.det(F)[..., None, None]
        I1 = np.trace(C, axis1=-2, axis2=-1)[..., None, None]
        s_iso = 2.0 * self.c10 * J ** (-2.0 / 3.0) * (np.eye(3) - I1 / 3.0 * Ci)
        s_vol = 2.0 / self.d1 * (J - 1.0) * J * Ci
        return s_iso, s_vol

    def pk1_tangent(self, F: np.ndarray, iso: float, extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """P = F (S_vol + iso S_iso + extra) [T, 3, 3] Pa and ∂P/∂F [T, 3, 3, 3, 3] (P_ij by F_kl)
        for cells' F [T, 3, 3], ``extra`` [T, 3, 3] a stress constant in F (the Prony history's)."""
        G = np.swapaxes(np.linalg.inv(F), -1, -2)                       # F⁻ᵀ
        J = np.linalg.det(F)[:, None, None]
        I1 = np.einsum("tij,tij->t", F, F)[:, None, None]
        a = J ** (-2.0 / 3.0)
        k = 2.0 / self.d1
        P = iso * 2.0 * self.c10 * a * (F - I1 / 3.0 * G) + k * (J - 1.0) * J * G
        if extra is not None:
            P = P + F @ extra
        A = np.zeros(F.shape[:1] + (3, 3, 3, 3))
        for kk in range(3):
            for ll in range(3):
                dF = np.zeros((3, 3))
                dF[kk, ll] = 1.0
                trG = G[:, kk, ll][:, None, None]                          # G : dF = d(ln J)
                dG = -G[:, :, ll][:, :, None] * G[:, kk, :][:, None, :]    # −G dFᵀ G
                dI1 = 2.0 * F[:, kk, ll][:, None, None]
                da = -2.0 / 3.0 * a * trG
                dP = (iso * 2.0 * self.c10 * (da * (F - I1 / 3.0 * G) + a * (dF - dI1 / 3.0 * G - I1 / 3.0 * dG))
                      + k * ((2.0 * J - 1.0) * J * trG * G + (J - 1.0) * J * dG))
                if extra is not None:
                    dP = dP + dF @ extra
                A[:, :, :, kk, ll] = dP
        return P, A


class Ogden:
    """The decoupled Ogden law Ψ = Σ_i 2 μ_i/α_i² (Σ_a λ̄_a^α_i − 3) + Σ_i (J − 1)^(2i)/D_i, with the
    principal stretches from the FE's regularised trigonometric eigenvalues of C̄ = J^(-2/3) C
    (``thermognn.generate.materials.regularised_eigenvalues``, ε = ``eps``): S_iso = 2 ∂Ψ_iso/∂C by
    complex-step differentiation of that same expression (exact to round-off, as UFL
    differentiates it), the tangent ∂P/∂F by central differences of P (step ``FD_STEP``)."""

    #: the FE's regularisation of the deviatoric norm (``generate.materials.EIGEN_EPS``)
    EIGEN_EPS = 1.0e-6
    #: central-difference step of the tangent (F is dimensionless, ~1)
    FD_STEP = 1.0e-6

    def __init__(self, mu: Sequence[float], alpha: Sequence[float], d: Sequence[float]) -> None:
        self.mu, self.alpha, self.d = (tuple(float(x) for x in v) for v in (mu, alpha, d))

    def isochoric_energy(self, C: np.ndarray) -> np.ndarray:
        """Ψ_iso [...] Pa of right Cauchy–Green tensors C [..., 3, 3] (real or complex: every
        operation is the analytic one, inner products without conjugation)."""
        J = np.sqrt(np.linalg.det(C))
        Cb = J[..., None, None] ** (-2.0 / 3.0) * C
        m = np.trace(Cb, axis1=-2, axis2=-1) / 3.0
        B = Cb - m[..., None, None] * np.eye(3)
        p = np.sqrt(np.einsum("...ij,...ij->...", B, B) / 6.0 + self.EIGEN_EPS**2)
        r = np.linalg.det(B) / (2.0 * p**3)
        r = np.where(r.real > 1.0, 1.0, np.where(r.real < -1.0, -1.0, r))
        phi = np.arccos(r) / 3.0
        psi = 0.0
        for mu, alpha in zip(self.mu, self.alpha):
            stretches = sum((m + 2.0 * p * np.cos(phi + 2.0 * math.pi * k / 3.0)) ** (alpha / 2.0) for k in range(3))
            psi = psi + 2.0 * mu / alpha**2 * (stretches - 3.0)
        return psi

    def pk2(self, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(S_iso, S_vol) [..., 3, 3] Pa of deformation gradients F [..., 3, 3]."""
        C = np.swapaxes(F, -1, -2) @ F
        h = 1e-30
        probe = np.zeros((9,) + C.shape, dtype=complex)                 # [9, ..., 3, 3]: C + i h E_kl
        probe[:] = C
        for k in range(3):
            for l in range(3):
                probe[3 * k + l, ..., k, l] += 1j * h
        dpsi = self.isochoric_energy(probe).imag / h                    # [9, ...]
        s_iso = 2.0 * np.moveaxis(dpsi, 0, -1).reshape(C.shape)
        J = np.linalg.det(F)[..., None, None]
        dU = sum(2.0 * (i + 1) * (J - 1.0) ** (2 * i + 1) / di for i, di in enumerate(self.d))
        return s_iso, dU * J * np.linalg.inv(C)

    def pk1(self, F: np.ndarray, iso: float, extra: np.ndarray | None = None) -> np.ndarray:
        """P = F (S_vol + iso S_iso + extra) [T, 3, 3] Pa."""
        s_iso, s_vol = self.pk2(F)
        S = s_vol + iso * s_iso + (extra if extra is not None else 0.0)
        return F @ S

    def pk1_tangent(self, F: np.ndarray, iso: float, extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """As ``NeoHookean.pk1_tangent``, the tangent by central differences."""
        steps = np.zeros((19, 1, 3, 3))                                  # 0, then ± h E_kl
        for k in range(3):
            for l in range(3):
                steps[1 + 3 * k + l, 0, k, l], steps[10 + 3 * k + l, 0, k, l] = self.FD_STEP, -self.FD_STEP
        P = self.pk1(F[None] + steps, iso, extra)                         # [19, T, 3, 3], all at once
        A = np.moveaxis((P[1:10] - P[10:]) / (2.0 * self.FD_STEP), 0, -1).reshape(F.shape + (3, 3))
        return P[0], A


def law_from_config(material: dict) -> tuple["NeoHookean | Ogden", tuple[tuple[float, float], ...]]:
    """(the law, Prony ((ḡ, τ [s]), ...)) of a scene's ``material`` mapping (the dataset's config;
    ValueError naming the law where it is neither neo-Hookean nor Ogden)."""
    law = material.get("law")
    prony = tuple((float(t["g"]), float(t["tau"])) for t in (material.get("prony") or []))
    if law == "neo_hookean":
        return NeoHookean(material["C10"], material["D1"]), prony
    if law == "ogden":
        return Ogden(material["mu"], material["alpha"], material["D"]), prony
    raise ValueError(f"hyperelastic FE: scene.material.law {law!r} is not reproduced (expected neo_hookean or ogden)")


class HyperelasticSolid(P1Cells):
    """The scene's hyperelastic solid (``law``: ``NeoHookean`` or ``Ogden``; Prony terms ((ḡ, τ [s]),
    ...)) on P1 cells ``tets`` [T, 4] of nodes X [N, 3] [m], with the mass, free DOFs, body force,
    Rayleigh damping and Newmark β, γ of ``lin`` (the dataset's ``/linear``), stepped with at most
    ``iterations`` Newton iterations a step (0: to the tolerance; module docstring)."""

    def __init__(self, lin: LinearSolid, X: np.ndarray, tets: np.ndarray, law, prony: Sequence[tuple[float, float]] = (),
                 iterations: int = 0) -> None:
        if lin.integrator != "newmark":
            raise ValueError(f"hyperelastic FE: integrator {lin.integrator!r} is not reproduced (expected newmark)")
        super().__init__(X, tets, lin.free)
        self.lin, self.law = lin, law
        self.prony = tuple((float(g), float(tau)) for g, tau in prony)
        self.iterations = int(iterations)
        n = int(self.free.sum())
        # the cells' pairs summed into one CSC pattern, built once: slot of each kept pair
        pairs, self._slot = np.unique(self._cols * n + self._rows, return_inverse=True)
        self._indices = (pairs % n).astype(np.int32)
        self._indptr = np.searchsorted(pairs // n, np.arange(n + 1)).astype(np.int32)
        mass = sp.csc_matrix(lin.mass)
        self._mass_values = np.asarray(mass[self._indices, np.repeat(np.arange(n), np.diff(self._indptr))]).ravel()
        if not np.isclose(self._mass_values.sum(), mass.sum(), rtol=1e-12, atol=0.0):
            raise ValueError("hyperelastic FE: the stored mass couples DOFs no cell couples (not a P1 mass)")
        self.steps = self.newton_iterations = 0

    @classmethod
    def of(cls, lin: LinearSolid, X: np.ndarray, tets: np.ndarray, material: dict, **options) -> "HyperelasticSolid":
        """From a scene's ``material`` mapping (the dataset's config)."""
        law, prony = law_from_config(material)
        return cls(lin, X, tets, law, prony, **options)

    # -- assembly ----------------------------------------------------------------------------
    def force_and_tangent(self, P: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, sp.csc_matrix]:
        """Σ_e V_e P_e Grad φ_a over the free DOFs [n] N and its tangent [n, n] N/m."""
        fe = np.einsum("t,tij,taj->tai", self.volume, P, self.grad).reshape(len(self.tets), 12)
        AG = np.einsum("tijkl,tbl->tijbk", A, self.grad)                  # [T, 3, 3, 4, 3]
        Ke = np.einsum("t,taj,tijbk->taibk", self.volume, self.grad, AG).reshape(len(self.tets), 144)
        return self.scatter(fe), self.matrix(np.bincount(self._slot, Ke.ravel()[self._keep], len(self._indices)))

    def matrix(self, values: np.ndarray) -> sp.csc_matrix:
        """The free-DOF matrix [n, n] of values in the cells' pattern (``_slot`` order)."""
        n = len(self._indptr) - 1
        return sp.csc_matrix((values, self._indices, self._indptr), shape=(n, n))

    # -- rollouts ----------------------------------------------------------------------------
    def rollout(self, u0: np.ndarray, v0: np.ndarray, forces: np.ndarray, dt: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Displacements U [S, n] m, velocities V [S, n] m/s over the free DOFs and the cells'
        Cauchy stresses [S, T, 3, 3] Pa from u0, v0 (the Prony history at rest: the first state
        as if applied at once, as ``generate`` starts) under the free-DOF forces [S, n] N."""
        lin = self.lin
        M = sp.csc_matrix(lin.mass)
        Fext = np.asarray(forces, dtype=float)
        if lin.body_force is not None:
            Fext = Fext + np.asarray(lin.body_force, dtype=float)[None]
        alpha_m, beta_k = (float(r) for r in lin.rayleigh)
        b, g = float(lin.beta), float(lin.gamma)
        c0 = 1.0 / (b * dt**2)
        decay = [math.exp(-dt / tau) for _, tau in self.prony]
        coef = [-math.expm1(-dt / tau) / (dt / tau) for _, tau in self.prony]
        g_inf = 1.0 - sum(gi for gi, _ in self.prony)
        iso = g_inf + sum(gi * ci for (gi, _), ci in zip(self.prony, coef))   # S_iso's weight in a step

        def committed(s_iso: np.ndarray, s_vol: np.ndarray, h: list[np.ndarray]) -> np.ndarray:
            """S = S_vol + g∞ S_iso + Σ ḡ_i h_i [T, 3, 3] Pa of a committed state."""
            return s_vol + g_inf * s_iso + sum(gi * hi for (gi, _), hi in zip(self.prony, h))

        u, v = np.array(u0, dtype=float), np.array(v0, dtype=float)
        Fc = deformation_gradients(self.positions(u), self.tets, self.grad)
        s_iso_n, s_vol = self.law.pk2(Fc)
        h = [s_iso_n.copy() for _ in self.prony]                          # h_i = S_iso(F0): applied at once
        P0 = Fc @ committed(s_iso_n, s_vol, h)
        f_int0 = self.scatter(np.einsum("t,tij,taj->tai", self.volume, P0, self.grad).reshape(len(self.tets), 12))
        a = sla.spsolve(M, Fext[0] - f_int0 - alpha_m * (M @ v))
        P_el_n = Fc @ (s_iso_n + s_vol)
        U, V, SIG = [u], [v], [self.cauchy(Fc, committed(s_iso_n, s_vol, h))]
        for s in range(1, Fext.shape[0]):
            hist = (sum(gi * (d * hi - c * s_iso_n) for (gi, _), d, c, hi in zip(self.prony, decay, coef, h))
                    if self.prony else None)                              # S's part fixed within the step
            u_it = u + dt * v                                             # the FE's predictor
            it, norm0 = 0, None
            while not (self.iterations and it >= self.iterations):       # the budget spent: take the iterate
                a_new = c0 * (u_it - u - dt * v) - (1.0 / (2.0 * b) - 1.0) * a
                v_new = v + dt * ((1.0 - g) * a + g * a_new)
                F = deformation_gradients(self.positions(u_it), self.tets, self.grad)
                P, A = self.law.pk1_tangent(F, iso, hist)
                f_int, K = self.force_and_tangent(P, A)
                R = M @ a_new + alpha_m * (M @ v_new) + f_int - Fext[s]
                T = K + self.matrix((c0 * (1.0 + alpha_m * g * dt)) * self._mass_values)
                if beta_k:
                    P_el, A_el = self.law.pk1_tangent(F, 1.0)
                    f_el, K_el = self.force_and_tangent(P_el - P_el_n, A_el)
                    R = R + beta_k / dt * f_el
                    T = T + beta_k / dt * K_el
                norm = float(np.linalg.norm(R))
                norm0 = norm if norm0 is None else norm0
                if norm <= max(ATOL, RTOL * norm0) or it >= MAX_ITERATIONS:
                    break
                u_it = u_it - sla.splu(T).solve(R)
                it += 1
            self.steps += 1
            self.newton_iterations += it
            a_new = c0 * (u_it - u - dt * v) - (1.0 / (2.0 * b) - 1.0) * a
            v = v + dt * ((1.0 - g) * a + g * a_new)
            F = deformation_gradients(self.positions(u_it), self.tets, self.grad)
            s_iso, s_vol = self.law.pk2(F)
            h = [d * hi + c * (s_iso - s_iso_n) for d, c, hi in zip(decay, coef, h)]
            s_iso_n, u, a = s_iso, u_it, a_new
            P_el_n = F @ (s_iso + s_vol)
            U.append(u)
            V.append(v)
            SIG.append(self.cauchy(F, committed(s_iso, s_vol, h)))
        return np.asarray(U), np.asarray(V), np.asarray(SIG)

    @staticmethod
    def cauchy(F: np.ndarray, S: np.ndarray) -> np.ndarray:
        """σ = J⁻¹ F S Fᵀ [T, 3, 3] Pa."""
        return F @ S @ np.swapaxes(F, -1, -2) / np.linalg.det(F)[:, None, None]

    def rollout_states(self, z: np.ndarray, forces: np.ndarray, X: np.ndarray, layout, dt: float) -> np.ndarray:
        """The model's states [S, N, D] from the first of the data states z [S, N, D] under the
        stored nodal forces [S, N, 3] N, as ``CorotatedSolid.rollout_states``: q = X + u [m],
        v [m/s], σ node-averaged [Pa]; any other column held at z[0]."""
        z = np.asarray(z, dtype=float)
        S, N = z.shape[0], z.shape[1]
        if "v" not in layout.names:
            raise ValueError("hyperelastic FE: the state has no velocity (quasi-static data)")
        sv = layout.slice("v")
        U, V, SIG = self.rollout(free_rows(z[:1, :, 0:3] - X[None], self.free)[0],
                                 free_rows(z[:1, :, sv], self.free)[0], free_rows(forces, self.free), dt)
        out = np.repeat(z[:1], S, axis=0)                                 # [S, N, D]
        out[..., 0:3] = X[None] + self.nodal(U)
        out[..., sv] = self.nodal(V)
        if "sigma" in layout.names:
            out[..., layout.slice("sigma")] = node_average(SIG, self.tets, self.volume, N)
        return out


__all__ = ["HyperelasticSolid", "NeoHookean", "Ogden", "law_from_config"]
