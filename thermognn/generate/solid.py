"""A nonlinear solid (dolfinx 0.5): hyperelastic, optionally viscous, inertial and under gravity.

The weak form reads like the balance of momentum in the reference configuration, for a test
function w (SI units, forces in N)::

    R(u; w) = ∫ ρ a·w dX  +  ∫ P(F) : Grad w dX  +  ∫ (αM ρ v·w + βK Ṗ : Grad w) dX
              − ∫ ρ g·w dX  −  f_ext · w  = 0

Only the terms the scene's effects call for are assembled (``inertia``: mass and Rayleigh
damping; ``gravity``: ρ g; ``viscous``: Prony internal variables in P). ``f_ext`` is a vector of
nodal forces [N] added to the assembled residual. Time integration is Newmark (β, γ; the default
β = 1/4, γ = 1/2 is the trapezoidal rule, energy conserving for linear problems), generalized-α
(ρ∞ < 1 damps the unresolved high frequencies) or quasi-static load stepping. Each step is solved by Newton's method with an LU solve (PETSc), a back-tracking
line search against non-finite residuals (J ≤ 0), and step cutting: a failed step is retried in
halves down to ``min_step_fraction`` of the nominal dt.

Finite-strain viscoelasticity (Simo 1987, Holzapfel's algorithm): with the isochoric elastic stress
S⁰_iso(t) and h_i(t) = ∫ exp(−(t−s)/τi) dS⁰_iso/ds ds, the stress is
S = S_vol + (1 − Σ ḡi) S⁰_iso + Σ ḡi h_i, i.e. S_iso(t) = ∫ g_R(t−s) dS⁰_iso/ds ds. The update over
a step Δt is exact for S⁰_iso linear in time within the step:
h_i ← exp(−Δt/τi) h_i + τi/Δt (1 − exp(−Δt/τi)) (S⁰_iso,new − S⁰_iso,old).
The internal variables live in a cell-wise constant (DG0) tensor space, exact for P1 tets where
F is constant per cell; viscous problems therefore require degree-1 elements.

Node-wise outputs (the graph nodes are the P1 nodes = mesh vertices): Cauchy stress σ and the
viscous overstresses are evaluated at each cell centroid and **volume-averaged** onto the nodes
(σ_node = Σ_cells |T| σ_T / Σ_cells |T| over the cells touching the node).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem import petsc as fem_petsc
from petsc4py import PETSc

from .materials import Material, cauchy_from_pk2, pk2_split, strain_energy, voigt


def direct_solver(comm, A) -> PETSc.KSP:
    """Sparse LU: MUMPS when PETSc has it, else PETSc's own LU with nested-dissection ordering."""
    ksp = PETSc.KSP().create(comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    pc = ksp.getPC()
    pc.setType("lu")
    if PETSc.Sys.hasExternalPackage("mumps"):
        pc.setFactorSolverType("mumps")
    else:
        pc.setFactorOrderingType("nd")
    return ksp


def material_constants(material: Material, domain) -> Material:
    """The same material with its law parameters as ``fem.Constant`` (lists stay lists)."""
    import dataclasses

    def const(v):
        return fem.Constant(domain, PETSc.ScalarType(v))

    params = {k: [const(x) for x in v] if isinstance(v, (list, tuple)) else const(v)
              for k, v in material.params.items()}
    return dataclasses.replace(material, params=params)


@dataclass
class SolverOptions:
    """Discretisation and solver settings (see conf/scene/block.yaml ``solver`` and ``time``)."""

    degree: int = 1                      # Lagrange degree of the displacement (1: P1 tets)
    quadrature_degree: int = 2           # ALWAYS explicit (Ogden's automatic estimate explodes)
    integrator: str = "newmark"          # newmark | generalized_alpha | quasi_static
    beta: float = 0.25                   # Newmark β (newmark)
    gamma: float = 0.5                   # Newmark γ (newmark)
    rho_inf: float = 1.0                 # generalized-α spectral radius at infinite frequency, in [0, 1]
    rayleigh: tuple[float, float] = (0.0, 0.0)   # (αM [1/s], βK [s])
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)  # [m/s^2]
    rtol: float = 1e-8                   # Newton: ||R|| <= max(atol, rtol ||R0||)
    atol: float = 1e-10                  # [N]
    max_iterations: int = 25
    min_step_fraction: float = 1.0 / 16  # step cutting floor, fraction of the nominal dt
    line_search_halvings: int = 6


