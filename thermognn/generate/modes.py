"""Does a dataset's time step resolve the solid's vibration modes? (linearised FE at rest; SI units)

Linearised about the undeformed rest state, the discrete solid obeys

    M ü + C u̇ + K u = f(t),   K = ∂f_int/∂u at u = 0 [N/m],   M = ∫ ρ N_i N_j dX [kg],

with the free-vibration modes K φ_k = ω_k² M φ_k, φ_kᵀ M φ_l = δ_kl (ω in rad/s). A mode with
ω dt > 2 (:data:`UNRESOLVED`) lies beyond the stability limit of any explicit step of size dt:
the data's implicit step follows it quasi-statically, its load and elastic force nearly cancel,
and an explicit learned step would have to produce that tiny remainder. Datasets whose strain
energy sits mostly in such modes are hard to learn; :func:`diagnose` measures this for
``generate``, which prints it and stores it as the dataset's ``time_resolution`` root attribute.

DOFs are node-blocked (node i, component c at 3 i + c, nodes in the order of ``solid.nodes``);
``free`` masks the DOFs that the solid's Dirichlet conditions leave free, and K, M are restricted
to them. :func:`rest_operators` gives dense arrays (meshes up to ~2,000 nodes: 16 n² bytes per
matrix for n DOFs) or, with ``sparse=True``, scipy CSR matrices. :func:`modal_basis` and
:func:`natural_frequencies` are dense and complete (O(n³): about 5 s for n = 1,500 on two cores,
minutes for 5,000); :func:`lowest_modes`, :func:`highest_frequency` and :func:`energy_shares`
take either kind, :func:`linear_rollout_error` the :func:`linear_solid` (sparse), and :func:`diagnose` (what ``generate`` runs) uses
sparse matrices and only the resolved modes, which gives the same figures in seconds; it is
skipped above :data:`MAX_DENSE_DOFS` free DOFs all the same.
"""

from __future__ import annotations

import time
from typing import Iterable

import numpy as np

from thermognn.core.linear import INTEGRATORS as LINEAR_INTEGRATORS
from thermognn.core.linear import LinearSolid, free_rows

#: ω dt above which a mode is unresolved (beyond the explicit, central-difference stability limit)
UNRESOLVED = 2.0
#: the diagnostic in ``generate`` is skipped above this many free DOFs
MAX_DENSE_DOFS = 6000


def _is_sparse(A) -> bool:
    import scipy.sparse as sp

    return sp.issparse(A)


# -- operators at rest --------------------------------------------------------------------------


def _assemble(form, sparse: bool):
    """Assemble a bilinear form (no boundary conditions): scipy CSR or dense array [n, n]."""
    import scipy.sparse as sp
    from dolfinx import fem
    from dolfinx.fem import petsc as fem_petsc

    A = fem_petsc.assemble_matrix(fem.form(form))
    A.assemble()
    try:
        indptr, indices, data = A.getValuesCSR()
        out = sp.csr_matrix((data.copy(), indices.copy(), indptr.copy()), shape=A.getSize())
    finally:
        A.destroy()
    return out if sparse else out.toarray()


def constrained_dofs(solid) -> np.ndarray:
    """Boolean mask [3N] of the DOFs held by the solid's Dirichlet conditions (``solid.bcs``)."""
    fixed = np.zeros(solid.u.x.array.size, dtype=bool)
    for bc in solid.bcs:
        dofs, n_owned = bc.dof_indices()          # unrolled (blocked) DOF indices, owned first
        fixed[np.asarray(dofs[:n_owned], dtype=np.int64)] = True
    return fixed


