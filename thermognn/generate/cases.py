"""Verification cases of the FE core with known answers (used by tests/test_fe_*.py and benchmarks/fe_*.py).

Each case builds a small problem, solves it with :class:`thermognn.generate.solid.Solid` and
returns the FE figures next to the reference ones. Units SI.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .materials import Material, principal_cauchy_closed_form
from .solid import Solid, SolverOptions


def box_mesh(lengths=(1.0, 1.0, 1.0), cells=(2, 2, 2), origin=(0.0, 0.0, 0.0)):
    """Structured tetrahedral box (dolfinx built-in, 6 tets per hexahedron)."""
    from dolfinx import mesh as dmesh
    from mpi4py import MPI

    o = np.asarray(origin, dtype=float)
    return dmesh.create_box(MPI.COMM_SELF, [o, o + np.asarray(lengths, dtype=float)], list(cells),
                            dmesh.CellType.tetrahedron)


def nodes_where(solid: Solid, mask_fn) -> np.ndarray:
    """Node indices whose reference coordinates satisfy mask_fn(x (N,3)) -> bool (N,)."""
    return np.flatnonzero(mask_fn(solid.nodes)).astype(np.int32)


# -- homogeneous uniaxial stress ------------------------------------------------------------


@dataclass
class UniaxialResult:
    stretch: float
    lateral_fe: float
    lateral_exact: float
    sigma11_fe: float
    sigma11_exact: float
    max_lateral_stress: float          # max |σ22|, |σ33|, |shear| over cells [Pa]
    sigma_spread: float                # max deviation of σ11 between cells [Pa]
    S11_fe: float = 0.0                # 2nd Piola–Kirchhoff S11 (cell mean) [Pa]
    S11_exact: float = 0.0             # J σ11 / λ² [Pa]

    @property
    def rel_error(self) -> float:
        return abs(self.sigma11_fe - self.sigma11_exact) / abs(self.sigma11_exact)


def lateral_stretch_exact(mat: Material, stretch: float) -> float:
    """λt with σ22 = σ33 = 0 for F = diag(λ, λt, λt) (bisection on the closed form)."""
    f = lambda lt: principal_cauchy_closed_form(mat, [stretch, lt, lt])[1]
    lo, hi = 0.2, 3.0
    flo = f(lo)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        fm = f(mid)
        if (fm > 0) == (flo > 0):
            lo, flo = mid, fm
        else:
            hi = mid
    return 0.5 * (lo + hi)


def uniaxial(mat: Material, stretch: float, n_steps: int = 5, cells=(2, 2, 2),
             quadrature_degree: int = 2) -> UniaxialResult:
    """Unit cube, symmetry rollers on x=0, y=0, z=0, face x=1 displaced to x=λ, the rest free.

    The exact solution is homogeneous, F = diag(λ, λt, λt), which P1 tets represent exactly.
    """
    domain = box_mesh(cells=cells)
    s = Solid(domain, mat, ("elastic",), SolverOptions(integrator="quasi_static",
                                                       quadrature_degree=quadrature_degree,
                                                       rtol=1e-12, atol=1e-9))
    tol = 1e-10
    for c in range(3):
        s.prescribe(nodes_where(s, lambda x, c=c: np.abs(x[:, c]) < tol), c, 0.0)
    pull = s.prescribe(nodes_where(s, lambda x: np.abs(x[:, 0] - 1.0) < tol), 0, 0.0)
    for k in range(1, n_steps + 1):
        r = s.step(1.0, lambda t, k=k: setattr(pull, "value", (stretch - 1.0) * k / n_steps))
        if not r.ok:
            raise RuntimeError(r.reason)
    sig = s.cauchy_stress_cells()                       # (T, 6)
    u = s.displacement()
    corner = nodes_where(s, lambda x: np.all(np.abs(x - 1.0) < tol, axis=1))[0]
    lt_fe = 1.0 + u[corner, 1]
    lt = lateral_stretch_exact(mat, stretch)
    exact = principal_cauchy_closed_form(mat, [stretch, lt, lt])[0]
    S = s.pk2_stress_cells()
    J = stretch * lt**2
    return UniaxialResult(stretch, lt_fe, lt, float(sig[:, 0].mean()), float(exact),
                          float(np.abs(sig[:, 1:]).max()), float(np.ptp(sig[:, 0])),
                          float(S[:, 0].mean()), float(J * exact / stretch**2))


def homogeneous_stress(mat: Material, stretches, n_steps: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Cauchy stress (T, 6) [Pa] of a unit cube with u = (F − I) X prescribed on its whole boundary,
    F = diag(stretches), next to the closed-form principal stresses (3,)."""
    s = Solid(box_mesh(cells=(1, 1, 1)), mat, ("elastic",),
              SolverOptions(integrator="quasi_static", rtol=1e-12, atol=1e-9))
    bnd = nodes_where(s, lambda x: np.any((np.abs(x) < 1e-10) | (np.abs(x - 1) < 1e-10), axis=1))
    g = s.prescribe_field(bnd)
    gx = g.x.array.reshape(-1, 3)                   # view: (N, 3)
    lam = np.asarray(stretches, dtype=float)
    for k in range(1, n_steps + 1):
        gx[bnd] = (k / n_steps) * (lam - 1.0) * s.nodes[bnd]
        r = s.step(1.0)
        if not r.ok:
            raise RuntimeError(r.reason)
    return s.cauchy_stress_cells(), principal_cauchy_closed_form(mat, lam)


