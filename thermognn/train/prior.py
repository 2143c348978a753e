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

torch only: the FE operators (K, M, Σ and their isochoric parts) are sparse
(:class:`SparseMatrix`); the linear step's effective stiffness has a dense inverse [n, n] (meshes
of a few thousand free DOFs), so its step is one dense product. M is solved by conjugate gradients
(:meth:`NewmarkPrior.mass_solve`), where a dense M⁻¹ cost the bunny's law prior 7 s and 226 MB.
"""

from __future__ import annotations

from typing import List, Optional, Tuple

import numpy as np
import torch
from scipy import sparse
from torch import Tensor, nn

from thermognn.core.linear import LinearSolid


#: ``NewmarkPrior.mass_solve``: the residual it stops at, relative to the right-hand side's (float64;
#: float32), and the most iterations it takes (a P1 mass matrix needs about 40 for 1e-14)
MASS_RTOL, MASS_RTOL_SINGLE = 1e-14, 1e-6
MASS_MAX_ITERATIONS = 200


def _dense(A) -> Tensor:
    return torch.as_tensor(A.toarray() if hasattr(A, "toarray") else np.asarray(A), dtype=torch.float64)


class SparseMatrix(nn.Module):
    """A fixed sparse matrix A [m, k] applied to rows: x [B, k] -> x Aᵀ [B, m], as a gather, a
    product and a scatter over its nonzeros (as message passing is), so that autograd of any
    order, TorchScript and any device take it. Its triplets are buffers left out of the state
    dict, as NewmarkPrior's operators are.

    ``A``: a scipy.sparse matrix or a dense array [m, k]; ``columns`` [k'] (optional) renumbers its
    columns (column j of A acts on column columns[j] of x, which may have more columns than A)."""

    def __init__(self, A, dtype: torch.dtype = torch.float64, columns: Optional[np.ndarray] = None) -> None:
        super().__init__()
        coo = sparse.coo_matrix(A)
        cols = coo.col if columns is None else np.asarray(columns, dtype=np.int64)[coo.col]
        self.register_buffer("rows", torch.as_tensor(coo.row, dtype=torch.long), persistent=False)    # [nnz]
        self.register_buffer("cols", torch.as_tensor(cols, dtype=torch.long), persistent=False)       # [nnz]
        self.register_buffer("values", torch.as_tensor(coo.data, dtype=torch.float64).to(dtype),
                             persistent=False)                                                      # [nnz]
        self.out_features = int(coo.shape[0])

    def forward(self, x: Tensor) -> Tensor:
        """x Aᵀ [B, m] of rows x [B, k]."""
        products = x.index_select(1, self.cols) * self.values                     # [B, nnz]
        return x.new_zeros([x.shape[0], self.out_features]).index_add(1, self.rows, products)


class NewmarkPrior(nn.Module):
    """The Newmark step above over the n free DOFs of an N-node mesh.

    Displacements u, velocities v [m/s], accelerations a [m/s²], forces and remainders G [N] are
    [B, n] rows over the free DOFs (node-blocked, as ``LinearSolid``); stresses [B, N, 6] Pa.
    The operators are buffers left out of the state dict (they are rebuilt from the dataset's
    ``/linear``; a TorchScript file keeps them): the sparse ``stiffness`` K, ``mass`` M,
    ``stress_operator`` Σ (from all 3N nodal DOFs) and, relaxing, ``stiffness_iso`` and
    ``stress_iso``; the dense ``step_inverse`` (the effective stiffness's inverse; empty with
    ``step_matrix`` False, for a subclass that steps otherwise), and M's diagonal ``mass_diagonal``
    [n] kg, which preconditions ``mass_solve``."""

    def __init__(self, linear: LinearSolid, n_nodes: int, dt: float, dtype: torch.dtype = torch.float64,
                 relax: bool = False, step_matrix: bool = True) -> None:
        super().__init__()
        if linear.integrator != "newmark":
            raise ValueError(f"linear prior: integrator {linear.integrator!r}, only newmark is reproduced")
        if linear.stress is None:
            raise ValueError("linear prior: the dataset's /linear has no stress operator (P1 meshes only)")
        terms = linear.relaxation(dt) if relax else []                 # [(ḡ_i, d_i, w_i)]
        if relax and (not terms or linear.stress_iso is None):
            raise ValueError("linear prior: relax needs a viscous solid (Prony terms and the isochoric K and Σ "
                             "in the dataset's /linear); this one is elastic")
        self.alpha_m, beta_k = (float(r) for r in linear.rayleigh)
        self.beta, self.gamma, self.dt = float(linear.beta), float(linear.gamma), float(dt)
        self.c = beta_k / self.dt                                                  # stiffness damping / dt
        self.c0 = 1.0 / (self.beta * self.dt**2)                                   # a1 = c0 u1 − predictor
        self.c1 = 1.0 / (2.0 * self.beta) - 1.0
        self.mass_factor = 1.0 + self.alpha_m * self.gamma * self.dt
        n = int(linear.mass.shape[0])
        # u1 = S⁻¹ (M (mass_factor p − αM v0 − αM dt (1 − γ) a0) + c K u0 + f1 + (1 + c) G1 − c G0 − history)
        if step_matrix:
            K, M = _dense(linear.stiffness), _dense(linear.mass)                  # [n, n]
            step_stiffness = _dense(linear.step_stiffness(dt)) if terms else K   # K_Δt
            step_inverse = torch.linalg.inv(self.c0 * self.mass_factor * M + self.c * K + step_stiffness)
            del step_stiffness, K, M
        else:
            step_inverse = torch.zeros(0, 0, dtype=torch.float64)                     # (a subclass's own step)
        mass_diagonal = torch.as_tensor(sparse.csr_matrix(linear.mass).diagonal(), dtype=torch.float64)   # [n] kg
        if not bool((mass_diagonal > 0).all()):
            raise ValueError("linear prior: /linear's mass matrix has a diagonal entry <= 0 (expected a mass "
                             "matrix, symmetric positive definite)")
        free = np.asarray(linear.free, dtype=bool)                                   # [3N]
        free_index = np.flatnonzero(free)                                            # [n]
        empty = np.zeros((0, n))
        self.stiffness = SparseMatrix(linear.stiffness, dtype)                      # K [n, n] N/m
        self.mass = SparseMatrix(linear.mass, dtype)                                # M [n, n] kg
        self.stress_operator = SparseMatrix(linear.stress, dtype, free_index)      # Σ [6N, 3N] Pa/m
        # the isochoric operator J = [K_iso; Σ_iso] [n + 6N, n] (none for the unrelaxed prior)
        self.stiffness_iso = SparseMatrix(linear.stiffness_iso if terms else empty, dtype)
        self.stress_iso = SparseMatrix(linear.stress_iso if terms else empty, dtype)
        operators = {
            "step_inverse": step_inverse, "mass_diagonal": mass_diagonal,
            "body_force": (torch.zeros(n, dtype=torch.float64) if linear.body_force is None
                           else torch.as_tensor(np.asarray(linear.body_force), dtype=torch.float64)),
            # per Prony term [T]: its weight ḡ_i, the decay d_i and the increment's weight w_i over a step
            "prony_weight": torch.tensor([t[0] for t in terms], dtype=torch.float64),
            "prony_decay": torch.tensor([t[1] for t in terms], dtype=torch.float64),
            "prony_increment": torch.tensor([t[2] for t in terms], dtype=torch.float64)}
        for name, value in operators.items():
            self.register_buffer(name, value.to(dtype), persistent=False)
        self.register_buffer("free", torch.as_tensor(free), persistent=False)
        self.register_buffer("free_index", torch.as_tensor(free_index, dtype=torch.long), persistent=False)
        self.n_nodes = int(n_nodes)
        self.n_free = int(n)
        # ``mass_solve``'s tolerances (float64, float32) and its most iterations (TorchScript reads
        # attributes, not globals)
        self.mass_rtol: List[float] = [MASS_RTOL, MASS_RTOL_SINGLE]
        self.mass_max_iterations = MASS_MAX_ITERATIONS
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

    def body_energy(self, u: Tensor, v: Tensor) -> Tensor:
        """The linearised solid's elastic and kinetic energy u K u / 2 + v M v / 2 [B] J at free-DOF
        displacements u [B, n] m and velocities v [B, n] m/s (a law prior: its law's,
        ``HyperelasticNewmarkPrior.energy``)."""
        return 0.5 * (self.stiffness(u) * u).sum(-1) + self.kinetic_energy(v)

    def kinetic_energy(self, v: Tensor) -> Tensor:
        """½ vᵀ M v [B] J of free-DOF velocities v [B, n] m/s."""
        return 0.5 * (self.mass(v) * v).sum(-1)

    # --- the step ---------------------------------------------------------------------------
    def elastic_force(self, u: Tensor) -> Tensor:
        """The prior's elastic internal force [B, n] N at free-DOF displacements u [B, n]: K u
        (unrelaxed; :class:`CorotatedNewmarkPrior`: corotated per cell)."""
        return self.stiffness(u)

    def newmark_predictor(self, u0: Tensor, v0: Tensor, a0: Tensor) -> Tensor:
        """c0 (u0 + Δt v0) + c1 a0 [B, n] m/s² from a step's start (u0 [m], v0 [m/s], a0 [m/s²]
        [B, n]): what Newmark's a1 = (u1 − u0 − Δt v0)/(β Δt²) − (1/(2β) − 1) a0 takes from the
        start, so that a1 = c0 u1 − predictor (``newmark_rates``)."""
        return self.c0 * (u0 + self.dt * v0) + self.c1 * a0

    def newmark_rates(self, u1: Tensor, v0: Tensor, a0: Tensor, predictor: Tensor) -> Tuple[Tensor, Tensor]:
        """(a1 [m/s²], v1 [m/s]) [B, n] of a step ending at u1 [B, n] m from v0, a0 with
        ``newmark_predictor``'s predictor: a1 = c0 u1 − predictor, v1 = v0 + Δt ((1 − γ) a0 + γ a1)."""
        a1 = self.c0 * u1 - predictor
        return a1, v0 + self.dt * ((1.0 - self.gamma) * a0 + self.gamma * a1)

    def initial_acceleration(self, u0: Tensor, v0: Tensor, f0: Tensor, G0: Tensor) -> Tensor:
        """a0 [B, n] from the equation of motion at the start, M a0 = f0 − K u0 + G0 − αM M v0
        (the FE starts from its own balance too)."""
        rhs = f0 + self.body_force - self.elastic_force(u0) + G0 - self.alpha_m * self.mass(v0)
        return self.mass_solve(rhs)

    @torch.jit.export
    def mass_solve(self, b: Tensor) -> Tensor:
        """M⁻¹ b [B, n] m/s² of forces b [B, n] N (``mass_cg``), with the gradient M⁻¹ ∂L/∂x of
        the exact inverse where b takes one (eager: :class:`MassSolve`), as a dense M⁻¹ gave."""
        if not torch.jit.is_scripting():
            if b.requires_grad:
                return self._mass_solve_autograd(b)
        return self.mass_cg(b)

    @torch.jit.unused
    def _mass_solve_autograd(self, b: Tensor) -> Tensor:
        return MassSolve.apply(b, self)

    def mass_cg(self, b: Tensor) -> Tensor:
        """M⁻¹ b [B, n] m/s² of forces b [B, n] N, by conjugate gradients preconditioned with M's
        diagonal D. A P1 mass matrix is as well conditioned as that on any mesh: D_e⁻¹ M_e of a
        tetrahedron has the eigenvalues 1/2 and 5/2, so D⁻¹ M's lie between them (Wathen 1987;
        the shell's, liver's and bunny's: 0.50–2.50) and each iteration takes at least
        (√5 − 1)/(√5 + 1) ≈ 0.38 off the error: about 40 iterations to round-off, whatever the
        mesh. Iterates until each sample's residual is below ``MASS_RTOL`` of its b
        (``MASS_RTOL_SINGLE`` in float32; a zero b gives 0) and raises if
        ``MASS_MAX_ITERATIONS`` do not get there (not a mass matrix)."""
        x = torch.zeros_like(b)
        r = b
        rtol = self.mass_rtol[0] if b.dtype == torch.float64 else self.mass_rtol[1]
        bound = rtol * torch.linalg.vector_norm(b, dim=1, keepdim=True)                    # [B, 1] N
        z = r / self.mass_diagonal
        p = z
        rz = (r * z).sum(1, keepdim=True)                                                   # [B, 1]
        for it in range(self.mass_max_iterations + 1):
            if bool((torch.linalg.vector_norm(r, dim=1, keepdim=True) <= bound).all()):
                return x
            if it == self.mass_max_iterations:
                break
            Mp = self.mass(p)
            pMp = (p * Mp).sum(1, keepdim=True)
            step = torch.where(pMp > 0, rz / torch.where(pMp > 0, pMp, torch.ones_like(pMp)), torch.zeros_like(pMp))
            x = x + step * p
            r = r - step * Mp
            z = r / self.mass_diagonal
            rz_next = (r * z).sum(1, keepdim=True)
            p = z + torch.where(rz > 0, rz_next / torch.where(rz > 0, rz, torch.ones_like(rz)),
                                torch.zeros_like(rz)) * p
            rz = rz_next
        raise RuntimeError("prior: the mass solve did not converge (is /linear's mass matrix a P1 mass matrix?)")

    def step(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor,
             G1: Tensor, h0: Tensor, f0: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(u1, v1, a1, h1) [B, n] (h1 [B, T, n + 6N]) from (u0, v0, a0), the Prony internal
        variables h0 at the step's start ([B, 0, 0] for the unrelaxed prior), the external force f1 at
        the step's end and the internal-force remainders G0, G1 at its start and end (all [B, n]);
        f0, the force at the step's start, is for the law prior's cut steps (unused here)."""
        predictor = self.newmark_predictor(u0, v0, a0)
        inertia = self.mass(self.mass_factor * predictor - self.alpha_m * v0
                            - self.alpha_m * self.dt * (1.0 - self.gamma) * a0)
        rhs = (inertia + self.c * self.stiffness(u0) + f1 + self.body_force + (1.0 + self.c) * G1
               - self.c * G0 - self.history_force(u0, h0))                                 # [B, n] N
        u1 = rhs @ self.step_inverse.T
        a1, v1 = self.newmark_rates(u1, v0, a0, predictor)
        return u1, v1, a1, self.relax(u0, u1, h0)

    @torch.jit.export
    def forget(self) -> None:
        """Drop what the prior keeps between steps (nothing here; the law prior keeps its last
        step start, its law's stresses and a kept tangent): a rollout starts without it."""
        pass

    def inverted(self, x: Tensor) -> Tensor:
        """Whether positions x [B, N, 3] m turn a cell inside out [B] (bool): never for the
        linearised prior, which has no cells (``CorotatedNewmarkPrior`` checks det F)."""
        return torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)

    # --- the Prony internal variables of the relaxing prior (module docstring) ---------------
    def isochoric(self, u: Tensor) -> Tensor:
        """J u = [K_iso u; Σ_iso u] [B, n + 6N] of displacements u [B, n]."""
        return torch.cat([self.stiffness_iso(u), self.stress_iso(u)], 1)

    def internal_variables(self, u: Tensor) -> Tensor:
        """h [B, T, n + 6N] at displacements u [B, n] applied at once (h_i = J u; a start)."""
        if self.n_terms == 0:
            return u.new_zeros(u.shape[0], 0, 0)
        return self.isochoric(u).unsqueeze(1).expand(-1, self.n_terms, -1).contiguous()

    def relax(self, u0: Tensor, u1: Tensor, h0: Tensor) -> Tensor:
        """h1 [B, T, n + 6N] after a step from u0 to u1 [B, n]: h_i ← d_i h_i + w_i J (u1 − u0)."""
        if self.n_terms == 0:
            return h0
        return (self.prony_decay.view(1, -1, 1) * h0
                + self.prony_increment.view(1, -1, 1) * self.isochoric(u1 - u0).unsqueeze(1))

    def history_force(self, u0: Tensor, h0: Tensor) -> Tensor:
        """f_int,lin − K_Δt u1 [B, n] N: what the internal variables h0 and u0 [B, n] add at a
        step's end (zero for the unrelaxed prior)."""
        if self.n_terms == 0:
            return torch.zeros_like(u0)
        n = self.n_free
        iso = self.stiffness_iso(u0).unsqueeze(1)                                  # K_iso u0 [B, 1, n]
        return (self.prony_weight.view(1, -1, 1) * (self.prony_decay.view(1, -1, 1) * h0[:, :, :n]
                                                     - self.prony_increment.view(1, -1, 1) * iso)).sum(1)

    def relaxation_force(self, u: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (h_i^f − K_iso u) [B, n] N: what relaxation takes off the linearised internal force
        at displacements u [B, n] with internal variables h (those of a step's end: f_int,lin =
        K u + this)."""
        return self._relaxation(self.stiffness_iso(u), h[:, :, :self.n_free])

    def internal_columns(self) -> List[Tuple[str, int]]:
        """The nodal columns ``pack_internal`` gives the internal variables, as (name, width) per
        group: per Prony term its force variable as a nodal vector (3) and its stress variable (6)."""
        return [(f"prony_{kind}_{i + 1}", width) for i in range(self.n_terms)
                for kind, width in (("force", 3), ("stress", 6))]

    def pack_internal(self, h: Tensor) -> Tensor:
        """Internal variables h [B, T, n + 6N] -> nodal columns [B, N, 9 T] (``internal_columns``)."""
        n, B = self.n_free, h.shape[0]
        cols: List[Tensor] = []
        for i in range(self.n_terms):
            cols.append(self.scatter(h[:, i, :n]))
            cols.append(h[:, i, n:].reshape(B, -1, 6))
        if len(cols) == 0:
            return h.new_zeros(B, self.n_nodes, 0)
        return torch.cat(cols, -1)

    def unpack_internal(self, x: Tensor) -> Tensor:
        """Nodal columns [B, N, 9 T] -> internal variables h [B, T, n + 6N]: the inverse of ``pack_internal``."""
        B = x.shape[0]
        terms: List[Tensor] = []
        for i in range(self.n_terms):
            terms.append(torch.cat([self.gather(x[:, :, 9 * i:9 * i + 3]),
                                    x[:, :, 9 * i + 3:9 * i + 9].reshape(B, -1)], -1))
        if len(terms) == 0:
            return x.new_zeros(B, 0, 0)
        return torch.stack(terms, 1)

    def _relaxation(self, iso: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (h_i − iso) [B, m]: what relaxation takes off the linearised force (iso = K_iso u,
        h the rows :n of the internal variables) or stress (Σ_iso u, rows n:) at displacements u,
        from iso [B, m] and those rows h [B, T, m] of the internal variables."""
        return (self.prony_weight.view(1, -1, 1) * (h - iso.unsqueeze(1))).sum(1)

    def physical_state(self, X: Tensor, u: Tensor, v: Tensor, H: Optional[Tensor], h: Tensor) -> Tensor:
        """Physical states [B, N, 12] (q = X + u m, v m/s, σ = stress(u) + H + the relaxation's Pa)
        of the mesh's reference positions X [N, 3] m, free-DOF u, v [B, n], the stress remainder H
        [B, N, 6] Pa (None: none) and the Prony internal variables h."""
        U = self.scatter(u)                                                         # [B, N, 3]
        return torch.cat([X.unsqueeze(0) + U, self.scatter(v), self.stress(U, H) + self.stress_relaxation(u, h)], -1)

    def stress_relaxation(self, u: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (h_i^σ − Σ_iso u) [B, N, 6] Pa: what relaxation takes off the linearised stress
        at displacements u [B, n] with internal variables h (zero for the unrelaxed prior)."""
        B = u.shape[0]
        if self.n_terms == 0:
            return u.new_zeros(B, self.n_nodes, 6)
        return self._relaxation(self.stress_iso(u), h[:, :, self.n_free:]).reshape(B, self.n_nodes, 6)

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
        linear = self.stress_operator(u.reshape(B, -1)).reshape(B, self.n_nodes, 6)
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
        c = self.c
        a = self.accelerations(uf, vf, ff)
        h = self.internal_history(uf)                                              # [S, T, n + 6N]
        # f_int,lin at every step's end: K u1 (the unrelaxed prior), or K u1 + Σ ḡ_i (h_i^f − K_iso u1)
        # (= K_Δt u1 + history_force, with the step's own update of h)
        elastic = self.elastic_force(uf)                                            # [S, n]: K u, or corotated
        f_lin = elastic[1:]
        if self.n_terms:
            f_lin = f_lin + self.relaxation_force(uf[1:], h[1:])
        # (1 + c) G1 − c G0 = M a1 + αM M v1 + c K (u1 − u0) + f_int,lin − f1 at every step's end
        lumped = (self.mass(a[1:] + self.alpha_m * vf[1:]) + c * (elastic[1:] - elastic[:-1]) + f_lin
                  - ff[1:] - self.body_force)                                      # [S - 1, n]
        return self.carried_remainders(lumped), sigma - self.stress(u) - self.stress_relaxation(uf, h)

    def carried_remainders(self, lumped: Tensor) -> Tensor:
        """G [S, n] N along one trajectory from what each of its S − 1 steps adds to the load,
        lumped [S − 1, n] N, by the step's own rule (1 + c) G1 − c G0 = lumped, from G = 0 at its
        first state (an unloaded start at rest, as generate's)."""
        c = self.c
        G = lumped.new_zeros(lumped.shape[0] + 1, lumped.shape[1])
        for s in range(lumped.shape[0]):
            G[s + 1] = (lumped[s] + c * G[s]) / (1.0 + c)
        return G


#: what the RuntimeError of a cell-wise prior's step holds where its state stopped being finite
#: ("corotated prior: a non-finite state ...", "law prior: ..."; the steps raise it literally:
#: TorchScript compiles no f-string of a global); training and validation catch it by this
DIVERGED = "prior: a non-finite state"
#: what the RuntimeError of a rollout stopped past its bound holds (``stop_if_run_away``:
#: ``LinearPriorModel.roll``'s ``bound``, ``rollout.validation_error``)
RAN_AWAY = "rollout: ran away"


def state_reach(z: Tensor, ref_pos: Tensor) -> Tensor:
    """[D] each column's largest |z| over the states z [..., N, D] (positions first, 3 columns,
    as displacements from ref_pos [N, 3] m; a NaN anywhere in a column makes it NaN)."""
    z = z.detach()
    return torch.cat([(z[..., :3] - ref_pos.to(z.dtype)).abs().flatten(0, -2).amax(0),
                      z[..., 3:].abs().flatten(0, -2).amax(0)])


def stop_if_run_away(z: Tensor, ref_pos: Tensor, bound: Tensor, step: int) -> None:
    """Raise the RuntimeError ``RAN_AWAY`` ("... at step s: column c reached x past b") where the
    states z [..., N, D] of rollout step ``step`` pass ``bound`` [D] (``state_reach``'s largest
    allowed; a NaN runs away too)."""
    reach = state_reach(z, ref_pos)
    within = reach <= bound.to(reach.dtype)
    if not bool(within.all()):
        c = int(torch.nonzero(~within)[0])
        raise RuntimeError(f"{RAN_AWAY} at step {step}: column {c} reached {float(reach[c]):.3g} "
                           f"past {float(bound[c]):.3g}")


class SparsePattern:
    """A fixed sparsity pattern of [n, n] matrices in CSC order: row index ``indices`` [nnz] and
    column pointers ``indptr`` [n + 1] (scipy's), with each slot's row and column as tensors."""

    def __init__(self, indices: np.ndarray, indptr: np.ndarray, n: int) -> None:
        self.indices, self.indptr, self.n = np.asarray(indices, np.int32), np.asarray(indptr, np.int32), int(n)
        self.rows = torch.as_tensor(self.indices, dtype=torch.long)                          # [nnz]
        self.cols = torch.as_tensor(np.repeat(np.arange(n), np.diff(self.indptr)), dtype=torch.long)   # [nnz]

    def matrix(self, values: np.ndarray) -> sparse.csc_matrix:
        return sparse.csc_matrix((values, self.indices, self.indptr), shape=(self.n, self.n))


#: SuperLU's options for the priors' step matrices, which are symmetric (a hyperelastic or
#: rotated stiffness, the mass and stiffness damping): a minimum-degree ordering of A + Aᵀ and
#: diagonal pivots unless one is below 1 % of its column's largest entry. Against COLAMD with
#: partial pivoting (min–median of repeated factors, 2 threads) it factors the shell's 1032 DOFs
#: in 2.9–3.6 ms against 5.3–6.7, the liver's 1278 in 6.7–12.6 against 8.6–15.3 and the bunny's
#: 5319 in 148–177 against 205–221 (docs/accuracy.md, session 73), to the same solution within
#: 1e-13 relative
SUPERLU_OPTIONS = {"permc_spec": "MMD_AT_PLUS_A", "diag_pivot_thresh": 0.01, "options": {"SymmetricMode": True}}


def sparse_factors(values: Tensor, pattern: SparsePattern) -> list:
    """One sparse LU (scipy's SuperLU, ``SUPERLU_OPTIONS``) per sample of the matrices ``values``
    [B, nnz] (detached: their gradient is not taken) in ``pattern``, for :func:`lu_solves` to
    solve with as often as a step needs."""
    from scipy.sparse.linalg import splu

    V = values.detach().cpu().numpy()
    return [splu(pattern.matrix(V[i]), **SUPERLU_OPTIONS) for i in range(V.shape[0])]


def lu_solves(lus: list, b: Tensor, transposed: bool = False) -> Tensor:
    """x [B, n] with A_i x_i = b_i (or A_iᵀ x_i = b_i, ``transposed``) by the factors ``lus`` of
    :func:`sparse_factors`; b [B, n] detached."""
    rhs = b.detach().cpu().numpy()
    return torch.as_tensor(np.stack([lu.solve(np.ascontiguousarray(rhs[i]), trans="T" if transposed else "N")
                                     for i, lu in enumerate(lus)]), dtype=b.dtype)


class MassSolve(torch.autograd.Function):
    """x = M⁻¹ b [B, n] by a prior's ``mass_cg``, with the exact inverse's gradient: ∂L/∂b =
    M⁻¹ ∂L/∂x (M symmetric), solved the same way (so autograd of any order passes). The CG
    iterates' own derivative is not M⁻¹: their Krylov coefficients depend on b."""

    @staticmethod
    def forward(ctx, b: Tensor, prior: "NewmarkPrior") -> Tensor:
        ctx.prior = prior
        return prior.mass_cg(b)

    @staticmethod
    def backward(ctx, grad_x: Tensor):
        return MassSolve.apply(grad_x, ctx.prior), None


class SparseSolve(torch.autograd.Function):
    """x [B, n] with A_i x_i = b_i, A_i the matrices of ``values`` [B, nnz] in a ``SparsePattern``:
    one sparse LU (scipy's SuperLU) per sample, kept for the backward pass, which solves with
    Aᵀ: ∂L/∂b = A⁻ᵀ ∂L/∂x and ∂L/∂A_rc = −(∂L/∂b)_r x_c on the pattern's slots. CPU, float64."""

    @staticmethod
    def forward(ctx, values: Tensor, b: Tensor, pattern: SparsePattern) -> Tensor:
        lus = sparse_factors(values, pattern)
        x = lu_solves(lus, b)
        ctx.lus, ctx.pattern = lus, pattern
        ctx.save_for_backward(x)
        return x

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_x: Tensor):
        (x,) = ctx.saved_tensors
        grad_b = lu_solves(ctx.lus, grad_x, transposed=True)
        grad_values = None
        if ctx.needs_input_grad[0]:
            grad_values = -grad_b[:, ctx.pattern.rows] * x[:, ctx.pattern.cols]        # [B, nnz]
        return grad_values, grad_b, None


class FactoredSolve(torch.autograd.Function):
    """x [B, n] with A_i x_i = b_i by the factors of :func:`sparse_factors` (A fixed: the gradient
    reaches b only, ∂L/∂b = A⁻ᵀ ∂L/∂x). CPU, float64."""

    @staticmethod
    def forward(ctx, b: Tensor, lus: list) -> Tensor:
        ctx.lus = lus
        return lu_solves(lus, b)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_x: Tensor):
        return lu_solves(ctx.lus, grad_x, transposed=True), None


def solve_each(A: Tensor, b: Tensor) -> Tensor:
    """x [B, n] with A[i] x[i] = b[i] (A [B, n, n], b [B, n]), one LU per sample: torch 2.13's
    CPU build fails batched LU factorisations with more than one thread (MKL's DLASWP rejects the
    pivots: "Pivots given to lu_solve must all be greater or equal to 1"), single ones do not. A
    GPU (``train.device=cuda``) solves them batched."""
    if A.device.type != "cpu":
        return torch.linalg.solve(A, b.unsqueeze(-1)).squeeze(-1)
    xs: List[Tensor] = []
    for i in range(A.shape[0]):
        xs.append(torch.linalg.solve(A[i], b[i]))
    return torch.stack(xs)


#: ``band_layout``: the block-tridiagonal factor is used where it takes at most this share of a
#: dense LU's flops (the liver, 1278 DOFs, keeps bandwidth 392 after reordering: no gain)
BAND_MAX_SHARE = 0.5


def band_layout(pattern: "SparsePattern", max_share: float = BAND_MAX_SHARE
                ) -> Optional[Tuple[np.ndarray, int, int, np.ndarray, np.ndarray]]:
    """A block-tridiagonal layout of the n × n matrices of a symmetric sparsity ``pattern``:
    its DOFs reordered by reverse Cuthill–McKee, so that every nonzero lies within the bandwidth w,
    and cut into blocks of w, so that every nonzero lies in a diagonal block or next to one.
    Returns (order [n]: the DOF at each reordered place, w, the number of blocks nb, each slot's
    place [nnz] in a [3, nb, w, w] storage of diagonal, lower and upper blocks (lower k: block
    row k + 1, column k; upper k: row k, column k + 1), the storage places of the padding's
    diagonal [nb w − n]); None where its factor (about 3 nb w³ flops, :func:`band_factor`) is
    not below ``max_share`` of a dense LU's (n³/3) or there is one block."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n = pattern.n
    A = pattern.matrix(np.ones(len(pattern.indices))).tocsr()
    order = np.asarray(reverse_cuthill_mckee(A, symmetric_mode=True), dtype=np.int64)
    place = np.empty(n, dtype=np.int64)
    place[order] = np.arange(n)
    i, j = place[pattern.rows.numpy()], place[pattern.cols.numpy()]                # [nnz] reordered
    w = max(int(np.abs(i - j).max()), 1)
    nb = -(-n // w)
    if nb < 2 or 3.0 * nb * w**3 > max_share * n**3 / 3.0:
        return None
    bi, bj, ri, rj = i // w, j // w, i % w, j % w
    part = np.where(bi == bj, 0, np.where(bi == bj + 1, 1, 2))                     # diagonal, lower, upper
    block = np.minimum(bi, bj)
    slot = ((part * nb + block) * w + ri) * w + rj
    pad = np.arange(n, nb * w)
    pad_slot = ((pad // w) * w + pad % w) * w + pad % w                          # diagonal blocks
    return order, w, nb, slot, pad_slot


#: ``dissection_layout``: one level of nested dissection is used where it takes at most this share
#: of a dense LU's flops (the liver, 1278 DOFs: two halves of 639 and 549 and a separator of 90)
DISSECTION_MAX_SHARE = 0.5


def dissection_layout(pattern: "SparsePattern", max_share: float = DISSECTION_MAX_SHARE
                      ) -> Optional[Tuple[np.ndarray, np.ndarray, int, int, np.ndarray, np.ndarray]]:
    """One level of nested dissection of the n × n matrices of a symmetric sparsity ``pattern``:
    its DOF graph cut in two at the median of its Fiedler vector (the Laplacian's second
    eigenvector, a spectral bisection), and the DOFs of one half that touch the other moved into
    a separator, so that no nonzero joins the two halves. With the halves padded to m DOFs each
    and the separator's s, the matrix is stored as [2, m, m] diagonal blocks A_kk, [2, m, s]
    A_ks, [2, s, m] A_sk and [s, s] A_ss (:func:`dissection_factor`).

    Returns (gather [2m + s]: the free DOF at each place, n where it is padding; scatter [n]: each
    DOF's place; m; s; each slot's place [nnz] in the flat storage; the storage places of the
    padding's diagonal [2m − n + s]); None where its factor (about 2m³/3 + 4m²s + 4ms² + 2s³/3 flops) is
    not below ``max_share`` of a dense LU's (2n³/3), or the cut leaves a half or the separator empty."""
    from scipy.sparse import csgraph, diags
    from scipy.sparse.linalg import eigsh

    n = pattern.n
    rows, cols = pattern.rows.numpy(), pattern.cols.numpy()
    off = rows != cols
    A = sparse.csr_matrix((np.ones(int(off.sum())), (rows[off], cols[off])), shape=(n, n))
    A = ((A + A.T) > 0).astype(float)
    if n < 8 or csgraph.connected_components(A, directed=False)[0] != 1:
        return None
    laplacian = (diags(np.asarray(A.sum(1)).ravel()) - A).tocsc()
    start = np.random.default_rng(0).standard_normal(n)              # (deterministic: the same layout each time)
    values, vectors = eigsh(laplacian, 2, sigma=-1e-6, which="LM", v0=start)
    fiedler = vectors[:, int(np.argsort(values)[1])]
    upper = fiedler > np.median(fiedler)
    coo = A.tocoo()
    touch = upper[coo.row] & ~upper[coo.col]
    separator = np.zeros(n, dtype=bool)
    separator[coo.row[touch]] = True
    halves = [np.flatnonzero(~upper), np.flatnonzero(upper & ~separator)]
    sep = np.flatnonzero(separator)
    m, ns = max(len(halves[0]), len(halves[1])), len(sep)
    if min(len(halves[0]), len(halves[1]), ns) == 0:
        return None
    if 2.0 * m**3 / 3.0 + 4.0 * m * m * ns + 4.0 * m * ns * ns + 2.0 * ns**3 / 3.0 > max_share * 2.0 * n**3 / 3.0:
        return None
    gather = np.full(2 * m + ns, n, dtype=np.int64)
    gather[:len(halves[0])] = halves[0]
    gather[m:m + len(halves[1])] = halves[1]
    gather[2 * m:] = sep
    scatter = np.empty(n, dtype=np.int64)
    real = gather < n
    scatter[gather[real]] = np.flatnonzero(real)
    part = np.full(n, 2)                                                  # 0, 1: a half; 2: the separator
    part[halves[1]] = 1
    part[halves[0]] = 0
    local = scatter - part * m                                            # place within its half or the separator
    pr, pc, lr, lc = part[rows], part[cols], local[rows], local[cols]
    if bool(((pr < 2) & (pc < 2) & (pr != pc)).any()):
        raise AssertionError("dissection_layout: a nonzero joins the two halves")
    ks, sk, ss = 2 * m * m, 2 * m * m + 2 * m * ns, 2 * m * m + 4 * m * ns
    slot = np.where((pr < 2) & (pc < 2), (pr * m + lr) * m + lc,
                    np.where(pc == 2, np.where(pr < 2, ks + (pr * m + lr) * ns + lc, ss + lr * ns + lc),
                             sk + (pc * ns + lr) * m + lc))
    pad = np.flatnonzero(~real[:2 * m])                                   # padded places of the halves
    pad_slot = ((pad // m) * m + pad % m) * m + pad % m
    return gather, scatter, m, ns, slot.astype(np.int64), pad_slot.astype(np.int64)


def dissection_factor(flat: Tensor, m: int, s: int) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The block LU of matrices stored as :func:`dissection_layout` lays them out, flat
    [B, 2m² + 4ms + s²]: each half's A_kk factored (partial pivoting within it; the step matrices
    are symmetric and their mass dominates), W_k = A_kk⁻¹ A_ks and the separator's Schur complement
    A_ss − Σ_k A_sk W_k factored. Returns (LU of the halves [B, 2, m, m], their pivots [B, 2, m],
    W = [W_1; W_2] [B, 2m, s], the couplings side by side [A_s1 A_s2] [B, s, 2m], the Schur complement's LU
    [B, s, s] and pivots [B, s]) for :func:`dissection_solve`, which takes the couplings' product
    with both halves as one matrix-vector product."""
    B = flat.shape[0]
    ks, sk, ss = 2 * m * m, 2 * m * m + 2 * m * s, 2 * m * m + 4 * m * s
    halves = flat[:, :ks].reshape(B * 2, m, m)
    A_ks = flat[:, ks:sk].reshape(B, 2, m, s)
    A_sk = flat[:, sk:ss].reshape(B, 2, s, m)
    lu, pivots = lu_factor_each(halves)
    lu, pivots = lu.reshape(B, 2, m, m), pivots.reshape(B, 2, m)
    W = torch.linalg.lu_solve(lu, pivots, A_ks)                                           # [B, 2, m, s]
    schur = flat[:, ss:].reshape(B, s, s) - (A_sk @ W).sum(1)                             # [B, s, s]
    lu_s, pivots_s = lu_factor_each(schur)
    W_s = W.reshape(B, 2 * m, s).contiguous()                                              # [B, 2m, s]
    return lu, pivots, W_s, A_sk.transpose(1, 2).reshape(B, s, 2 * m), lu_s, pivots_s     # A_s [B, s, 2m]


def dissection_solve(lu: Tensor, pivots: Tensor, W: Tensor, A_s: Tensor, lu_s: Tensor, pivots_s: Tensor,
                     r: Tensor) -> Tensor:
    """x [B, 2m + s] with A x = r [B, 2m + s] (halves, then the separator) for the A that
    :func:`dissection_factor` factored (W [B, 2m, s], A_s = [A_s1 A_s2] [B, s, 2m]): y_k = A_kk⁻¹ r_k,
    x_s = S⁻¹ (r_s − Σ_k A_sk y_k), x_k = y_k − W_k x_s."""
    B, m, s = r.shape[0], lu.shape[-1], lu_s.shape[-1]
    y = torch.linalg.lu_solve(lu, pivots, r[:, :2 * m].reshape(B, 2, m, 1)).reshape(B, 2 * m, 1)   # [B, 2m, 1]
    g = torch.baddbmm(r[:, 2 * m:].unsqueeze(-1), A_s, y, beta=1.0, alpha=-1.0)          # [B, s, 1]
    x_s = torch.linalg.lu_solve(lu_s, pivots_s, g)                                         # [B, s, 1]
    x_k = torch.baddbmm(y, W, x_s, beta=1.0, alpha=-1.0)                                   # [B, 2m, 1]
    return torch.cat([x_k.reshape(B, 2 * m), x_s.squeeze(-1)], 1)


def lu_factor_each(A: Tensor) -> Tuple[Tensor, Tensor]:
    """(LU, pivots) of A [B, m, m]: one sample at a time on the CPU (``solve_each``), batched elsewhere.
    The LU factors stay column-major ([B, m, m] with strides (m², 1, m)), as LAPACK writes them, so
    ``torch.linalg.lu_solve`` takes them without a copy (a row-major stack cost the liver's
    dissected step three transposing copies of its halves, 5.6 ms)."""
    if A.device.type != "cpu":
        return torch.linalg.lu_factor(A)
    if A.shape[0] == 1:                        # no stacked copy (serve's one sample)
        lu, piv = torch.linalg.lu_factor(A[0])
        return lu.unsqueeze(0), piv.unsqueeze(0)
    lus: List[Tensor] = []
    pivots: List[Tensor] = []
    for i in range(A.shape[0]):
        lu, piv = torch.linalg.lu_factor(A[i])
        lus.append(lu.mT)                      # column-major: its transpose is row-major, stacked as is
        pivots.append(piv)
    return torch.stack(lus).mT, torch.stack(pivots)


def band_factor(S: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """The block LU of block-tridiagonal matrices S [B, 3, nb, w, w] (``band_layout``'s diagonal,
    lower and upper blocks D, L, U), without pivoting across blocks (the step matrices are
    symmetric and their mass dominates; within a block, partial pivoting): the Schur complements
    D'_k = D_k − L_(k−1) X_(k−1), X_k = D'_k⁻¹ U_k. Returns (LU of each D' [B, nb, w, w], its
    pivots [B, nb, w], X [B, nb, w, w] (the last zero), L [B, nb, w, w]) for :func:`band_solve`."""
    D, L, U = S[:, 0], S[:, 1], S[:, 2]
    lus: List[Tensor] = []
    pivots: List[Tensor] = []
    Xs: List[Tensor] = []
    nb = S.shape[2]
    for k in range(nb):
        Dk = D[:, k]
        if k > 0:
            Dk = Dk - L[:, k - 1] @ Xs[k - 1]
        lu, piv = lu_factor_each(Dk)
        lus.append(lu)
        pivots.append(piv)
        Xs.append(torch.linalg.lu_solve(lu, piv, U[:, k]) if k < nb - 1 else torch.zeros_like(Dk))
    return torch.stack([lu.mT for lu in lus], 1).mT, torch.stack(pivots, 1), torch.stack(Xs, 1), L   # column-major LUs


def band_solve(lu: Tensor, pivots: Tensor, X: Tensor, L: Tensor, r: Tensor) -> Tensor:
    """x [B, nb, w] with S x = r [B, nb, w] for the block-tridiagonal S that :func:`band_factor`
    factored: forward c_k = D'_k⁻¹ (r_k − L_(k−1) c_(k−1)), back x_k = c_k − X_k x_(k+1)."""
    nb = r.shape[1]
    cs: List[Tensor] = []
    for k in range(nb):
        g = r[:, k]
        if k > 0:
            g = g - (L[:, k - 1] @ cs[k - 1].unsqueeze(-1)).squeeze(-1)
        cs.append(torch.linalg.lu_solve(lu[:, k], pivots[:, k], g.unsqueeze(-1)).squeeze(-1))
    xs: List[Tensor] = [cs[nb - 1]]
    for k in range(nb - 2, -1, -1):
        xs.insert(0, cs[k] - (X[:, k] @ xs[0].unsqueeze(-1)).squeeze(-1))
    return torch.stack(xs, 1)


#: Newton iterations of :func:`polar_rotation`: from singular values in [0.5, 1.5], six reach round-off
POLAR_ITERATIONS = 8


def polar_rotation(F: Tensor, iterations: int = POLAR_ITERATIONS) -> Tensor:
    """R of the polar decomposition F = R U [..., 3, 3] (det F > 0) by Newton's iteration
    R ← (R + R⁻ᵀ) / 2 from R = F, which takes each singular value s to (s + 1/s) / 2. Smooth
    where F = I, so autograd of any order passes (an SVD's gradient is undefined where singular
    values coincide, as they do at rest); scriptable."""
    R = F
    for _ in range(iterations):
        R = 0.5 * (R + torch.linalg.inv(R).transpose(-1, -2))
    return R


class CorotatedNewmarkPrior(NewmarkPrior):
    """The Newmark step of the solid corotated per P1 cell (``thermognn.core.corotated``): each
    cell's linear force R_e K_e (R_eᵀ x_e − X_e) and linear stress in its rotated frame, the
    rotations R_e implicit in each step (``sweeps`` fixed-point sweeps, each one linear solve; docs/
    accuracy.md, session 42: two reach the shell's converged errors). The solve is a sparse LU on
    the CPU (``sparse_solve``: the bunny's 5319 DOFs in 0.2 s, 7x faster than dense with twice the
    threads), dense and batched on a GPU and in TorchScript. With the
    remainders G = f_corot(u) − f_int(u) and H = σ − σ_corot (what ``remainders`` recovers) it is
    the FE step; with none, the corotated FE model ``evaluate`` reports. The rotations are
    differentiable (:func:`polar_rotation`), so rollouts back-propagate through them.

    ``relax`` (a viscous solid): it relaxes as the corotated FE model does, each cell's Prony
    history in its rotated frame. Per term i and cell e the internal variable is the isochoric
    stress history s_i,e (Voigt, Pa) of the cell's strain ε̃ = sym(R_eᵀ F_e) − I: it starts at
    2 μ dev ε̃ and steps as s_i ← d_i s_i + w_i 2 μ dev sym(R₁ᵀ (F₁ − F₀)) (the increment in the
    step's end frame). Its force is the cell's V_e s ∇φ_a (K_iso,e of the history), so with
    K_Δt,e = K_e − Σ ḡ_i (1 − w_i) K_iso,e the internal force at a step's end is
    Σ_e R_e (K_Δt,e d_e + Σ ḡ_i V_e (d_i s_i − w_i 2 μ dev ε̃₀) ∇φ) (``thermognn.core.corotated``),
    and the stress R (λ tr ε̃ I + 2 μ ε̃ + Σ ḡ_i (s_i − 2 μ dev ε̃)) Rᵀ. The variables are per cell
    ([B, T_prony, 6 T]); carried states hold them packed into nodal columns (``pack_internal``).

    X [N, 3] m, tets [T, 4], Lamé λ, μ [Pa] at rest; the operators of ``linear`` as
    :class:`NewmarkPrior` takes them (its K is the assembled K_e; its Σ is not used).

    ``neo_hookean`` (C10 [Pa], D1 [1/Pa]; ``model.prior_stress=material``): the stress is the
    material's own law of each cell's F (:func:`neo_hookean_cauchy`) instead of the corotated
    linear stress, so that H = σ − σ(u) vanishes for the FE's data (the FE's P1 stress is that
    law, volume-averaged at the nodes) and the σ of a rollout is wrong only where its strains are."""

    def __init__(self, linear: LinearSolid, n_nodes: int, dt: float, X: np.ndarray, tets: np.ndarray,
                 lam: float, mu: float, sweeps: int = 3, dtype: torch.dtype = torch.float64,
                 neo_hookean: Optional[Tuple[float, float]] = None, relax: bool = False) -> None:
        if relax and neo_hookean is not None:
            raise ValueError("the material law's stress has no Prony history (relax with the corotated linear stress)")
        super().__init__(linear, n_nodes, dt, dtype, relax=relax, step_matrix=False)   # its step solves anew
        from thermognn.core.corotated import element_stiffness
        from thermognn.core.kinematics import shape_gradients

        X, tets = np.asarray(X, dtype=float), np.asarray(tets, dtype=np.int64)
        T, n = len(tets), self.n_free
        Ke, Ke_iso = element_stiffness(X, tets, lam, mu)                              # [T, 12, 12] N/m
        grad, volume = shape_gradients(X, tets)                                       # [T, 4, 3], [T]
        index = np.full(3 * n_nodes, -1)
        index[np.asarray(linear.free, dtype=bool)] = np.arange(n)
        dofs = index[(3 * tets[:, :, None] + np.arange(3)).reshape(T, 12)]            # [T, 12] free index or −1
        rows, cols = np.repeat(dofs, 12, axis=1).ravel(), np.tile(dofs, (1, 12)).ravel()   # [T 144]
        keep = np.flatnonzero((rows >= 0) & (cols >= 0))
        weight = np.zeros(n_nodes)
        np.add.at(weight, tets.ravel(), np.repeat(volume, 4))
        buffers = {
            "cell_nodes": torch.as_tensor(tets),                                      # [T, 4]
            "cell_dofs": torch.as_tensor((3 * tets[:, :, None] + np.arange(3)).reshape(-1)),  # [12 T] of 3N
            "shape_grad": torch.as_tensor(grad, dtype=dtype),                         # [T, 4, 3] 1/m
            "cell_X": torch.as_tensor(X[tets], dtype=dtype),                          # [T, 4, 3] m
            "cell_K": torch.as_tensor(Ke, dtype=dtype),                               # [T, 12, 12] N/m
            "pair_keep": torch.as_tensor(keep),                                       # [k] of T 144
            "cell_volume": torch.as_tensor(volume, dtype=dtype),                      # [T] m³
            "node_weight": torch.as_tensor(weight, dtype=dtype),                      # [N] m³
            "reference": torch.as_tensor(X, dtype=dtype),                             # [N, 3] m
            # (1 + c) K_e − Σ ḡ_i (1 − w_i) K_iso,e: the step's cell stiffness with stiffness damping
            # and relaxation (K_Δt,e + c K_e; (1 + c) K_e for the elastic prior)
            "cell_K_step": torch.as_tensor((1.0 + self.c) * Ke - self._shrink() * Ke_iso, dtype=dtype),
            "voigt_eye": torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0, 0.0], dtype=dtype)}                # I in Voigt
        # the step matrix's sparsity (CSC over the free DOFs), for the CPU's sparse LU (``sparse_solve``)
        mass = sparse.csc_matrix(linear.mass, dtype=float)
        mass_rows, mass_cols = mass.nonzero()
        pair_key = cols[keep] * n + rows[keep]                                        # [k] column-major
        key = np.unique(np.concatenate([pair_key, mass_cols * n + mass_rows]))       # [nnz]
        self.pattern = SparsePattern(key % n, np.searchsorted(key // n, np.arange(n + 1)), n)
        buffers.update({
            "pair_slot": torch.as_tensor(np.searchsorted(key, pair_key)),            # [k] of nnz
            "slot_flat": torch.as_tensor((key % n) * n + key // n),                  # [nnz] of n n (row-major)
            "mass_values": torch.as_tensor(np.asarray(mass[key % n, key // n]).ravel(), dtype=dtype)})  # [nnz] kg
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        #: solve each sweep by sparse LU (scipy) on the CPU, where a dense LU of a few thousand DOFs
        #: takes seconds; dense on a GPU (batched) and in TorchScript (export, serve)
        self.sparse_cpu = True
        self.lam, self.mu, self.sweeps = float(lam), float(mu), int(sweeps)
        self.n_cells = int(T)
        # Σ ḡ_i w_i: the weight of the cells' isochoric stress at a step's start in its history force
        self.history_increment = float((self.prony_weight * self.prony_increment).sum())
        # nodal columns per Prony term that hold its 6 T cell variables in a carried state [N, ...]
        self.cell_columns = -(-6 * T // int(n_nodes))
        self.material_stress = neo_hookean is not None
        self.c10, self.d1 = (float(neo_hookean[0]), float(neo_hookean[1])) if neo_hookean is not None else (0.0, 0.0)

    # --- per cell -------------------------------------------------------------------------------
    def positions(self, u: Tensor) -> Tensor:
        """Nodal positions x [B, N, 3] m of free-DOF displacements u [B, n]."""
        return self.reference.unsqueeze(0) + self.scatter(u)

    def deformation_gradients(self, x: Tensor) -> Tensor:
        """F [B, T, 3, 3] of the cells at positions x [B, N, 3] m (constant over a P1 cell)."""
        return torch.einsum("btai,taj->btij", x[:, self.cell_nodes], self.shape_grad)   # x_e [B, T, 4, 3]

    def inverted(self, x: Tensor) -> Tensor:
        """Whether positions x [B, N, 3] m turn a cell inside out (det F <= 0) [B] (bool): where
        they do, the polar factor is a reflection and the corotated force pushes on through."""
        return (torch.linalg.det(self.deformation_gradients(x.to(self.cell_X.dtype))) <= 0).any(1)

    def rotations(self, x: Tensor) -> Tuple[Tensor, Tensor]:
        """(R [B, T, 3, 3], F [B, T, 3, 3]) of the cells at positions x [B, N, 3]."""
        F = self.deformation_gradients(x)
        return polar_rotation(F), F

    def local(self, R: Tensor, x: Tensor) -> Tensor:
        """R_eᵀ x_e − X_e [B, T, 12] m (x [B, N, 3]); x = X gives R_eᵀ X_e − X_e."""
        xe = x[:, self.cell_nodes]                                                    # [B, T, 4, 3]
        d = torch.einsum("btji,btaj->btai", R, xe) - self.cell_X.unsqueeze(0)
        return d.reshape(d.shape[0], d.shape[1], 12)

    def to_free(self, R: Tensor, fe: Tensor) -> Tensor:
        """Cell forces fe [B, T, 12] in the rotated frames, rotated back and summed into the free DOFs [B, n]."""
        B, T = fe.shape[0], fe.shape[1]
        f = torch.einsum("btij,btaj->btai", R, fe.reshape(B, T, 4, 3)).reshape(B, -1)   # [B, 12 T]
        full = fe.new_zeros(B, 3 * self.n_nodes).index_add(1, self.cell_dofs, f)        # [B, 3N]
        return full.index_select(1, self.free_index)

    def elastic_force(self, u: Tensor) -> Tensor:
        """Σ_e R_e K_e (R_eᵀ x_e − X_e) [B, n] N at free-DOF displacements u [B, n]."""
        x = self.positions(u)
        R, _ = self.rotations(x)
        return self.to_free(R, torch.einsum("tij,btj->bti", self.cell_K, self.local(R, x)))

    def rotated_pairs(self, R: Tensor, cell_K: Tensor) -> Tensor:
        """The entries R_e K_e R_eᵀ [B, k] N/m of the cells' K_e [T, 12, 12] that fall on pairs of
        free DOFs (``pair_keep``), unsummed: ``sparse_values`` sums them into ``pattern``'s slots."""
        B, T = R.shape[0], R.shape[1]
        KR = torch.einsum("ztij,tajck,ztlk->ztaicl", R, cell_K.reshape(T, 4, 3, 4, 3), R).reshape(B, T * 144)
        return KR.index_select(1, self.pair_keep)

    def sparse_values(self, pairs: Tensor) -> Tensor:
        """The step matrix c0 m_f M + K [B, nnz] N/m in ``pattern``'s slots, of the stiffness's
        unsummed pairs [B, k] N/m (``rotated_pairs``; the law prior's tangent pairs)."""
        return (self.c0 * self.mass_factor * self.mass_values).expand(pairs.shape[0], -1).index_add(
            1, self.pair_slot, pairs)

    def placed_values(self, pairs: Tensor, size: int, slot: Tensor) -> Tensor:
        """The step matrix's nonzeros (``sparse_values`` of the stiffness's pairs [B, k] N/m) put
        into a zero storage [B, size] at their places ``slot`` [nnz]: distinct places, so copied in
        place (an index_add into zeros took the liver's dense matrix 4–24 ms more)."""
        return pairs.new_zeros(pairs.shape[0], size).index_copy_(1, slot, self.sparse_values(pairs))

    def dense_system(self, pairs: Tensor) -> Tensor:
        """The step matrix c0 m_f M + K [B, n, n] N/m, dense, of the stiffness's pairs [B, k]: its
        nonzeros put in place (``placed_values``; one n × n array written once: the liver's 1278²
        took a fifth of a scripted law-prior step when mass and stiffness were summed as dense
        arrays, docs/accuracy.md session 74)."""
        B, n = pairs.shape[0], self.n_free
        return self.placed_values(pairs, n * n, self.slot_flat).reshape(B, n, n)

    @torch.jit.unused
    def sparse_solve(self, R: Tensor, b: Tensor) -> Tensor:
        """u [B, n] m solving (c0 m_f M + Σ_e R_e K_Δt,e R_eᵀ) u = b [B, n] N, the step's system,
        assembled into ``pattern`` and factorised by sparse LU (:class:`SparseSolve`): the system
        ``dense_system`` builds dense (TorchScript, a GPU)."""
        return SparseSolve.apply(self.sparse_values(self.rotated_pairs(R, self.cell_K_step)), b, self.pattern)

    # --- the step -------------------------------------------------------------------------------
    def step(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor,
             G1: Tensor, h0: Tensor, f0: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(u1, v1, a1, h1) as :meth:`NewmarkPrior.step`, with the corotated internal force:
        M a1 + αM M v1 + c (f(u1) − f(u0)) + f(u1) = f1 + (1 + c) G1 − c G0, f(u1) = K_R u1 +
        Σ_e R_e K_e (R_eᵀ X_e − X_e) with R at the latest iterate of u1 (``sweeps`` solves)."""
        predictor = self.newmark_predictor(u0, v0, a0)
        inertia = self.mass(self.mass_factor * predictor - self.alpha_m * v0
                            - self.alpha_m * self.dt * (1.0 - self.gamma) * a0)
        x0 = self.positions(u0)
        R, F0 = self.rotations(x0)                                                          # at the step's start
        rhs = (inertia + self.c * self.to_free(R, torch.einsum("tij,btj->bti", self.cell_K, self.local(R, x0)))
               + f1 + self.body_force + (1.0 + self.c) * G1 - self.c * G0)                  # [B, n] N
        reference = self.reference.unsqueeze(0).expand(u0.shape[0], -1, -1)
        u1 = u0
        for sweep in range(self.sweeps):         # fixed-point sweeps: the rotations of the latest u1
            if sweep > 0:
                R, _ = self.rotations(self.positions(u1))
            # the cells' K_Δt + c K (class doc) of R_eᵀ X_e − X_e, and relaxing, the history at the step's start
            cell = torch.einsum("tij,btj->bti", self.cell_K_step, self.local(R, reference))     # [B, T, 12] N
            if self.n_terms > 0:
                history = (self.prony_weight * self.prony_decay).view(1, -1, 1, 1) * h0.reshape(
                    h0.shape[0], self.n_terms, self.n_cells, 6)                              # [B, T_p, T, 6] Pa
                cell = cell + self.cell_force(history.sum(1) - self.history_increment
                                              * self.deviatoric_stress(R, F0))
            b = rhs - self.to_free(R, cell)
            if not bool(torch.isfinite(b).all()):      # a cell flattened, or the remainders blew up
                raise RuntimeError("corotated prior: a non-finite state (a cell inverted, or the remainders diverged)")
            if not torch.jit.is_scripting() and self.sparse_cpu and b.device.type == "cpu":
                u1 = self.sparse_solve(R, b)
            else:
                u1 = solve_each(self.dense_system(self.rotated_pairs(R, self.cell_K_step)), b)   # A [B, n, n] N/m
        a1, v1 = self.newmark_rates(u1, v0, a0, predictor)
        return u1, v1, a1, self.relax(u0, u1, h0)

    # --- the Prony history per cell (``relax``; class docstring) ---------------------------------
    def _shrink(self) -> float:
        """Σ ḡ_i (1 − w_i): how much of K_iso the step's stiffness K_Δt takes off (0 elastic)."""
        return float((self.prony_weight * (1.0 - self.prony_increment)).sum())

    def deviatoric_stress(self, R: Tensor, F: Tensor) -> Tensor:
        """2 μ dev sym(Rᵀ F) [B, T, 6] Pa (Voigt 11 22 33 12 13 23): the isochoric stress of the
        cells' strain in their rotated frames (R, F [B, T, 3, 3]; with F an increment F₁ − F₀, of
        the increment's)."""
        local = R.transpose(-1, -2) @ F
        eps = 0.5 * (local + local.transpose(-1, -2))
        tr = eps.diagonal(dim1=-2, dim2=-1).sum(-1)                                        # [B, T]
        return 2.0 * self.mu * (_voigt(eps) - (tr / 3.0).unsqueeze(-1) * self.voigt_eye)

    def cell_force(self, s: Tensor) -> Tensor:
        """The nodal forces V_e s ∇φ_a [B, T, 12] N of cell stresses s [B, T, 6] Pa (Voigt), in the
        cells' own frames: K_e of a cell displacement is that of its stress."""
        S = _matrix(s)                                                                       # [B, T, 3, 3]
        f = torch.einsum("btij,taj->btai", S, self.shape_grad) * self.cell_volume.view(1, -1, 1, 1)
        return f.reshape(f.shape[0], f.shape[1], 12)

    def internal_variables(self, u: Tensor) -> Tensor:
        """h [B, T_prony, 6 T] at displacements u [B, n] applied at once: s_i = 2 μ dev ε̃ per cell."""
        if self.n_terms == 0:
            return u.new_zeros(u.shape[0], 0, 0)
        R, F = self.rotations(self.positions(u))
        s = self.deviatoric_stress(R, F).reshape(u.shape[0], 1, -1)
        return s.expand(-1, self.n_terms, -1).contiguous()

    def relax(self, u0: Tensor, u1: Tensor, h0: Tensor) -> Tensor:
        """h1 after a step from u0 to u1 [B, n]: s_i ← d_i s_i + w_i 2 μ dev sym(R₁ᵀ (F₁ − F₀))."""
        if self.n_terms == 0:
            return h0
        R1, F1 = self.rotations(self.positions(u1))
        F0 = self.deformation_gradients(self.positions(u0))
        step = self.deviatoric_stress(R1, F1 - F0).reshape(u0.shape[0], 1, -1)               # [B, 1, 6 T]
        return self.prony_decay.view(1, -1, 1) * h0 + self.prony_increment.view(1, -1, 1) * step

    def _relaxed(self, R: Tensor, F: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (s_i − 2 μ dev ε̃) [B, T, 6] Pa: what relaxation takes off the cells' stress."""
        s = h.reshape(h.shape[0], self.n_terms, self.n_cells, 6)
        return (self.prony_weight.view(1, -1, 1, 1) * (s - self.deviatoric_stress(R, F).unsqueeze(1))).sum(1)

    def relaxation_force(self, u: Tensor, h: Tensor) -> Tensor:
        """Σ_e R_e V_e Σ ḡ_i (s_i − 2 μ dev ε̃) ∇φ [B, n] N at displacements u [B, n] with the
        internal variables h of a step's end."""
        R, F = self.rotations(self.positions(u))
        return self.to_free(R, self.cell_force(self._relaxed(R, F, h)))

    def stress_relaxation(self, u: Tensor, h: Tensor) -> Tensor:
        """R Σ ḡ_i (s_i − 2 μ dev ε̃) Rᵀ [B, N, 6] Pa, volume-averaged at the nodes."""
        B = u.shape[0]
        if self.n_terms == 0:
            return u.new_zeros(B, self.n_nodes, 6)
        R, F = self.rotations(self.positions(u))
        return self.nodal(R @ _matrix(self._relaxed(R, F, h)) @ R.transpose(-1, -2))

    def internal_columns(self) -> List[Tuple[str, int]]:
        """Per Prony term its cell variables (6 T, Voigt per cell, cell-major), packed row-major
        into ``cell_columns`` nodal columns (zero-padded)."""
        return [(f"prony_cells_{i + 1}", self.cell_columns) for i in range(self.n_terms)]

    def pack_internal(self, h: Tensor) -> Tensor:
        """h [B, T_prony, 6 T] -> nodal columns [B, N, T_prony cell_columns] (``internal_columns``)."""
        B, N, w = h.shape[0], self.n_nodes, self.cell_columns
        if self.n_terms == 0:
            return h.new_zeros(B, N, 0)
        padded = torch.cat([h, h.new_zeros(B, self.n_terms, N * w - 6 * self.n_cells)], -1)   # [B, T_p, N w]
        return padded.reshape(B, self.n_terms, N, w).permute(0, 2, 1, 3).reshape(B, N, self.n_terms * w)

    def unpack_internal(self, x: Tensor) -> Tensor:
        """Nodal columns [B, N, T_prony cell_columns] -> h [B, T_prony, 6 T]: the inverse of ``pack_internal``."""
        B, N, w = x.shape[0], self.n_nodes, self.cell_columns
        if self.n_terms == 0:
            return x.new_zeros(B, 0, 0)
        flat = x.reshape(B, N, self.n_terms, w).permute(0, 2, 1, 3).reshape(B, self.n_terms, N * w)
        return flat[:, :, :6 * self.n_cells].contiguous()

    def stress(self, u: Tensor, H: Optional[Tensor] = None) -> Tensor:
        """Nodal Cauchy stress σ_cell + H [B, N, 6] Pa (Voigt 11 22 33 12 13 23) of the nodal
        displacements u [B, N, 3] m, volume-averaged at the nodes as the dataset's. σ_cell: the
        corotated linear stress R (λ tr ε̃ I + 2 μ ε̃) Rᵀ, ε̃ = sym(Rᵀ F) − I (the stress the corotated
        force balances), or with ``neo_hookean`` the material's law of F."""
        B = u.shape[0]
        x = self.reference.unsqueeze(0) + u
        if self.material_stress:
            sig = neo_hookean_cauchy(self.deformation_gradients(x), self.c10, self.d1)     # [B, T, 3, 3]
        else:
            R, F = self.rotations(x)
            local = R.transpose(-1, -2) @ F
            eye = torch.eye(3, dtype=u.dtype, device=u.device)
            eps = 0.5 * (local + local.transpose(-1, -2)) - eye
            tr = eps.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
            sig = R @ (self.lam * tr * eye + 2.0 * self.mu * eps) @ R.transpose(-1, -2)    # [B, T, 3, 3]
        cell = self.nodal(sig)
        return cell if H is None else cell + H

    def nodal(self, sig: Tensor) -> Tensor:
        """Cell tensors sig [B, T, 3, 3] volume-averaged at the nodes [B, N, 6] (Voigt), as the
        dataset stores its stress."""
        B = sig.shape[0]
        voigt = _voigt(sig) * self.cell_volume.view(1, -1, 1)                                 # [B, T, 6]
        T = voigt.shape[1]
        nodal = voigt.new_zeros(B, self.n_nodes, 6).index_add(
            1, self.cell_nodes.reshape(-1), voigt.unsqueeze(2).expand(B, T, 4, 6).reshape(B, 4 * T, 6))
        return nodal / self.node_weight.view(1, -1, 1)


def _voigt(S: Tensor) -> Tensor:
    """Symmetric tensors [..., 3, 3] -> Voigt [..., 6] (11 22 33 12 13 23)."""
    return torch.stack([S[..., 0, 0], S[..., 1, 1], S[..., 2, 2], S[..., 0, 1], S[..., 0, 2], S[..., 1, 2]], -1)


def _matrix(s: Tensor) -> Tensor:
    """Voigt [..., 6] (11 22 33 12 13 23) -> symmetric tensors [..., 3, 3]."""
    rows = [torch.stack([s[..., 0], s[..., 3], s[..., 4]], -1), torch.stack([s[..., 3], s[..., 1], s[..., 5]], -1),
            torch.stack([s[..., 4], s[..., 5], s[..., 2]], -1)]
    return torch.stack(rows, -2)


def neo_hookean_cauchy(F: Tensor, c10: float, d1: float) -> Tensor:
    """Cauchy stress σ [..., 3, 3] Pa of the neo-Hookean law Ψ = C10 (Ī1 − 3) + (J − 1)² / D1
    (``thermognn/generate/materials.py``; C10 [Pa], D1 [1/Pa]) at deformation gradients F [..., 3, 3]:
    σ = 2 C10 / J dev(B̄) + 2 / D1 (J − 1) I, B̄ = J^(−2/3) F Fᵀ. Smooth at F = I (autograd of
    any order); J ≤ 0 (an inverted cell) gives NaN."""
    J = torch.linalg.det(F)[..., None, None]                                           # [..., 1, 1]
    Bbar = J.pow(-2.0 / 3.0) * (F @ F.transpose(-1, -2))
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    dev = Bbar - Bbar.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None] / 3.0 * eye
    return 2.0 * c10 / J * dev + 2.0 / d1 * (J - 1.0) * eye