def rest_operators(solid, sparse: bool = False):
    """The solid's stiffness and mass at rest over its free DOFs: (K [N/m], M [kg], free).

    K is the tangent ∂f_int/∂u at u = 0 of the solid's *own* elastic internal force
    f_int = ∫ P : Grad w dX, P = F S_el(F) (S_el: the law's isochoric + volumetric 2nd
    Piola–Kirchhoff stress, the instantaneous elastic response, without Prony relaxation,
    Rayleigh damping or the generalized-α blend), so it holds for every material law. M is the
    consistent mass ∫ ρ δu·w dX. Both use ``solid.dx`` (explicit quadrature degree). ``solid.u``
    is zeroed for the assembly and restored afterwards.

    Returns K [n, n], M [n, n] (n = free.sum(), symmetric; dense arrays, or scipy CSR matrices
    with ``sparse``) and ``free`` [3N] bool.
    """
    import ufl

    w = ufl.TestFunction(solid.V)
    du = ufl.TrialFunction(solid.V)
    mass = solid.rho * ufl.inner(du, w) * solid.dx
    M = _assemble(mass, sparse=True)               # [3N, 3N]
    free = ~constrained_dofs(solid)                # [3N]
    idx = np.flatnonzero(free)
    K = rest_stiffness(solid, solid._S_el)[idx][:, idx]       # elastic 2nd Piola stress of solid.u [Pa]
    M = M[idx][:, idx]
    return (K.tocsr(), M.tocsr(), free) if sparse else (K.toarray(), M.toarray(), free)


def rest_stiffness(solid, S):
    """∂/∂u ∫ F S : Grad w dX at u = 0 [N/m] (scipy CSR over all 3N DOFs, symmetrised) for a 2nd
    Piola–Kirchhoff stress S [Pa] written in ``solid.u`` (the law's whole elastic stress, or a
    part of it). ``solid.u`` is zeroed for the assembly and restored afterwards."""
    import ufl

    w, du = ufl.TestFunction(solid.V), ufl.TrialFunction(solid.V)
    form = ufl.derivative(ufl.inner(solid._F * S, ufl.grad(w)) * solid.dx, solid.u, du)
    saved = solid.u.x.array.copy()
    try:
        solid.u.x.array[:] = 0.0
        K = _assemble(form, sparse=True)           # [3N, 3N]
    finally:
        solid.u.x.array[:] = saved
    return (0.5 * (K + K.T)).tocsr()               # symmetric up to round-off already


# -- modes ------------------------------------------------------------------------------------