# -- Prony relaxation ------------------------------------------------------------------------


def relaxation(mat: Material, stretch: float = 1.1, dt: float = 0.005, t_end: float | None = None):
    """Step stretch (applied in the first step dt, then held) of a unit cube, F = diag(λ, 1, 1)
    prescribed everywhere on the boundary; returns times [s], deviatoric σ11 − σ22 [Pa] per step
    (the volumetric part does not relax) and the Prony g_R(t)."""
    tau_max = max(t.tau for t in mat.prony)
    t_end = t_end if t_end is not None else 5.0 * tau_max
    domain = box_mesh(cells=(1, 1, 1))
    s = Solid(domain, mat, ("elastic", "viscous"), SolverOptions(integrator="quasi_static", rtol=1e-12, atol=1e-9))
    bnd = nodes_where(s, lambda x: np.any((np.abs(x) < 1e-10) | (np.abs(x - 1) < 1e-10), axis=1))
    g = s.prescribe_field(bnd)                        # u = ((λ − 1) X, 0, 0) on the boundary
    g.x.array.reshape(-1, 3)[bnd, 0] = (stretch - 1.0) * s.nodes[bnd, 0]
    times, dev = [0.0], [0.0]
    n = int(round(t_end / dt))
    for k in range(1, n + 1):
        r = s.step(dt)
        if not r.ok:
            raise RuntimeError(r.reason)
        sig = s.cauchy_stress_cells()
        times.append(k * dt)
        dev.append(float(np.mean(sig[:, 0] - sig[:, 1])))
    times = np.asarray(times)
    g_R = 1.0 - sum(t.g * (1.0 - np.exp(-times / t.tau)) for t in mat.prony)
    return times, np.asarray(dev), g_R


# -- cantilever ------------------------------------------------------------------------------


@dataclass
class CantileverResult:
    n_nodes: int
    tip_fe: float
    tip_exact: float
    seconds: float

    @property
    def rel_error(self) -> float:
        return abs(self.tip_fe - self.tip_exact) / abs(self.tip_exact)