@dataclass
class StepReport:
    ok: bool
    reason: str = ""
    iterations: int = 0
    cuts: int = 0


class Solid:
    """Displacement-based finite-element solid on a dolfinx mesh.

    Attributes (nodal arrays, blocked: node i, component c at 3 i + c):
      u, u_n, v_n, a_n: displacement [m], velocity [m/s], acceleration [m/s^2] (fem.Function)
      f_ext: external nodal forces [N] (fem.Function used as a plain vector)
    """

    def __init__(self, domain, material: Material, effects, options: SolverOptions | None = None):
        self.domain = domain
        self.mat = material
        self.effects = tuple(effects)
        self.opt = options or SolverOptions()
        self.inertia = "inertia" in self.effects and self.opt.integrator != "quasi_static"
        self.viscous = "viscous" in self.effects and len(material.prony) > 0
        self.gravity = "gravity" in self.effects
        if self.viscous and self.opt.degree != 1:
            raise ValueError("viscous internal variables are cell-wise constant: use degree-1 elements")

        V = fem.VectorFunctionSpace(domain, ("Lagrange", self.opt.degree))
        self.V = V
        self.u = fem.Function(V, name="u")
        self.u_n = fem.Function(V)
        self.v_n = fem.Function(V)
        self.a_n = fem.Function(V)
        self.f_ext = fem.Function(V)
        self.f_n = fem.Function(V)          # external force at t_n (generalized-α)
        self.beta, self.gamma, self.alpha_m, self.alpha_f = self._integrator_parameters()
        self.bcs: list = []
        self.dx = ufl.Measure("dx", domain=domain, metadata={"quadrature_degree": self.opt.quadrature_degree})
        self.dt = fem.Constant(domain, PETSc.ScalarType(1.0))
        self.rho = fem.Constant(domain, PETSc.ScalarType(material.density))
        # material parameters as fem.Constants: one compiled kernel serves every parameter value
        self.mat_ufl = material_constants(material, domain)

        w = ufl.TestFunction(V)
        du = ufl.TrialFunction(V)
        F, S_iso, S_vol = pk2_split(self.mat_ufl, self.u)
        self._F = F
        self._S_el = S_iso + S_vol
        S_trial, S_committed = self._viscous_stress(S_iso, S_vol)
        P = F * S_trial
        self._w = w
        self._P = P
        if self.alpha_f:  # generalized-α: internal force (1 − αf) f_int(u_n+1) + αf f_int(u_n)
            F_n, S_iso_n, S_vol_n = pk2_split(self.mat_ufl, self.u_n)
            self._P = (1.0 - self.alpha_f) * P + self.alpha_f * F_n * self._committed_stress(S_iso_n, S_vol_n)
        if self.inertia:
            b, g, dt = self.beta, self.gamma, self.dt
            a_new = (self.u - self.u_n - dt * self.v_n) / (b * dt**2) - (1.0 / (2 * b) - 1.0) * self.a_n
            v_new = self.v_n + dt * ((1 - g) * self.a_n + g * a_new)
            a_mid = (1.0 - self.alpha_m) * a_new + self.alpha_m * self.a_n
            v_mid = (1.0 - self.alpha_f) * v_new + self.alpha_f * self.v_n
            R = self.rho * ufl.inner(a_mid, w) * self.dx + self._force_terms(v_mid)
        else:
            R = self._force_terms(None)
        self.residual_form = fem.form(R)
        self.jacobian_form = fem.form(ufl.derivative(R, self.u, du))

        # outputs: Cauchy stress at the centroid of every cell
        centroid = np.array([[0.25, 0.25, 0.25]])
        self._sigma_expr = fem.Expression(voigt(cauchy_from_pk2(F, S_committed)), centroid)
        self._pk2_expr = fem.Expression(voigt(S_committed), centroid)
        self._energy_form = fem.form(strain_energy(self.mat_ufl, self.u) * self.dx)
        self._kinetic_form = fem.form(0.5 * self.rho * ufl.inner(self.v_n, self.v_n) * self.dx)
        self._setup_topology()

        self.b = fem_petsc.create_vector(self.residual_form)
        self.A = fem_petsc.create_matrix(self.jacobian_form)
        self.du = fem.Function(V)
        self.ksp = direct_solver(domain.comm, self.A)
        self.time = 0.0

    # -- assembly pieces ---------------------------------------------------------------------
    def _integrator_parameters(self) -> tuple[float, float, float, float]:
        """(β, γ, αm, αf). Generalized-α (Chung & Hulbert 1993) from ρ∞:
        αm = (2ρ∞ − 1)/(ρ∞ + 1), αf = ρ∞/(ρ∞ + 1), γ = ½ − αm + αf, β = ¼ (1 − αm + αf)²;
        the balance is enforced at t_n+1−α: M a_(n+1−αm) + f_int,(n+1−αf) = f_ext,(n+1−αf)."""
        o = self.opt
        if o.integrator == "generalized_alpha" and self.inertia:
            r = o.rho_inf
            if not 0.0 <= r <= 1.0:
                raise ValueError(f"rho_inf = {r}: expected in [0, 1]")
            am, af = (2 * r - 1) / (r + 1), r / (r + 1)
            return 0.25 * (1 - am + af) ** 2, 0.5 - am + af, am, af
        return o.beta, o.gamma, 0.0, 0.0

    def _committed_stress(self, S_iso, S_vol):
        """Total S of a committed state from its elastic parts and the committed h_i [Pa]."""
        if not self.viscous:
            return S_iso + S_vol
        g_inf = 1.0 - sum(self._g)
        return S_vol + g_inf * S_iso + sum(g * h for g, h in zip(self._g, self.h_n))

    def _viscous_stress(self, S_iso, S_vol):
        """(S used in the residual for the current step, S of the committed state)."""
        if not self.viscous:
            return S_vol + S_iso, S_vol + S_iso
        W = fem.TensorFunctionSpace(self.domain, ("DG", 0))
        self._W = W
        self.h_n = [fem.Function(W) for _ in self.mat.prony]       # h_i at t_n [Pa]
        self.Siso_n = fem.Function(W)                               # S⁰_iso at t_n [Pa]
        self._decay = [fem.Constant(self.domain, PETSc.ScalarType(1.0)) for _ in self.mat.prony]
        self._coef = [fem.Constant(self.domain, PETSc.ScalarType(1.0)) for _ in self.mat.prony]
        self._g = [fem.Constant(self.domain, PETSc.ScalarType(t.g)) for t in self.mat.prony]   # ḡi
        g_inf = 1.0 - sum(self._g)
        h_trial = [d * h + c * (S_iso - self.Siso_n) for d, c, h in zip(self._decay, self._coef, self.h_n)]
        S_trial = S_vol + g_inf * S_iso + sum(g * h for g, h in zip(self._g, h_trial))
        S_committed = self._committed_stress(S_iso, S_vol)
        X = W.element.interpolation_points()
        self._h_trial_expr = [fem.Expression(h, X) for h in h_trial]
        self._Siso_expr = fem.Expression(S_iso, X)
        self._h_tmp = [fem.Function(W) for _ in self.mat.prony]
        F = self._F
        centroid = np.array([[0.25, 0.25, 0.25]])
        # viscous overstress Q_i = ḡi (S⁰_iso − h_i), pushed forward to Cauchy form [Pa]
        self._xi_expr = [fem.Expression(voigt(cauchy_from_pk2(F, g * (S_iso - h))), centroid)
                         for g, h in zip(self._g, self.h_n)]
        return S_trial, S_committed

    def _force_terms(self, v, stiffness_damping: bool = True):
        """Internal (+ Rayleigh damping at velocity v) − gravity forces, as a form in w.

        Stiffness-proportional damping βK K v is written as βK times the stress rate over the
        step, βK (P(F_n+1) − P(F_n)) / Δt : Grad w (= βK ∂P/∂F : Grad v to first order in Δt),
        which is cheap to assemble and dissipative.
        """
        w = self._w
        R = ufl.inner(self._P, ufl.grad(w)) * self.dx
        if v is not None:
            alpha_m, beta_k = self.opt.rayleigh
            if alpha_m:
                R += alpha_m * self.rho * ufl.inner(v, w) * self.dx
            if beta_k and stiffness_damping:
                F_n, S_iso_n, S_vol_n = pk2_split(self.mat_ufl, self.u_n)
                P_n = F_n * (S_iso_n + S_vol_n)
                P_el = self._F * (self._S_el)
                R += beta_k * ufl.inner((P_el - P_n) / self.dt, ufl.grad(w)) * self.dx
        if self.gravity:
            R -= self.rho * ufl.inner(ufl.as_vector(self.opt.gravity), w) * self.dx
        return R

    def _setup_topology(self) -> None:
        """Node coordinates, cells (node indices) and the cell-to-node averaging weights."""
        V = self.V
        self.nodes = V.tabulate_dof_coordinates()[:, :3].copy()             # (N, 3) [m]
        n_cells = self.domain.topology.index_map(3).size_local
        self.cells = V.dofmap.list.array.reshape(n_cells, -1).astype(np.int64)  # (T, nodes per cell)
        x = self.nodes[self.cells[:, :4]]                                    # (T, 4, 3)
        self.cell_volume = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0  # (T,) [m^3]
        weight = np.zeros(len(self.nodes))
        np.add.at(weight, self.cells.ravel(), np.repeat(self.cell_volume, self.cells.shape[1]))
        self._node_weight = weight
        self._cell_ids = np.arange(n_cells, dtype=np.int32)

    def node_average(self, cell_values: np.ndarray) -> np.ndarray:
        """Volume-average cell values (T, k) onto the nodes: (N, k)."""
        k = cell_values.shape[1]
        out = np.zeros((len(self.nodes), k))
        contrib = cell_values * self.cell_volume[:, None]
        for c in range(self.cells.shape[1]):
            np.add.at(out, self.cells[:, c], contrib)
        return out / self._node_weight[:, None]

    # -- boundary conditions and loads -----------------------------------------------------
    def clamp(self, node_ids) -> None:
        """Fix all displacement components at the given nodes (u = 0)."""
        dofs = np.asarray(node_ids, dtype=np.int32)
        self.bcs.append(fem.dirichletbc(np.zeros(3, dtype=PETSc.ScalarType), dofs, self.V))

    def prescribe(self, node_ids, component: int, value: float = 0.0) -> fem.Constant:
        """Prescribe one displacement component [m] at the nodes; returns the Constant to update."""
        c = fem.Constant(self.domain, PETSc.ScalarType(value))
        dofs = (3 * np.asarray(node_ids, dtype=np.int32) + component).astype(np.int32)
        self.bcs.append(fem.dirichletbc(c, dofs, self.V.sub(component)))
        return c

    def prescribe_field(self, node_ids) -> fem.Function:
        """Prescribe all displacement components at the nodes from a Function [m] (returned, to set)."""
        g = fem.Function(self.V)
        self.bcs.append(fem.dirichletbc(g, np.asarray(node_ids, dtype=np.int32)))
        return g

    def set_nodal_force(self, force: np.ndarray) -> None:
        """External nodal forces (N, 3) [N]."""
        self.f_ext.x.array[:] = np.asarray(force, dtype=float).ravel()

    # -- Newton ----------------------------------------------------------------------------
    def _assemble_residual(self) -> float:
        b = self.b
        with b.localForm() as loc:
            loc.set(0.0)
        fem_petsc.assemble_vector(b, self.residual_form)
        b.axpy(-(1.0 - self.alpha_f), self.f_ext.vector)
        if self.alpha_f:
            b.axpy(-self.alpha_f, self.f_n.vector)
        fem_petsc.apply_lifting(b, [self.jacobian_form], bcs=[self.bcs], x0=[self.u.vector], scale=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem_petsc.set_bc(b, self.bcs, self.u.vector, -1.0)
        return b.norm()

    def internal_force(self) -> np.ndarray:
        """Residual without boundary conditions, as (N, 3) [N]: reactions at constrained nodes."""
        b = fem_petsc.assemble_vector(self.residual_form)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        out = b.array.copy().reshape(-1, 3)
        b.destroy()
        return out

    def _back_track(self, fraction: float) -> float:
        """Move u back towards where the last Newton update started by ``fraction`` of that update
        (``du`` holds the update as applied; a non-finite residual's line search calls this with
        1/2, 1/4, ..., so that u stands at 1/2, 1/4, ... of the update) and return the residual
        norm [N] there. (Before session 88 u moved on along the update instead, so a non-finite
        residual always failed the attempt and the step was cut.)"""
        self.u.vector.axpy(-fraction, self.du.vector)
        self.u.x.scatter_forward()
        return self._assemble_residual()

    def newton(self) -> StepReport:
        """Solve R(u) = 0 from the current u; u is left at the last iterate."""
        o = self.opt
        norm0 = None
        for it in range(o.max_iterations + 1):
            norm = self._assemble_residual()
            halvings = 0
            while not math.isfinite(norm) and it > 0 and halvings < o.line_search_halvings:
                norm = self._back_track(0.5 ** (halvings + 1))
                halvings += 1
            if not math.isfinite(norm):
                return StepReport(False, f"non-finite residual at Newton iteration {it} (J <= 0?)", it)
            if norm0 is None:
                norm0 = norm
            if norm <= max(o.atol, o.rtol * norm0):
                return StepReport(True, "", it)
            if it == o.max_iterations:
                break
            self.A.zeroEntries()
            fem_petsc.assemble_matrix(self.A, self.jacobian_form, bcs=self.bcs)
            self.A.assemble()
            try:
                self.ksp.solve(self.b, self.du.vector)
            except PETSc.Error as exc:  # e.g. MUMPS: singular tangent
                return StepReport(False, f"LU solve failed at Newton iteration {it} (PETSc error {exc.ierr})", it)
            self.du.x.scatter_forward()
            if self.ksp.getConvergedReason() < 0:
                return StepReport(False, f"LU solve failed at Newton iteration {it} "
                                         f"(KSP reason {self.ksp.getConvergedReason()})", it)
            if not np.all(np.isfinite(self.du.x.array)):
                return StepReport(False, f"non-finite Newton update at iteration {it}", it)
            self.u.vector.axpy(-1.0, self.du.vector)
            self.u.x.scatter_forward()
            self.du.x.array[:] *= -1.0  # store the applied direction for the line search
            if np.max(np.abs(self.du.x.array)) <= 1e-14 * (1.0 + np.max(np.abs(self.u.x.array))):
                return StepReport(True, "", it + 1)  # stagnated at round-off
        return StepReport(False, f"Newton did not converge in {o.max_iterations} iterations "
                                 f"(|R| = {norm:.3e} N, |R0| = {norm0:.3e} N)", o.max_iterations)

    # -- time stepping ---------------------------------------------------------------------
    def _set_dt(self, dt: float) -> None:
        self.dt.value = dt
        if self.viscous:
            for t, d, c in zip(self.mat.prony, self._decay, self._coef):
                x = dt / t.tau
                d.value = math.exp(-x)
                c.value = (-math.expm1(-x)) / x

    def _predict(self, dt: float) -> None:
        self.u.x.array[:] = self.u_n.x.array
        if self.inertia:
            self.u.x.array[:] += dt * self.v_n.x.array

    def _commit(self, dt: float) -> None:
        if self.inertia:
            b, g = self.beta, self.gamma
            a_new = ((self.u.x.array - self.u_n.x.array - dt * self.v_n.x.array) / (b * dt**2)
                     - (1.0 / (2 * b) - 1.0) * self.a_n.x.array)
            self.v_n.x.array[:] += dt * ((1 - g) * self.a_n.x.array + g * a_new)
            self.a_n.x.array[:] = a_new
        if self.viscous:
            for tmp, expr in zip(self._h_tmp, self._h_trial_expr):
                tmp.interpolate(expr)
            self.Siso_n.interpolate(self._Siso_expr)
            for h, tmp in zip(self.h_n, self._h_tmp):
                h.x.array[:] = tmp.x.array
        self.u_n.x.array[:] = self.u.x.array
        self.f_n.x.array[:] = self.f_ext.x.array
        self.time += dt

    def step(self, dt: float, set_loads=None) -> StepReport:
        """Advance by dt [s]. ``set_loads(t)`` sets f_ext and Dirichlet values for time t.

        A failed attempt is retried as two half steps, recursively, down to the floor
        ``min_step_fraction * dt``; on failure the state stays at the last converged sub-step.
        """
        floor = self.opt.min_step_fraction * dt * (1 - 1e-9)
        report = StepReport(True)

        def attempt(h: float, t_end: float) -> bool:
            if set_loads is not None:
                set_loads(t_end)
            self._set_dt(h)
            self._predict(h)
            r = self.newton()
            report.iterations += r.iterations
            if r.ok:
                self._commit(h)
                return True
            report.reason = r.reason
            self.u.x.array[:] = self.u_n.x.array
            if h / 2 < floor:
                return False
            report.cuts += 1
            t0 = t_end - h
            return attempt(h / 2, t0 + h / 2) and attempt(h / 2, t_end)

        report.ok = attempt(dt, self.time + dt)
        if report.ok:
            report.reason = ""
        else:
            report.reason = f"step to t = {self.time + dt:.4g} s failed below the cut floor: {report.reason}"
        return report

    def initial_acceleration(self) -> None:
        """a0 from M a0 = f_ext + ρ g − f_int(u0) (needed when the initial state is not at rest)."""
        self.f_n.x.array[:] = self.f_ext.x.array
        if not self.inertia:
            return
        if not hasattr(self, "_mass_ksp"):  # built once: mass matrix (LU) and the force form
            w, du = ufl.TestFunction(self.V), ufl.TrialFunction(self.V)
            M = fem_petsc.assemble_matrix(fem.form(self.rho * ufl.inner(du, w) * self.dx), bcs=self.bcs)
            M.assemble()
            self._mass_ksp = direct_solver(self.domain.comm, M)
            self._force_form = fem.form(self._force_terms(self.v_n, stiffness_damping=False))
        # forces at the current state (u = u_n, v = v_n)
        self.u.x.array[:] = self.u_n.x.array
        self._set_dt(1.0)
        b = fem_petsc.assemble_vector(self._force_form)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        b.axpy(-1.0, self.f_ext.vector)
        b.scale(-1.0)
        fem_petsc.set_bc(b, self.bcs, scale=0.0)
        self._mass_ksp.solve(b, self.a_n.vector)
        self.a_n.x.scatter_forward()
        b.destroy()

    def reset(self) -> None:
        """Back to the undeformed state at rest, t = 0 (boundary conditions kept)."""
        fields = [self.u, self.u_n, self.v_n, self.a_n, self.f_ext, self.f_n]
        if self.viscous:
            fields += [self.Siso_n, *self.h_n]
        for f in fields:
            f.x.array[:] = 0.0
        self.time = 0.0

    # -- outputs ---------------------------------------------------------------------------
    def cauchy_stress_nodes(self) -> np.ndarray:
        """Cauchy stress per node (N, 6) [Pa], Voigt 11 22 33 12 13 23, volume-averaged."""
        return self.node_average(self._sigma_expr.eval(self._cell_ids))

    def cauchy_stress_cells(self) -> np.ndarray:
        """Cauchy stress at each cell centroid (T, 6) [Pa]."""
        return self._sigma_expr.eval(self._cell_ids)

    def pk2_stress_nodes(self) -> np.ndarray:
        """2nd Piola–Kirchhoff stress per node (N, 6) [Pa], Voigt 11 22 33 12 13 23, volume-averaged."""
        return self.node_average(self._pk2_expr.eval(self._cell_ids))

    def pk2_stress_cells(self) -> np.ndarray:
        """2nd Piola–Kirchhoff stress at each cell centroid (T, 6) [Pa]."""
        return self._pk2_expr.eval(self._cell_ids)

    def viscous_overstress_nodes(self) -> list[np.ndarray]:
        """Per Prony term, the Cauchy push-forward of Q_i = ḡi (S⁰_iso − h_i) per node (N, 6) [Pa]."""
        if not self.viscous:
            return []
        return [self.node_average(e.eval(self._cell_ids)) for e in self._xi_expr]

    def displacement(self) -> np.ndarray:
        return self.u_n.x.array.reshape(-1, 3).copy()      # (N, 3) [m]

    def velocity(self) -> np.ndarray:
        return self.v_n.x.array.reshape(-1, 3).copy()      # (N, 3) [m/s]

    def strain_energy(self) -> float:
        """∫ Ψ dX at the current iterate u [J]."""
        return float(fem.assemble_scalar(self._energy_form))

    def kinetic_energy(self) -> float:
        """∫ ½ ρ v·v dX of the committed velocity [J]."""
        return float(fem.assemble_scalar(self._kinetic_form))
