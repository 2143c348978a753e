"""The linearised FE step as a prior for a learned model: the data's own Newmark step applied to
the solid linearised at rest (``/linear`` in the dataset, :class:`thermognn.core.linear.LinearSolid`),
with the nonlinear part of the solid left as two remainders a network can learn.

The FE solid (``thermognn/generate/solid.py``) steps, over its free DOFs::

    M a1 + αM M v1 + βK (f_int(u1) − f_int(u0)) / dt + f_int(u1) = f1          [N]
    u1 = u0 + dt v0 + dt² ((1/2 − β) a0 + β a1),   v1 = v0 + dt ((1 − γ) a0 + γ a1)

(stiffness damping written as βK times the internal force's change over the step). With the
internal force split as f_int(u) = K u − G(u), K the stiffness at rest, this is exactly::

    M a1 + αM M v1 + c K (u1 − u0) + K u1 = f1 + (1 + c) G(u1) − c G(u0),      c = βK / dt

and the nodal Cauchy stress [Pa] is σ = Σ u + H. G [N] (the internal force's nonlinear
remainder) and H [Pa] (the stress's) vanish for small displacements: with G = H = 0 the step is
the linearised FE model ``evaluate`` reports, and with the exact remainders of a trajectory
(:meth:`NewmarkPrior.remainders`) it reproduces that trajectory to round-off. A hybrid model
learns G and H; the linear solve spreads G over the body, so a local correction suffices.

A viscous solid's ``/linear`` also holds its Prony relaxation (``LinearSolid.prony``), which the
linearised baseline steps. By default this prior takes the unrelaxed K and Σ and leaves the
relaxation to the remainders (of first order in the load). With ``relax`` it relaxes as the
baseline does (``thermognn.core.linear``): per Prony term i (weight ḡ_i, time τ_i) it carries
internal variables h_i = [h_i^f (n, N); h_i^σ (6N, Pa)], the isochoric force and stress
J u = [K_iso u; Σ_iso u] seen through exp(−t/τ_i), updated over a step as the FE updates its own::

    h_i ← d_i h_i + w_i J (u1 − u0),   d_i = exp(−Δt/τ_i),   w_i = τ_i/Δt (1 − d_i)
    f_int,lin = K_Δt u1 + Σ ḡ_i (d_i h_i^f − w_i K_iso u0),   K_Δt = K − Σ ḡ_i (1 − w_i) K_iso
    σ_lin = Σ u + Σ ḡ_i (h_i^σ − Σ_iso u)

(h_i = J u at a start, as if its displacement were applied at once). The step then reads
M a1 + αM M v1 + c K (u1 − u0) + f_int,lin = f1 + (1 + c) G1 − c G0, and σ = σ_lin + H: the
remainders are again what the linearised solid misses, now of second order in the load.

torch only (dense operators, for meshes of a few thousand free DOFs).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import Tensor, nn

from thermognn.core.linear import LinearSolid


def _dense(A) -> Tensor:
    return torch.as_tensor(A.toarray() if hasattr(A, "toarray") else np.asarray(A), dtype=torch.float64)


class NewmarkPrior(nn.Module):
    """The Newmark step above over the n free DOFs of an N-node mesh, as dense matrices.

    Displacements u, velocities v [m/s], accelerations a [m/s²], forces and remainders G [N] are
    [B, n] rows over the free DOFs (node-blocked, as ``LinearSolid``); stresses [B, N, 6] Pa.
    The operators are buffers left out of the state dict (they are rebuilt from the dataset's
    ``/linear``; a TorchScript file keeps them)."""

    def __init__(self, linear: LinearSolid, n_nodes: int, dt: float, dtype: torch.dtype = torch.float64,
                 relax: bool = False) -> None:
        super().__init__()
        if linear.integrator != "newmark":
            raise ValueError(f"linear prior: integrator {linear.integrator!r}, only newmark is reproduced")
        if linear.stress is None:
            raise ValueError("linear prior: the dataset's /linear has no stress operator (P1 meshes only)")
        terms = linear.relaxation(dt) if relax else []                 # [(ḡ_i, d_i, w_i)]
        if relax and (not terms or linear.stress_iso is None):
            raise ValueError("linear prior: relax needs a viscous solid (Prony terms and the isochoric K and Σ "
                             "in the dataset's /linear); this one is elastic")
        K, M = _dense(linear.stiffness), _dense(linear.mass)                      # [n, n]
        self.alpha_m, beta_k = (float(r) for r in linear.rayleigh)
        self.beta, self.gamma, self.dt = float(linear.beta), float(linear.gamma), float(dt)
        self.c = beta_k / self.dt                                                  # stiffness damping / dt
        self.c0 = 1.0 / (self.beta * self.dt**2)                                   # a1 = c0 u1 − predictor
        self.c1 = 1.0 / (2.0 * self.beta) - 1.0
        mass_factor = 1.0 + self.alpha_m * self.gamma * self.dt
        n = K.shape[0]
        if terms:                          # the isochoric operator J = [K_iso; Σ_iso] [n + 6N, n]
            iso = torch.cat([_dense(linear.stiffness_iso), _dense(linear.stress_iso)], 0)
            step_stiffness = _dense(linear.step_stiffness(dt))                         # K_Δt
        else:
            iso, step_stiffness = torch.zeros(0, n, dtype=torch.float64), K
        S_inv = torch.linalg.inv(self.c0 * mass_factor * M + self.c * K + step_stiffness)   # effective stiffness⁻¹
        # u1 = S⁻¹ (mass_factor M p + c K u0 − αM M v0 − αM dt (1 − γ) M a0 + f1 + (1 + c) G1 − c G0 − history)
        free = torch.as_tensor(np.asarray(linear.free, dtype=bool))                 # [3N]
        stress_operator = torch.zeros(6 * n_nodes, 3 * n_nodes, dtype=torch.float64)  # [6N, 3N]
        stress_operator[:, free] = _dense(linear.stress)
        operators = {
            "from_predictor": S_inv @ (mass_factor * M), "from_u": self.c * S_inv @ K,
            "from_v": -self.alpha_m * S_inv @ M, "from_a": -self.alpha_m * self.dt * (1.0 - self.gamma) * S_inv @ M,
            "from_force": S_inv, "stiffness": K, "mass": M, "mass_inv": torch.linalg.inv(M),
            "body_force": (torch.zeros(n, dtype=torch.float64) if linear.body_force is None
                           else torch.as_tensor(np.asarray(linear.body_force), dtype=torch.float64)),
            "stress_operator": stress_operator, "iso_operator": iso,
            # per Prony term [T]: its weight ḡ_i, the decay d_i and the increment's weight w_i over a step
            "prony_weight": torch.tensor([t[0] for t in terms], dtype=torch.float64),
            "prony_decay": torch.tensor([t[1] for t in terms], dtype=torch.float64),
            "prony_increment": torch.tensor([t[2] for t in terms], dtype=torch.float64)}
        for name, value in operators.items():
            self.register_buffer(name, value.to(dtype), persistent=False)
        self.register_buffer("free", free, persistent=False)
        self.register_buffer("free_index", torch.nonzero(free).flatten(), persistent=False)  # [n]
        self.n_nodes = int(n_nodes)
        self.n_free = int(n)
        self.n_terms = len(terms)          # 0: the unrelaxed prior (internal variables [B, 0, 0])

    # --- free DOFs <-> nodal fields ---------------------------------------------------------
    def free_nodes(self) -> Tensor:
        """[N] bool: the nodes none of whose DOFs is clamped."""
        return self.free.reshape(self.n_nodes, 3).all(1)

    def gather(self, nodal: Tensor) -> Tensor:
        """[B, N, 3] nodal vectors -> [B, n] over the free DOFs."""
        return nodal.reshape(nodal.shape[0], -1).index_select(1, self.free_index)

    def scatter(self, rows: Tensor) -> Tensor:
        """[B, n] free-DOF rows -> [B, N, 3] nodal vectors (zero at clamped DOFs)."""
        B = rows.shape[0]
        full = rows.new_zeros(B, 3 * self.n_nodes).index_copy(1, self.free_index, rows)  # [B, 3N]
        return full.reshape(B, self.n_nodes, 3)

    # --- the step ---------------------------------------------------------------------------
    def initial_acceleration(self, u0: Tensor, v0: Tensor, f0: Tensor, G0: Tensor) -> Tensor:
        """a0 [B, n] from the equation of motion at the start, M a0 = f0 − K u0 + G0 − αM M v0
        (the FE starts from its own balance too)."""
        rhs = f0 + self.body_force - u0 @ self.stiffness.T + G0 - self.alpha_m * v0 @ self.mass.T
        return rhs @ self.mass_inv.T

    def step(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor,
             G1: Tensor, h0: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(u1, v1, a1, h1) [B, n] (h1 [B, T, n + 6N]) from (u0, v0, a0), the Prony internal
        variables h0 at the step's start ([B, 0, 0] for the unrelaxed prior), the external force f1 at
        the step's end and the internal-force remainders G0, G1 at its start and end (all [B, n])."""
        predictor = self.c0 * (u0 + self.dt * v0) + self.c1 * a0
        u1 = (predictor @ self.from_predictor.T + u0 @ self.from_u.T + v0 @ self.from_v.T + a0 @ self.from_a.T
              + (f1 + self.body_force + (1.0 + self.c) * G1 - self.c * G0 - self.history_force(u0, h0))
              @ self.from_force.T)
        a1 = self.c0 * u1 - predictor
        v1 = v0 + self.dt * ((1.0 - self.gamma) * a0 + self.gamma * a1)
        return u1, v1, a1, self.relax(u0, u1, h0)

    # --- the Prony internal variables of the relaxing prior (module docstring) ---------------
    def internal_variables(self, u: Tensor) -> Tensor:
        """h [B, T, n + 6N] at displacements u [B, n] applied at once (h_i = J u; a start)."""
        if self.n_terms == 0:
            return u.new_zeros(u.shape[0], 0, 0)
        return (u @ self.iso_operator.T).unsqueeze(1).expand(-1, self.n_terms, -1).contiguous()

    def relax(self, u0: Tensor, u1: Tensor, h0: Tensor) -> Tensor:
        """h1 [B, T, n + 6N] after a step from u0 to u1 [B, n]: h_i ← d_i h_i + w_i J (u1 − u0)."""
        if self.n_terms == 0:
            return h0
        return (self.prony_decay.view(1, -1, 1) * h0
                + self.prony_increment.view(1, -1, 1) * ((u1 - u0) @ self.iso_operator.T).unsqueeze(1))

    def history_force(self, u0: Tensor, h0: Tensor) -> Tensor:
        """f_int,lin − K_Δt u1 [B, n] N: what the internal variables h0 and u0 [B, n] add at a
        step's end (zero for the unrelaxed prior)."""
        if self.n_terms == 0:
            return torch.zeros_like(u0)
        n = self.n_free
        iso = (u0 @ self.iso_operator[:n].T).unsqueeze(1)                          # K_iso u0 [B, 1, n]
        return (self.prony_weight.view(1, -1, 1) * (self.prony_decay.view(1, -1, 1) * h0[:, :, :n]
                                                     - self.prony_increment.view(1, -1, 1) * iso)).sum(1)

    def _relaxation(self, u: Tensor, h: Tensor, start: int, end: int) -> Tensor:
        """Σ ḡ_i (h_i − J u) over the rows start:end of J = [K_iso; Σ_iso] [B, end − start]: what
        relaxation takes off the linearised force (rows :n) or stress (rows n:) at displacements
        u [B, n] with internal variables h [B, T, n + 6N]."""
        iso = (u @ self.iso_operator[start:end].T).unsqueeze(1)                    # [B, 1, end − start]
        return (self.prony_weight.view(1, -1, 1) * (h[:, :, start:end] - iso)).sum(1)

    def stress_relaxation(self, u: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (h_i^σ − Σ_iso u) [B, N, 6] Pa: what relaxation takes off the linearised stress
        at displacements u [B, n] with internal variables h (zero for the unrelaxed prior)."""
        B = u.shape[0]
        if self.n_terms == 0:
            return u.new_zeros(B, self.n_nodes, 6)
        return self._relaxation(u, h, self.n_free, self.iso_operator.shape[0]).reshape(B, self.n_nodes, 6)

    def internal_history(self, u: Tensor) -> Tensor:
        """The internal variables h [S, T, n + 6N] along one trajectory of displacements u [S, n],
        from h = J u[0] at its start (an unloaded start, as generate's)."""
        h = [self.internal_variables(u[:1])]
        for s in range(u.shape[0] - 1):
            h.append(self.relax(u[s:s + 1], u[s + 1:s + 2], h[-1]))
        return torch.cat(h)

    def stress(self, u: Tensor, H: Optional[Tensor] = None) -> Tensor:
        """Nodal Cauchy stress σ = Σ u + H [B, N, 6] Pa (Voigt 11 22 33 12 13 23) of the nodal
        displacements u [B, N, 3] m (H = 0: the linearised stress; unrelaxed, see
        ``stress_relaxation``)."""
        B = u.shape[0]
        linear = (u.reshape(B, -1) @ self.stress_operator.T).reshape(B, self.n_nodes, 6)
        return linear if H is None else linear + H

    def accelerations(self, u: Tensor, v: Tensor, f: Tensor) -> Tensor:
        """Newmark's accelerations a [S, n] m/s² along one trajectory of free-DOF displacements u,
        velocities v and forces f [S, n]: a0 from the balance at the start (G0 = 0: an unloaded
        start at rest, as generate's), then v1 = v0 + dt ((1 − γ) a0 + γ a1) solved for a1."""
        dt, g = self.dt, self.gamma
        a = torch.zeros_like(u)
        a[0] = self.initial_acceleration(u[:1], v[:1], f[:1], torch.zeros_like(u[:1]))[0]
        for s in range(u.shape[0] - 1):
            a[s + 1] = (v[s + 1] - v[s] - dt * (1.0 - g) * a[s]) / (g * dt)
        return a

    # --- what a learned model must supply ---------------------------------------------------
    def remainders(self, u: Tensor, v: Tensor, sigma: Tensor, f: Tensor) -> tuple[Tensor, Tensor]:
        """The exact remainders along one FE trajectory: G [S, n] N and H [S, N, 6] Pa, from its
        displacements u [S, N, 3], velocities v [S, N, 3], stresses [S, N, 6] and nodal forces
        f [S, N, 3]. Assumes G = 0 at the first state (an unloaded start at rest, as generate's);
        the relaxing prior's internal variables follow the trajectory's own displacements."""
        uf, vf, ff = self.gather(u), self.gather(v), self.gather(f)
        S = uf.shape[0]
        K, M, c = self.stiffness, self.mass, self.c
        a = self.accelerations(uf, vf, ff)
        h = self.internal_history(uf)                                              # [S, T, n + 6N]
        # f_int,lin at every step's end: K u1 (the unrelaxed prior), or K u1 + Σ ḡ_i (h_i^f − K_iso u1)
        # (= K_Δt u1 + history_force, with the step's own update of h)
        f_lin = uf[1:] @ K.T
        if self.n_terms:
            f_lin = f_lin + self._relaxation(uf[1:], h[1:], 0, self.n_free)
        # (1 + c) G1 − c G0 = M a1 + αM M v1 + c K (u1 − u0) + f_int,lin − f1 at every step's end
        lumped = (a[1:] @ M.T + self.alpha_m * vf[1:] @ M.T + c * (uf[1:] - uf[:-1]) @ K.T + f_lin
                  - ff[1:] - self.body_force)                                      # [S - 1, n]
        G = torch.zeros_like(uf)
        for s in range(S - 1):
            G[s + 1] = (lumped[s] + c * G[s]) / (1.0 + c)
        return G, sigma - self.stress(u) - self.stress_relaxation(uf, h)