def cantilever(n_length: int = 20, n_section: int = 2, degree: int = 2, length: float = 1.0,
               height: float = 0.05, load: float = None) -> CantileverResult:
    """Clamped-free beam (square section h x h) under a small tip shear; Euler–Bernoulli
    δ = P L³ / (3 E I). Neo-Hookean with ν = 0 (K = 2μ/3) so the clamp adds no Poisson
    stiffening; E = 2μ. Load is a uniform traction on the tip face (as nodal forces of the
    consistent face load), small enough that δ/L ~ 1e-4."""
    t0 = time.perf_counter()
    mu = 1.0e6
    mat = Material("neo_hookean", {"C10": mu / 2.0, "D1": 2.0 / (2.0 * mu / 3.0)}, density=1000.0)
    E = 2.0 * mu
    I = height**4 / 12.0
    P = load if load is not None else 3.0 * E * I / length**3 * 1e-4 * length
    domain = box_mesh((length, height, height), (n_length, n_section, n_section))
    s = Solid(domain, mat, ("elastic",), SolverOptions(degree=degree, quadrature_degree=2 * degree,
                                                       integrator="quasi_static", rtol=1e-10, atol=1e-12))
    s.clamp(nodes_where(s, lambda x: x[:, 0] < 1e-10))
    # consistent nodal forces of a uniform traction −P/h² e_z on the tip face
    import ufl
    from dolfinx import fem
    from dolfinx.mesh import locate_entities_boundary, meshtags
    facets = locate_entities_boundary(domain, 2, lambda x: np.isclose(x[0], length))
    tags = meshtags(domain, 2, facets, np.ones(len(facets), dtype=np.int32))
    ds = ufl.Measure("ds", domain=domain, subdomain_data=tags, metadata={"quadrature_degree": 2 * degree})
    w = ufl.TestFunction(s.V)
    trac = fem.Constant(domain, np.array([0.0, 0.0, -P / height**2]))
    f = fem.petsc.assemble_vector(fem.form(ufl.inner(trac, w) * ds(1)))
    force = f.array.copy().reshape(-1, 3)
    r = s.step(1.0, lambda t: s.set_nodal_force(force))
    if not r.ok:
        raise RuntimeError(r.reason)
    tip = nodes_where(s, lambda x: np.isclose(x[:, 0], length))
    delta = -float(s.displacement()[tip, 2].mean())
    return CantileverResult(len(s.nodes), delta, P * length**3 / (3 * E * I), time.perf_counter() - t0)


# -- energy conservation ---------------------------------------------------------------------