def modal_basis(K: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All modes, dense: (ω [n] rad/s ascending, Φ [n, n]) with K Φ = M Φ diag(ω²), Φᵀ M Φ = I
    (negative round-off eigenvalues, e.g. rigid modes of an unclamped body, give ω = 0)."""
    import scipy.linalg as sl

    w2, phi = sl.eigh(K, M)
    return np.sqrt(np.maximum(w2, 0.0)), phi


def natural_frequencies(K: np.ndarray, M: np.ndarray) -> np.ndarray:
    """All natural angular frequencies ω [rad/s] of K φ = ω² M φ, ascending [n] (dense)."""
    import scipy.linalg as sl

    return np.sqrt(np.maximum(sl.eigh(K, M, eigvals_only=True), 0.0))


def lowest_modes(K, M, omega_limit: float, dense_fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """The modes with ω ≤ ``omega_limit`` [rad/s] and always the lowest one: (ω [m] ascending,
    Φ [n, m], Φᵀ M Φ = I). Dense K, M: LAPACK on that subset. Sparse: shift-invert Lanczos
    (ARPACK) below the spectrum, doubling the number of modes until one exceeds the limit, then
    a Rayleigh–Ritz step on them; dense instead once more than ``dense_fraction`` n are needed
    (or when ARPACK does not converge)."""
    import scipy.linalg as sl

    n = K.shape[0]
    lam_limit = float(omega_limit) ** 2
    if not _is_sparse(K) or n < 50:
        Kd = K.toarray() if _is_sparse(K) else K
        Md = M.toarray() if _is_sparse(M) else M
        w2, phi = sl.eigh(Kd, Md, subset_by_value=(-np.inf, lam_limit))
        if w2.size == 0:
            w2, phi = sl.eigh(Kd, Md, subset_by_index=(0, 0))
        return np.sqrt(np.maximum(w2, 0.0)), phi
    import scipy.sparse.linalg as sla

    Kc, Mc = K.tocsc(), M.tocsc()
    sigma = -0.01 * lam_limit               # below the spectrum: K − σM is SPD even if K is singular
    lu = sla.splu((Kc - sigma * Mc).tocsc())
    opinv = sla.LinearOperator((n, n), matvec=lu.solve, dtype=float)
    k = min(12, n - 2)
    while True:
        try:
            w2, phi = sla.eigsh(Kc, k=k, M=Mc, sigma=sigma, which="LM", OPinv=opinv)
        except sla.ArpackNoConvergence:
            return lowest_modes(K.toarray(), M.toarray(), omega_limit)
        if w2.max() > lam_limit or k >= n - 2:
            break
        if 2 * k > dense_fraction * n:
            return lowest_modes(K.toarray(), M.toarray(), omega_limit)
        k = min(2 * k, n - 2)
    # Rayleigh–Ritz on the Lanczos vectors: M-orthonormal, clusters included
    w2, c = sl.eigh(phi.T @ (K @ phi), phi.T @ (M @ phi))
    phi = phi @ c
    keep = w2 <= lam_limit
    keep[0] = True
    return np.sqrt(np.maximum(w2[keep], 0.0)), phi[:, keep]


def highest_frequency(K, M) -> float:
    """ω_max [rad/s], the largest natural frequency (dense: LAPACK; sparse: Lanczos, to 1e-6,
    dense if it does not converge)."""
    import scipy.linalg as sl

    n = K.shape[0]
    if _is_sparse(K) and n >= 50:
        import scipy.sparse.linalg as sla

        lu = sla.splu(M.tocsc())
        minv = sla.LinearOperator((n, n), matvec=lu.solve, dtype=float)
        try:
            w2 = sla.eigsh(K.tocsc(), k=1, M=M.tocsc(), Minv=minv, which="LA", tol=1e-6,
                           return_eigenvectors=False)
            return float(np.sqrt(max(w2[0], 0.0)))
        except sla.ArpackNoConvergence:
            pass
    Kd = K.toarray() if _is_sparse(K) else K
    Md = M.toarray() if _is_sparse(M) else M
    return float(np.sqrt(max(sl.eigh(Kd, Md, subset_by_index=(n - 1, n - 1), eigvals_only=True)[0], 0.0)))


def resolution(omega: np.ndarray, dt: float, *, modes: int | None = None,
               omega_max: float | None = None) -> dict:
    """How many modes a step dt [s] resolves: ω_1 dt, ω_max dt, number of modes, and how many
    have ω dt > :data:`UNRESOLVED` (= 2). ``omega`` [rad/s]: all frequencies, or only the
    lowest ones (every ω dt <= 2 among them), with ``modes`` the total count and ``omega_max``."""
    wdt = np.asarray(omega, dtype=float) * float(dt)
    n = int(wdt.size if modes is None else modes)
    top = float(wdt.max() if omega_max is None else omega_max * dt)
    return {"omega_1_dt": float(wdt.min()), "omega_max_dt": top, "modes": n,
            "unresolved": n - int(np.count_nonzero(wdt <= UNRESOLVED))}


# -- what the data put into those modes ---------------------------------------------------------


def energy_shares(K, M, free: np.ndarray, nodes: np.ndarray, trajectories: Iterable, layout,
                  dt: float, *, modes=None) -> dict:
    """Share of the data's strain and kinetic energy carried by the unresolved modes (ω dt > 2).

    trajectories: iterable of schema ``Trajectory`` (z [S, N, D]; q = z[..., 0:3] [m] and, when
    ``layout`` has it, v = z[..., layout.slice('v')] [m/s]); nodes: reference positions X [N, 3] [m].
    Each snapshot's u = q − X and v over the free DOFs are projected on the M-orthonormal modes,
    ξ = Φᵀ M u, η = Φᵀ M v; per mode the strain energy ω² ξ² / 2 and kinetic η² / 2 [J], summed
    over all snapshots and trajectories. Since the modes are complete, the sum over all of them
    is uᵀ K u / 2 and vᵀ M v / 2, so only the resolved modes (ω dt <= 2) are needed: the
    unresolved share is 1 − resolved / total. ``modes``: (ω, Φ) holding at least every resolved
    mode (others are ignored), e.g. from :func:`modal_basis`; default :func:`lowest_modes`.
    K, M dense or sparse.

    Returns ``strain_unresolved``, ``kinetic_unresolved`` (None without v) in [0, 1] and the
    resolved shares ``strain_resolved``, ``kinetic_resolved`` (0 where the data hold no energy).
    """
    omega, phi = modes if modes is not None else lowest_modes(K, M, UNRESOLVED / dt)
    lo = omega * dt <= UNRESOLVED                                  # [m] resolved modes
    omega, MPhi = omega[lo], np.asarray(M @ phi[:, lo])            # [r], [n, r]
    X = np.asarray(nodes, dtype=float)[None]                       # [1, N, 3]
    has_v = "v" in layout.names
    strain = kinetic = strain_lo = kinetic_lo = 0.0                # [J] summed over snapshots
    for traj in trajectories:
        z = np.asarray(traj.z)                                     # [S, N, D]
        U = free_rows(z[..., 0:3] - X, free)                      # [S, n] [m]
        strain += 0.5 * float(np.sum(U * np.asarray(K @ U.T).T))
        strain_lo += 0.5 * float(np.sum(omega**2 * (U @ MPhi) ** 2))
        if has_v:
            V = free_rows(z[..., layout.slice("v")], free)        # [S, n] [m/s]
            kinetic += 0.5 * float(np.sum(V * np.asarray(M @ V.T).T))
            kinetic_lo += 0.5 * float(np.sum((V @ MPhi) ** 2))

    def share(part, total):
        return float(np.clip(part / total, 0.0, 1.0)) if total > 0 else 0.0

    out = {"strain_unresolved": share(strain - strain_lo, strain), "strain_resolved": share(strain_lo, strain),
           "kinetic_unresolved": None, "kinetic_resolved": None}
    if has_v:
        out.update(kinetic_unresolved=share(kinetic - kinetic_lo, kinetic),
                   kinetic_resolved=share(kinetic_lo, kinetic))
    return out


def linear_stress(solid, free: np.ndarray, isochoric: bool = False):
    """Σ [6N, n] Pa/m (scipy CSR): the nodal Cauchy stress (Voigt 11 22 33 12 13 23, volume-averaged
    cell values as the dataset stores them, ``Solid.node_average``) of a small displacement of the
    n free DOFs, σ = λ tr(ε) I + 2 μ ε with ε = sym(Grad u) and the law's moduli at rest
    (μ = ``shear_modulus``, λ = K − 2μ/3; every isotropic hyperelastic law, and the unrelaxed
    Prony response, linearise to this at rest); with ``isochoric`` its isochoric part alone,
    2 μ dev ε (λ = −2μ/3), the part a Prony series relaxes. P1 tets only (None for higher
    degrees, whose nodes are not the cells' vertices alone)."""
    import scipy.sparse as sp

    cells = solid.cells
    if cells.shape[1] != 4:
        return None
    mu = solid.mat.shear_modulus
    lam = (0.0 if isochoric else solid.mat.bulk_modulus) - 2.0 * mu / 3.0
    x = solid.nodes[cells]                                          # [T, 4, 3]
    G = np.linalg.inv(x[:, 1:] - x[:, :1])                          # [T, 3, 3]: columns are grad phi_1..3
    grad = np.concatenate([-G.sum(2, keepdims=True), G], 2).transpose(0, 2, 1)   # [T, 4, 3] grad phi_a
    voigt = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    B = np.zeros((len(cells), 6, 4, 3))                             # d sigma_r / d u_(a, c) per cell
    for r, (i, j) in enumerate(voigt):
        for c in range(3):
            B[:, r, :, c] = (lam * grad[:, :, c] * (i == j) + mu * grad[:, :, j] * (c == i)
                             + mu * grad[:, :, i] * (c == j))
    weight = solid.cell_volume[:, None, None, None, None] / solid._node_weight[cells][:, :, None, None, None]  # [T, 4, 1, 1, 1]
    # every cell's stress goes, volume-weighted, to each of its 4 nodes: rows 6 node + r, cols 3 node' + c
    rows = (6 * cells[:, :, None, None, None] + np.arange(6)[None, None, :, None, None])
    cols = (3 * cells[:, None, None, :, None] + np.arange(3)[None, None, None, None, :])
    rows, cols, vals = np.broadcast_arrays(rows, cols, weight * B[:, None])    # [T, 4, 6, 4, 3] each
    n = len(solid.nodes)
    full = sp.coo_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(6 * n, 3 * n)).tocsr()
    return full[:, np.flatnonzero(free)]


def linear_solid(solid, sparse: bool = True) -> LinearSolid:
    """The solid linearised at rest (``thermognn.core.linear.LinearSolid``): K, M over the free
    DOFs (:func:`rest_operators`), the stress operator (:func:`linear_stress`), the solid's
    Rayleigh damping, Newmark β, γ and integrator ('quasi_static' without inertia), the
    gravity load (:func:`body_force`) over the free DOFs, the law's moduli at rest (μ0, K0: the
    corotated baseline's), and for a viscous solid its Prony terms
    with the isochoric parts of K and Σ they relax (:func:`rest_stiffness` of the law's
    isochoric stress)."""
    K, M, free = rest_operators(solid, sparse=sparse)
    opt = solid.opt
    gravity = body_force(solid)
    viscous = {}
    if solid.viscous:
        from .materials import pk2_split

        idx = np.flatnonzero(free)
        K_iso = rest_stiffness(solid, pk2_split(solid.mat_ufl, solid.u)[1])[idx][:, idx]
        viscous = {"prony": tuple((float(t.g), float(t.tau)) for t in solid.mat.prony),
                   "stiffness_iso": K_iso if sparse else K_iso.toarray(),
                   "stress_iso": linear_stress(solid, free, isochoric=True)}
    return LinearSolid(stiffness=K, mass=M, free=free, stress=linear_stress(solid, free),
                       rayleigh=tuple(float(r) for r in opt.rayleigh),
                       integrator=opt.integrator if solid.inertia else "quasi_static",
                       beta=float(opt.beta), gamma=float(opt.gamma),
                       body_force=None if gravity is None else gravity.ravel()[free],
                       shear_modulus=float(solid.mat.shear_modulus), bulk_modulus=float(solid.mat.bulk_modulus),
                       **viscous)


def linear_rollout_error(linear: LinearSolid, nodes: np.ndarray, trajectories: Iterable, layout,
                         dt: float) -> dict | None:
    """How far the linearised FE model is from the data: re-simulate each trajectory with it
    (:meth:`LinearSolid.rollout`: from each trajectory's own first state u_0 = q_0 − X, v_0,
    under its stored nodal forces, force[s] at t_s, with the data's own integrator applied to
    the linear system; generalized-α is not reproduced: None).

    Returns {"u": ||U_lin − U|| / ||U||, "v": same for the velocities (None for quasi-static)},
    norms over all snapshots and free DOFs of a trajectory at once, averaged over trajectories
    (those that never move are left out); None when there is nothing to compare."""
    if linear.integrator not in LINEAR_INTEGRATORS:
        return None
    dynamic = linear.integrator == "newmark"
    if dynamic and "v" not in layout.names:
        return None
    X = np.asarray(nodes, dtype=float)[None]                       # [1, N, 3]
    errs_u, errs_v = [], []
    for traj in trajectories:
        z = np.asarray(traj.z)                                     # [S, N, D]
        U = linear.free_rows(z[..., 0:3] - X)                      # [S, n] [m]
        V = linear.free_rows(z[..., layout.slice("v")]) if dynamic else None   # [S, n] [m/s]
        U_lin, V_lin = linear.rollout(U[0], None if V is None else V[0], linear.free_rows(traj.force), dt)
        nu = np.linalg.norm(U)
        if nu == 0:
            continue
        errs_u.append(np.linalg.norm(U_lin - U) / nu)
        if V is not None and np.linalg.norm(V) > 0:
            errs_v.append(np.linalg.norm(V_lin - V) / np.linalg.norm(V))
    if not errs_u:
        return None
    return {"u": float(np.mean(errs_u)), "v": float(np.mean(errs_v)) if errs_v else None}


def body_force(solid) -> np.ndarray | None:
    """Consistent nodal gravity load ∫ ρ g·w dX [N] as [N, 3] when the solid has gravity, else None."""
    if not solid.gravity:
        return None
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc as fem_petsc
    from petsc4py import PETSc

    w = ufl.TestFunction(solid.V)
    b = fem_petsc.assemble_vector(fem.form(solid.rho * ufl.inner(ufl.as_vector(solid.opt.gravity), w) * solid.dx))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    out = b.array.copy().reshape(-1, 3)
    b.destroy()
    return out


# -- the diagnostic generate runs -------------------------------------------------------------


def diagnose(solid, trajectories, layout, dt: float, max_dofs: int | None = None,
             linear: LinearSolid | None = None) -> dict:
    """Resolution, energy shares and linearised re-simulation error of a dataset's trajectories.

    trajectories: a callable returning a fresh iterable of (ok) schema ``Trajectory`` each time
    (the data are read twice). Sparse operators, the resolved modes only (:func:`lowest_modes`)
    and :func:`highest_frequency`: the same figures as the dense, complete eigenproblem at a
    fraction of its cost. Returns a JSON-ready dict: dt [s], free_dofs, the keys of
    :func:`resolution` and :func:`energy_shares`, ``linear_rollout_error`` ({"u", "v"} or None:
    generalized-α, or nothing to compare), ``trajectories`` (count) and ``seconds`` (its cost); or
    {"skipped": reason} above ``max_dofs`` (default :data:`MAX_DENSE_DOFS`) free DOFs.
    ``linear``: the solid's :func:`linear_solid`, when the caller has built it already.
    """
    t0 = time.perf_counter()
    max_dofs = MAX_DENSE_DOFS if max_dofs is None else max_dofs
    n_free = int((~constrained_dofs(solid)).sum())
    if n_free > max_dofs:
        return {"skipped": f"{n_free} free DOFs > {max_dofs}", "free_dofs": n_free, "dt": dt}
    linear = linear_solid(solid) if linear is None else linear
    K, M, free = linear.stiffness, linear.mass, linear.free
    omega, phi = lowest_modes(K, M, UNRESOLVED / dt)
    out: dict = {"dt": float(dt), "free_dofs": n_free,
                 **resolution(omega, dt, modes=n_free, omega_max=highest_frequency(K, M))}
    count = 0

    def counted():
        nonlocal count
        for traj in trajectories():
            count += 1
            yield traj

    out.update(energy_shares(K, M, free, solid.nodes, counted(), layout, dt, modes=(omega, phi)))
    out["linear_rollout_error"] = linear_rollout_error(linear, solid.nodes, trajectories(), layout, dt)
    out["trajectories"] = count
    out["rotations"] = rotations(solid, trajectories, layout, dt, count)
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


#: rotation_report reads at most this many trajectories, evenly spaced (about 1 s each on the liver)
MAX_ROTATION_TRAJECTORIES = 12


def rotations(solid, trajectories, layout, dt: float, count: int) -> dict | None:
    """``thermognn.core.kinematics.rotation_report`` of the data (P1 tets; None otherwise): how
    far its cells rotate, and how far the linear stress of its own displacements is from its
    stress, plain and corotated, with the law's moduli at rest (as ``linear_stress``) and its
    Prony terms for a viscous solid; over at most ``MAX_ROTATION_TRAJECTORIES`` of the ``count``
    trajectories, evenly spaced."""
    from thermognn.core.kinematics import rotation_report

    if solid.cells.shape[1] != 4 or count < 1:
        return None
    k = min(count, MAX_ROTATION_TRAJECTORIES)
    pick = set(np.linspace(0, count - 1, k).round().astype(int).tolist())
    mu = solid.mat.shear_modulus
    prony = tuple((float(t.g), float(t.tau)) for t in solid.mat.prony) if solid.viscous else ()
    return rotation_report(solid.nodes, solid.cells, (t for i, t in enumerate(trajectories()) if i in pick),
                           layout, solid.mat.bulk_modulus - 2.0 * mu / 3.0, mu, prony, dt)


def describe(report: dict, scene: str = "") -> list[str]:
    """One or two console lines (rich markup) that summarise :func:`diagnose`'s report."""
    where = f" ({scene})" if scene else ""
    if "skipped" in report:
        return [f"time resolution{where}: not computed, {report['skipped']}"]
    pct = lambda x: f"{100 * x:.0f} %"  # noqa: E731
    text = (f"time resolution{where}: dt {report['dt']:g} s resolves {report['modes'] - report['unresolved']} "
            f"of {report['modes']} modes (omega_1 dt {report['omega_1_dt']:.3g}, omega_max dt "
            f"{report['omega_max_dt']:.3g}); unresolved modes carry {pct(report['strain_unresolved'])} of the "
            f"strain energy")
    if report.get("kinetic_unresolved") is not None:
        text += f", {pct(report['kinetic_unresolved'])} of the kinetic energy"
    lin = report.get("linear_rollout_error")
    if lin is not None:
        text += f"; linearised FE re-simulates it to u {100 * lin['u']:.1f} %"
        if lin.get("v") is not None:
            text += f", v {100 * lin['v']:.1f} %"
    lines = [text]
    rot = report.get("rotations")
    if rot:
        line = (f"rotations{where}: cells rotate up to {rot['rotation_max_deg']:.0f}° (RMS {rot['rotation_rms_deg']:.1f}° "
                f"at the last step) and strain up to {pct(rot['strain_max'])} (volume RMS {pct(rot['strain_rms'])} "
                f"where it peaks)")
        if rot.get("stress_plain") is not None:
            line += (f"; the linear stress of the data's own displacements is off by {pct(rot['stress_plain'])} of its "
                     f"stress, corotated {pct(rot['stress_corotated'])}")
        lines.append(line)
    if report["strain_unresolved"] > 0.5:
        lines.append("[yellow]hint[/]: most of this data's strain energy is in modes dt does not resolve: it "
                     "responds quasi-statically, and explicit learned steps reproduce such data poorly "
                     "(see docs/accuracy.md)")
    if rot and rot.get("stress_plain") is not None and rot["stress_plain"] > 0.1 \
            and rot["stress_corotated"] < 0.5 * rot["stress_plain"]:
        lines.append("[yellow]hint[/]: the cells' rotations are read as strain by the solid linearised at rest "
                     "(a spurious pressure): model=linear_prior's stress remainder has to undo it where a "
                     "corotated one would not (see docs/accuracy.md, session 40)")
    return lines