def energy_history(n_steps: int = 200, dt: float = 2e-3, cells=(2, 2, 4), v0: float = 0.05,
                   rayleigh=(0.0, 0.0), integrator: str = "newmark", rho_inf: float = 1.0) -> np.ndarray:
    """Block 0.02 x 0.02 x 0.04 m clamped at z = 0, released with a bending velocity
    v_x = v0 z/Lz and no load; trapezoidal Newmark by default. Returns total energy (kinetic + strain) [J] per step."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}, density=1000.0)
    domain = box_mesh((0.02, 0.02, 0.04), cells)
    s = Solid(domain, mat, ("elastic", "inertia"), SolverOptions(integrator=integrator, rho_inf=rho_inf,
                                                                 rayleigh=tuple(rayleigh), rtol=1e-11, atol=1e-13))
    s.clamp(nodes_where(s, lambda x: x[:, 2] < 1e-10))
    v = s.v_n.x.array.reshape(-1, 3)
    v[:, 0] = v0 * s.nodes[:, 2] / 0.04
    v[s.nodes[:, 2] < 1e-10] = 0.0
    s.initial_acceleration()
    energy = [s.kinetic_energy() + s.strain_energy()]
    for _ in range(n_steps):
        r = s.step(dt)
        if not r.ok:
            raise RuntimeError(r.reason)
        energy.append(s.kinetic_energy() + s.strain_energy())
    return np.asarray(energy)


# -- snap-through ----------------------------------------------------------------------------


@dataclass
class SnapThroughPath:
    """Displacement-controlled load–displacement path of the shallow arch (downward positive)."""

    displacement: np.ndarray = field(default_factory=lambda: np.zeros(0))   # apex deflection [m]
    force: np.ndarray = field(default_factory=lambda: np.zeros(0))          # reaction [N]
    ok: bool = True
    reason: str = ""


def shallow_arch_mesh(span: float = 0.2, width: float = 0.01, rise: float = 0.02, thickness: float = 0.005,
                      cell_size: float = 0.006):
    """Points and tets of the clamped shallow cylindrical cap meshes/shell.geo."""
    from thermognn.core.config import project_path
    from .meshing import gmsh_geo_to_arrays

    return gmsh_geo_to_arrays(project_path("meshes/shell.geo"),
                              dict(L=span, W=width, H=rise, t=thickness, h=cell_size))


def _arch_solid(degree, span, width, rise, thickness, cell_size, mu, nu):
    """Quasi-static solid on the shallow arch with both end faces clamped; returns (solid, crown nodes)."""
    from .meshing import to_dolfinx

    points, tets = shallow_arch_mesh(span, width, rise, thickness, cell_size)
    K = 2.0 * mu * (1 + nu) / (3 * (1 - 2 * nu))
    mat = Material("neo_hookean", {"C10": mu / 2.0, "D1": 2.0 / K}, density=1000.0)
    s = Solid(to_dolfinx(points, tets), mat, ("elastic",),
              SolverOptions(degree=degree, quadrature_degree=2 * degree, integrator="quasi_static",
                            rtol=1e-9, atol=1e-9, min_step_fraction=1 / 64))
    s.clamp(nodes_where(s, lambda x: np.abs(np.abs(x[:, 0]) - span / 2) < 1e-8))
    R = (span**2 / 4 + rise**2) / (2 * rise)
    z_top = lambda x: np.sqrt(np.maximum((R + thickness / 2) ** 2 - x**2, 0)) + rise - R
    crown = nodes_where(s, lambda x: (np.abs(x[:, 0]) <= cell_size / 2) & (np.abs(x[:, 2] - z_top(x[:, 0])) < 1e-6))
    if len(crown) == 0:
        raise RuntimeError("no crown nodes found")
    return s, crown


def snap_through(n_steps: int = 30, max_deflection_factor: float = 2.2, degree: int = 2,
                 span: float = 0.2, width: float = 0.01, rise: float = 0.02, thickness: float = 0.005,
                 cell_size: float = 0.006, mu: float = 1.0e6, nu: float = 0.3) -> SnapThroughPath:
    """Clamped shallow arch (both end faces fixed) pushed down at its crown by displacement control.

    The crown line (nodes within cell_size/2 of x = 0 on the top surface, across the width) gets a
    prescribed vertical displacement −w, w = 0 … factor · rise in n_steps; the reaction there is
    the load. Displacement control passes the limit point (the load drops while w grows), which
    load control would have to jump. P2 tetrahedra (bending without locking).
    """
    s, crown = _arch_solid(degree, span, width, rise, thickness, cell_size, mu, nu)
    w_bc = s.prescribe(crown, 2, 0.0)
    path = SnapThroughPath()
    ws, fs = [0.0], [0.0]
    w_max = max_deflection_factor * rise
    for k in range(1, n_steps + 1):
        target = -w_max * k / n_steps
        start = float(w_bc.value)
        r = s.step(1.0, lambda t, a=start, b=target, t0=s.time: setattr(w_bc, "value", a + (b - a) * (t - t0)))
        if not r.ok:
            path.ok, path.reason = False, r.reason
            break
        reaction = -float(s.internal_force()[crown, 2].sum())   # force pushing the crown down [N]
        ws.append(-target)
        fs.append(reaction)
    path.displacement, path.force = np.asarray(ws), np.asarray(fs)
    return path


def snap_through_arc_length(n_increments: int = 40, ds: float = 0.004, max_deflection_factor: float = 2.0,
                            degree: int = 2, span: float = 0.2, width: float = 0.01, rise: float = 0.02,
                            thickness: float = 0.005, cell_size: float = 0.006, mu: float = 1.0e6,
                            nu: float = 0.3) -> SnapThroughPath:
    """The same arch under a crown line load (load control) traced by arc-length continuation:
    force = λ × 1 N shared equally by the crown nodes, displacement = mean crown deflection [m]."""
    from .continuation import arc_length

    s, crown = _arch_solid(degree, span, width, rise, thickness, cell_size, mu, nu)
    f_hat = np.zeros_like(s.nodes)
    f_hat[crown, 2] = -1.0 / len(crown)
    path = arc_length(s, f_hat, lambda u: -float(u[crown, 2].mean()), ds=ds, n_increments=n_increments,
                      max_displacement=max_deflection_factor * rise)
    return SnapThroughPath(np.asarray(path.displacement), np.asarray(path.load_factor), path.ok, path.reason)
