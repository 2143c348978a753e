"""The time-resolution diagnostic (thermognn/generate/modes.py): linearised operators at rest
against analytic values and invariants, the linearised re-simulation, and generate's hook."""

import dataclasses
import io
import json
import math
import re
import tempfile
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from thermognn.core.schema import Dataset, Trajectory  # noqa: E402
from thermognn.core.state import state_layout  # noqa: E402
from thermognn.generate import cases, modes  # noqa: E402
from thermognn.generate.materials import Material, PronyTerm  # noqa: E402
from thermognn.generate.solid import Solid, SolverOptions  # noqa: E402

LENGTHS = (0.02, 0.03, 0.01)                     # box [m]
VOLUME = float(np.prod(LENGTHS))                 # [m^3]
NEO_HOOKEAN = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}, density=1100.0)
OGDEN_LIVER = Material("ogden", {"mu": [2.0e3], "alpha": [16.19], "D": [1.0e-4]}, density=1000.0)


def _free_box(mat):
    """Unclamped box (2 x 2 x 1 hexahedra, 6 P1 tets each): every DOF free. Quasi-static elastic,
    as in test_fe_materials, so that the (slow to compile) Ogden forms come from the JIT cache."""
    return Solid(cases.box_mesh(LENGTHS, (2, 2, 1)), mat, ("elastic",),
                 SolverOptions(integrator="quasi_static", rtol=1e-12, atol=1e-9))


def test_mass_of_rigid_translation():
    """tᵀ M t = ρ V |t|² for a rigid translation t (consistent mass), to 1e-10."""
    s = _free_box(NEO_HOOKEAN)
    K, M, free = modes.rest_operators(s)
    assert free.all() and M.shape == (3 * len(s.nodes),) * 2
    t = np.tile([0.3, -1.2, 0.7], len(s.nodes))
    assert t @ M @ t == pytest.approx(1100.0 * VOLUME * (0.3**2 + 1.2**2 + 0.7**2), rel=1e-10)


@pytest.mark.parametrize("mat", [NEO_HOOKEAN, OGDEN_LIVER], ids=["neo_hookean", "ogden"])
def test_stiffness_at_rest_rigid_modes_and_uniform_strain(mat):
    """Unclamped: K annihilates the 6 rigid modes (translations, rotations e_k × X), and for the
    uniform strain u = (x, 0, 0), which P1 represents exactly, uᵀ K u = V (λ + 2μ) with the law's
    moduli at rest: μ = 2 C10 (neo-Hookean) or Σ μi (Ogden), bulk K0 = 2/D1, λ = K0 − 2μ/3.
    The solid's own tangent is used, so this checks the laws' linearisation, not a separate form.
    (Ogden's regularised eigenvalues change the tangent at rest by O(ε²) ~ 1e-12 only.)"""
    s = _free_box(mat)
    saved = np.linspace(0.0, 1e-3, s.u.x.array.size)
    s.u.x.array[:] = saved                                   # rest_operators must restore it
    K, M, free = modes.rest_operators(s)
    assert np.array_equal(s.u.x.array, saved)
    assert np.allclose(K, K.T, rtol=0, atol=1e-12 * np.abs(K).max())
    X = s.nodes
    norm_K = np.linalg.norm(K, 2)
    for k in range(3):
        e = np.eye(3)[k]
        for r in (np.tile(e, len(X)), np.cross(e, X).ravel()):
            assert np.linalg.norm(K @ r) / (norm_K * np.linalg.norm(r)) < 1e-8
    mu, K0 = mat.shear_modulus, mat.bulk_modulus
    u = np.zeros_like(X)
    u[:, 0] = X[:, 0]
    u = u.ravel()
    assert u @ K @ u == pytest.approx(VOLUME * (K0 - 2 * mu / 3 + 2 * mu), rel=1e-8)
    # the linear stress operator: the same uniform strain gives sigma = (λ + 2μ, λ, λ, 0, 0, 0) at every node
    sigma = (modes.linear_stress(s, free) @ u).reshape(-1, 6)
    lam = K0 - 2 * mu / 3
    assert np.allclose(sigma, [lam + 2 * mu, lam, lam, 0, 0, 0], rtol=0, atol=1e-9 * (lam + 2 * mu))


def test_cantilever_first_bending_frequency_matches_euler_bernoulli():
    """Clamped beam L/h = 20, square section, ν = 0, P2 tets (10 x 1 x 1 boxes): the first two
    (degenerate, y and z) bending frequencies within 1 % of Euler–Bernoulli
    ω1 = 1.8751² sqrt(E I / (ρ A L⁴)). (The converged 3-D value lies ~0.15 % below it: shear
    deformation and rotary inertia, O((h/L)²); this mesh is 0.07 % below.)"""
    mu, rho, L, h = 1.0e6, 1000.0, 1.0, 0.05
    mat = Material("neo_hookean", {"C10": mu / 2, "D1": 2 / (2 * mu / 3)}, density=rho)
    s = Solid(cases.box_mesh((L, h, h), (10, 1, 1)), mat, ("elastic",),
              SolverOptions(degree=2, quadrature_degree=4))
    s.clamp(cases.nodes_where(s, lambda x: x[:, 0] < 1e-10))
    K, M, free = modes.rest_operators(s)
    assert free.sum() == 3 * (len(s.nodes) - 9)                  # 9 P2 nodes on the clamped face
    omega = modes.natural_frequencies(K, M)
    assert np.all(np.diff(omega) >= 0)
    exact = 1.8751**2 * np.sqrt(2 * mu * h**4 / 12 / (rho * h * h * L**4))
    assert omega[0] == pytest.approx(exact, rel=0.01) and omega[1] == pytest.approx(exact, rel=0.01)
    r = modes.resolution(omega, 2.0 / exact)                     # ω1 dt = 2: at the limit
    assert r["modes"] == len(omega) and r["omega_1_dt"] == pytest.approx(2 * omega[0] / exact)
    assert r["unresolved"] == np.count_nonzero(omega * 2.0 / exact > 2.0) and 0 < r["unresolved"] < len(omega)


def _bent_block(load: float, integrator: str = "newmark", steps: int = 8, dt: float = 2e-3, prony=(),
                law: tuple[str, dict] = ("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})):
    """Block 0.02 x 0.02 x 0.04 m (48 P1 tets) clamped at z = 0, top face pushed sideways by a
    total force ``load`` [N] (x), linearly ramped over 4 steps, Rayleigh (αM, βK) = (5 1/s, 1e-3 s),
    viscous with the Prony terms ``prony`` ((g, tau [s]), ...) if any, of the ``law`` (name,
    parameters); returns (solid, layout, trajectory) with z = (q, v, σ) as generate stores it."""
    mat = Material(law[0], dict(law[1]), density=1000.0, prony=tuple(PronyTerm(g, tau) for g, tau in prony))
    effects = ("elastic", "inertia") if integrator != "quasi_static" else ("elastic",)
    effects += ("viscous",) if prony else ()
    s = Solid(cases.box_mesh((0.02, 0.02, 0.04), (2, 2, 4)), mat, effects,
              SolverOptions(integrator=integrator, rayleigh=(5.0, 1e-3), rtol=1e-13, atol=1e-18))
    s.clamp(cases.nodes_where(s, lambda x: x[:, 2] < 1e-10))
    top = cases.nodes_where(s, lambda x: x[:, 2] > 0.04 - 1e-10)
    full = np.zeros_like(s.nodes)
    full[top, 0] = load / len(top)
    layout = state_layout(effects)
    ramp = lambda t: min(1.0, t / (4 * dt))  # noqa: E731

    def state():
        z = np.zeros((len(s.nodes), layout.dim))
        z[:, 0:3] = s.nodes + s.displacement()
        if "v" in layout.names:
            z[:, layout.slice("v")] = s.velocity()
        z[:, layout.slice("sigma")] = s.cauchy_stress_nodes()
        return z

    s.set_nodal_force(0.0 * full)
    s.initial_acceleration()
    zs, forces = [state()], [0.0 * full]
    for k in range(1, steps + 1):
        assert s.step(dt, lambda t: s.set_nodal_force(ramp(t) * full)).ok
        zs.append(state())
        forces.append(ramp(k * dt) * full)
    traj = Trajectory("traj_0", dt * np.arange(steps + 1), np.stack(zs), np.stack(forces), top)
    return s, layout, traj


@pytest.mark.parametrize("integrator", ["newmark", "quasi_static"])
def test_viscoelastic_linearisation_relaxes_as_the_fe_solid(integrator):
    """A viscous solid (Prony terms on the isochoric stress) is linearised with the same
    relaxation (``linear_solid``: K_iso and Σ_iso relaxed step by step as the FE relaxes its
    internal variables): at 1 mN it re-simulates the FE's own u, v and σ to the nonlinearity
    (< 1e-3), 100x better than at 1 N; without the relaxation (the instantaneous K and Σ, what
    the elastic linearisation would be) it misses the creep by far more. The operators survive
    the dataset file."""
    from thermognn.core.schema import DatasetWriter, Mesh

    terms = ((0.4, 4e-3), (0.2, 2e-2))
    errors = {}
    for load in (1e-3, 1.0):
        s, layout, traj = _bent_block(load, integrator, steps=12, prony=terms)
        linear = modes.linear_solid(s)
        assert linear.viscous and linear.prony == terms
        elastic = dataclasses.replace(linear, prony=(), stiffness_iso=None, stress_iso=None)
        for name, model in (("viscous", linear), ("elastic", elastic)):
            pred = model.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3)     # [S, N, D]
            errors[load, name] = {g: np.linalg.norm(pred[..., layout.slice(g)] - traj.z[..., layout.slice(g)])
                                  / np.linalg.norm(traj.z[..., layout.slice(g)]) for g in layout.names if g != "q"}
            errors[load, name]["u"] = (np.linalg.norm(pred[..., :3] - traj.z[..., :3])
                                       / np.linalg.norm(traj.z[..., :3] - s.nodes))
    for g, small in errors[1e-3, "viscous"].items():
        assert small < 1e-3 and small * 100 < errors[1.0, "viscous"][g], (g, errors)
        assert errors[1e-3, "elastic"][g] > 30 * small, (g, errors)
    dataset = Path(tempfile.mkdtemp()) / "d.h5"
    with DatasetWriter(dataset, Mesh(s.nodes, s.cells[:, :4], np.zeros(len(s.nodes), dtype=np.int8)), layout, 2e-3,
                       "{}", "{}", "bend", ("elastic", "viscous")) as w:
        w.write(traj)
        w.set_linear(linear)
    back = Dataset(dataset).linear_solid()
    assert back.prony == terms and abs(back.stiffness_iso - linear.stiffness_iso).max() == 0
    assert abs(back.stress_iso - linear.stress_iso).max() == 0


@pytest.mark.parametrize("integrator", ["newmark", "quasi_static"])
def test_linear_rollout_error_vanishes_with_the_load(integrator):
    """The linearised model (``linear_solid``: K, M, stress operator, the solid's Rayleigh damping
    and integrator) re-simulates the solid's own data with an error that is the nonlinearity
    only, so it scales with the load: at 1 mN (1.3e-5 m, error ~1e-4) at least 100x smaller than
    at 1 N (12 mm, ~0.1), in u, v and the nodal Cauchy stress sigma."""
    errors, stress_errors = {}, {}
    for load in (1e-3, 1.0):
        s, layout, traj = _bent_block(load, integrator)
        linear = modes.linear_solid(s)
        assert linear.integrator == integrator and linear.rayleigh == (5.0, 1e-3)
        errors[load] = modes.linear_rollout_error(linear, s.nodes, [traj], layout, 2e-3)
        pred = linear.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3)     # [S, N, D]
        sl = layout.slice("sigma")
        stress_errors[load] = np.linalg.norm(pred[..., sl] - traj.z[..., sl]) / np.linalg.norm(traj.z[..., sl])
        assert np.allclose(pred[0], traj.z[0])
    small, large = errors[1e-3], errors[1.0]
    assert small["u"] * 100 < large["u"] and large["u"] > 1e-2
    assert stress_errors[1e-3] < 1e-3 and stress_errors[1e-3] * 100 < stress_errors[1.0]
    if integrator == "newmark":
        assert small["v"] * 100 < large["v"]
    else:
        assert small["v"] is None
    linear.integrator = "generalized_alpha"
    assert modes.linear_rollout_error(linear, s.nodes, [traj], layout, 2e-3) is None
    with pytest.raises(ValueError, match="generalized_alpha"):
        linear.rollout(np.zeros(linear.n_free), np.zeros(linear.n_free), np.zeros((2, linear.n_free)), 2e-3)


def test_energy_shares_and_sparse_modes_match_the_complete_modal_sums():
    """At a step that leaves some modes on either side of ω dt = 2: the shares of strain and
    kinetic energy in the unresolved modes equal the direct sums ω² ξ² / 2, η² / 2 over those
    modes of the complete dense eigenbasis (ξ = Φᵀ M u, Φᵀ M Φ = I), to 1e-8, and lie in [0, 1]
    with their complements summing to 1. The sparse path generate uses (Lanczos for the resolved
    modes and ω_max) gives the same frequencies, resolution and shares. Without v in the layout
    the kinetic share is None."""
    s, layout, traj = _bent_block(0.1)
    K, M, free = modes.rest_operators(s)
    omega, phi = modes.modal_basis(K, M)
    assert np.allclose(phi.T @ M @ phi, np.eye(len(omega)), atol=1e-8)
    assert np.allclose(omega, modes.natural_frequencies(K, M), rtol=1e-8)
    dt = 2.0 / np.sqrt(omega[1] * omega[2])                      # two modes resolved
    hi = omega * dt > 2.0
    U = (traj.z[:, :, 0:3] - s.nodes).reshape(len(traj.z), -1)[:, free]
    V = traj.z[:, :, 3:6].reshape(len(traj.z), -1)[:, free]
    strain = (omega**2 * (U @ M @ phi) ** 2).sum(0)              # per mode (x 2) [J]
    kinetic = ((V @ M @ phi) ** 2).sum(0)
    expected = {"strain": strain[hi].sum() / strain.sum(), "kinetic": kinetic[hi].sum() / kinetic.sum()}
    assert 0.1 < expected["strain"] < 0.9 and 0.001 < expected["kinetic"] < 0.9

    Ks, Ms, free_s = modes.rest_operators(s, sparse=True)
    assert np.array_equal(free_s, free) and np.allclose(Ks.toarray(), K, rtol=0, atol=1e-12 * np.abs(K).max())
    low, phi_low = modes.lowest_modes(Ks, Ms, 2.0 / dt)
    assert len(low) == np.count_nonzero(~hi) and np.allclose(low, omega[~hi], rtol=1e-8)
    assert modes.highest_frequency(Ks, Ms) == pytest.approx(omega[-1], rel=1e-6)
    many, _ = modes.lowest_modes(Ks, Ms, np.sqrt(omega[19] * omega[20]))   # > 12: Lanczos restarts
    assert np.allclose(many, omega[:20], rtol=1e-8)
    full = modes.resolution(omega, dt)
    assert full["unresolved"] == hi.sum() and full["modes"] == len(omega)
    part = modes.resolution(low, dt, modes=len(omega), omega_max=modes.highest_frequency(Ks, Ms))
    assert part == pytest.approx(full, rel=1e-6)
    for e in (modes.energy_shares(K, M, free, s.nodes, [traj], layout, dt, modes=(omega, phi)),
              modes.energy_shares(K, M, free, s.nodes, [traj], layout, dt),
              modes.energy_shares(Ks, Ms, free, s.nodes, [traj], layout, dt)):
        for kind in ("strain", "kinetic"):
            hi_share, lo_share = e[f"{kind}_unresolved"], e[f"{kind}_resolved"]
            assert hi_share == pytest.approx(expected[kind], abs=1e-8)
            assert 0 <= hi_share <= 1 and 0 <= lo_share <= 1 and hi_share + lo_share == pytest.approx(1, abs=1e-12)
    e = modes.energy_shares(K, M, free, s.nodes, [traj], state_layout(("elastic",)), dt)
    assert e["kinetic_unresolved"] is None and e["strain_unresolved"] == pytest.approx(expected["strain"], abs=1e-8)


def test_generate_stores_time_resolution(tmp_path, monkeypatch):
    """generate writes the diagnostic as the root attribute ``time_resolution`` (JSON); when the
    diagnostic fails, generate still succeeds, without the attribute."""
    from thermognn.core.config import load_config
    from thermognn.core.schema import Dataset
    from thermognn.generate import generate

    tiny = ["scene.loads.n_trajectories=2", "scene.time.steps=4", "scene.loads.ramp_steps=2",
            "scene.mesh.cell_size=0.01"]
    d = Dataset(generate(load_config([f"out={tmp_path / 'a'}", *tiny])))
    import h5py

    with h5py.File(d.path, "r") as f:
        report = json.loads(f.attrs["time_resolution"])
    assert report == d.time_resolution
    for key in ("omega_1_dt", "omega_max_dt", "modes", "unresolved", "strain_unresolved",
                "kinetic_unresolved", "linear_rollout_error"):
        assert key in report
    assert report["modes"] == report["free_dofs"] == 3 * int((d.mesh.node_type != 1).sum())
    assert report["trajectories"] == 2 and report["dt"] == pytest.approx(0.01)
    assert 0 <= report["strain_unresolved"] <= 1 and set(report["linear_rollout_error"]) == {"u", "v"}
    # rotations (thermognn/core/kinematics.py): the cells under the load point turn about 10°, enough
    # for the plain linear stress of the data's own displacements to be 10 % off its stress; the
    # corotated one is not (measured: 0.100 and 0.0079)
    rot = report["rotations"]
    assert rot["trajectories"] == 2 and 0 < rot["rotation_max_deg"] < 20
    assert 0 < rot["stress_plain"] < 0.2 and 0 < rot["stress_corotated"] < 0.25 * rot["stress_plain"]
    assert 0 < rot["strain_rms"] < rot["strain_max"] < 1          # the cells under the load strain most
    # the plain cell formula is generate's stress operator: Σ u of the stored /linear
    from thermognn.core.kinematics import linear_cell_stress, node_average, shape_gradients

    lin, mesh, z = d.linear_solid(), d.mesh, d.read("traj_1").z
    mu, kappa = 2 * 1.0e4, 2 / 1.0e-5                                       # the block: 2 C10, 2 / D1
    plain = node_average(linear_cell_stress(z[..., 0:3], mesh.nodes, mesh.tets, kappa - 2 * mu / 3, mu),
                         mesh.tets, shape_gradients(mesh.nodes, mesh.tets)[1], len(mesh.nodes))
    sigma_u = (lin.stress @ lin.free_rows(z[..., 0:3] - mesh.nodes[None]).T).T.reshape(plain.shape)
    assert np.allclose(plain, sigma_u, rtol=1e-9, atol=1e-9 * np.abs(sigma_u).max())

    def broken(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(modes, "diagnose", broken)
    d = Dataset(generate(load_config([f"out={tmp_path / 'b'}", *tiny[1:], "scene.loads.n_trajectories=1"])))
    assert d.ok_names == ["traj_0"] and d.time_resolution is None


def _rel(a, b) -> float:
    """‖a − b‖ / ‖b‖."""
    return float((a - b).norm() / b.norm())


def _prior_rollout(prior, u, v, f, G, H):
    """A NewmarkPrior's (or CorotatedNewmarkPrior's) rollout from the first of the displacements
    u, velocities v [S, N, 3] under the loads f [S, N, 3], with the remainders G [S, n] and H
    (None or [S, N, 6]), its Prony internal variables carried: (U, V [S, N, 3], σ [S, N, 6]), as
    its ``physical_state`` composes them (what a model's rollout reports)."""
    import torch

    uf, vf = prior.gather(u[:1]), prior.gather(v[:1])
    h = prior.internal_variables(uf)                                      # [1, T, n + 6N]
    a = prior.initial_acceleration(uf, vf, prior.gather(f[:1]), G[:1])
    us, vs, hs = [uf], [vf], [h]
    for k in range(1, len(f)):
        uf, vf, a, h = prior.step(uf, vf, a, prior.gather(f[k:k + 1]), G[k - 1:k], G[k:k + 1], h)
        us, vs, hs = us + [uf], vs + [vf], hs + [h]
    origin = torch.zeros(prior.n_nodes, 3, dtype=uf.dtype)               # q = 0 + U: the displacements
    z = prior.physical_state(origin, torch.cat(us), torch.cat(vs), H, torch.cat(hs))    # [S, N, 12]
    return z[..., 0:3], z[..., 3:6], z[..., 6:12]


def test_the_prior_solves_the_fe_mass_matrix_by_conjugate_gradients():
    """NewmarkPrior.mass_solve (no dense M⁻¹ kept: the bunny's was 226 MB): the FE's consistent
    mass matrix of the bent block solved for a batch of loads (one of them zero) to 1e-12 of a
    dense solve, its gradient M⁻¹ w (M symmetric), the same in TorchScript, and a /linear whose
    mass has a diagonal entry <= 0 refused by name."""
    torch = pytest.importorskip("torch")
    from thermognn.train.prior import NewmarkPrior

    s, _, _ = _bent_block(1.0, "newmark", steps=1)
    linear = modes.linear_solid(s)
    prior = NewmarkPrior(linear, len(s.nodes), 2e-3)
    M = torch.as_tensor(np.asarray(linear.mass.todense() if hasattr(linear.mass, "todense") else linear.mass))
    g = torch.Generator().manual_seed(3)
    b = torch.randn(3, prior.n_free, generator=g, dtype=torch.float64) * 1e-2
    b[1] = 0.0
    b.requires_grad_(True)
    x = prior.mass_solve(b)
    exact = torch.linalg.solve(M, b.detach().T).T
    assert float((x - exact).norm() / exact.norm()) < 1e-12 and float(x[1].abs().max()) == 0.0
    w = torch.randn(3, prior.n_free, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad((x * w).sum(), b)
    assert float((grad - torch.linalg.solve(M, w.T).T).norm() / grad.norm()) < 1e-10
    scripted = torch.jit.script(prior)
    assert float((scripted.mass_solve(b.detach()) - x.detach()).abs().max()) == 0.0
    linear.mass = -linear.mass
    with pytest.raises(ValueError, match="mass matrix has a diagonal entry <= 0"):
        NewmarkPrior(linear, len(s.nodes), 2e-3)


def test_newmark_prior_with_the_exact_remainders_is_the_fe_step():
    """thermognn/train/prior.py: the data's Newmark step on the linearised solid, plus the
    internal-force remainder G = K u − f_int(u) and the stress remainder H = σ − Σ u. With
    G = H = 0 it is the linearised FE model (LinearSolid.rollout); with the remainders
    ``remainders`` recovers from an FE trajectory (12 mm bend, mass and stiffness damping) it
    reproduces that trajectory to round-off in u, v and σ. G vanishes at rest and is a sizeable
    share of the load here (the nonlinearity a hybrid model learns)."""
    torch = pytest.importorskip("torch")
    from thermognn.train.prior import NewmarkPrior

    s, layout, traj = _bent_block(1.0, "newmark")
    dt, X = 2e-3, s.nodes
    linear = modes.linear_solid(s)
    prior = NewmarkPrior(linear, len(X), dt)
    z, f = torch.as_tensor(traj.z), torch.as_tensor(traj.force)
    u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., layout.slice("sigma")]
    G, H = prior.remainders(u, v, sigma, f)
    assert float(G[0].abs().max()) == 0.0
    assert float(G.norm() / prior.gather(f).norm()) > 0.05

    U, V, Sig = _prior_rollout(prior, u, v, f, G, H)
    assert _rel(U, u) < 1e-9 and _rel(V, v) < 1e-9 and _rel(Sig, sigma) < 1e-9
    U, V, Sig = _prior_rollout(prior, u, v, f, torch.zeros_like(G), None)
    lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))
    assert _rel(U, lin[..., 0:3] - torch.as_tensor(X)) < 1e-10 and _rel(V, lin[..., 3:6]) < 1e-10
    assert _rel(Sig, lin[..., layout.slice("sigma")]) < 1e-10
    assert _rel(U, u) > 1e-2                                   # the remainders are what it lacked
    linear.integrator = "quasi_static"
    with pytest.raises(ValueError, match="quasi_static"):
        NewmarkPrior(linear, len(X), dt)


def test_relaxing_prior_with_the_exact_remainders_is_the_viscous_fe_step():
    """``NewmarkPrior(relax=True)`` (``model.prior_relax``) on a viscous 12 mm bend (two Prony
    terms, mass and stiffness damping): it carries the Prony internal variables between steps as
    the linearised baseline does, so with G = H = 0 it is the relaxing linearised FE model
    (LinearSolid.rollout_states) and with the exact remainders the FE trajectory, to round-off.
    Its remainders start at second order in the load: from 1 N to 1 mN their share of the load
    (G) and of the stress (H) falls 1000-fold, while the unrelaxed prior's, which leaves the
    relaxation (of first order) to the network, stays a few per cent of its 1 N share. An elastic
    solid has nothing to relax: a one-line error."""
    torch = pytest.importorskip("torch")
    from thermognn.train.prior import NewmarkPrior

    terms = ((0.4, 4e-3), (0.2, 2e-2))
    share = {}
    for load in (1e-3, 1.0):
        s, layout, traj = _bent_block(load, "newmark", steps=12, prony=terms)
        dt, X = 2e-3, s.nodes
        linear = modes.linear_solid(s)
        z, f = torch.as_tensor(traj.z), torch.as_tensor(traj.force)
        u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., layout.slice("sigma")]
        for relax in (True, False):
            prior = NewmarkPrior(linear, len(X), dt, relax=relax)
            G, H = prior.remainders(u, v, sigma, f)
            assert float(G[0].abs().max()) == 0.0
            share[load, relax] = float(G.norm() / prior.gather(f).norm()), float(H.norm() / sigma.norm())
        prior = NewmarkPrior(linear, len(X), dt, relax=True)
        assert prior.n_terms == 2
        G, H = prior.remainders(u, v, sigma, f)

        U, V, Sig = _prior_rollout(prior, u, v, f, G, H)
        assert _rel(U, u) < 1e-9 and _rel(V, v) < 1e-9 and _rel(Sig, sigma) < 1e-9, load
        U, V, Sig = _prior_rollout(prior, u, v, f, torch.zeros_like(G), None)
        lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))
        assert _rel(U, lin[..., 0:3] - torch.as_tensor(X)) < 1e-10 and _rel(V, lin[..., 3:6]) < 1e-10
        assert _rel(Sig, lin[..., layout.slice("sigma")]) < 1e-10
    for k in (0, 1):       # G and H relative to the load and stress: ∝ load (relaxing), not (unrelaxed)
        assert share[1e-3, True][k] < 3e-3 * share[1.0, True][k], share
        assert share[1e-3, False][k] > 3e-2 * share[1.0, False][k], share
        assert share[1e-3, True][k] < 3e-2 * share[1e-3, False][k], share
    with pytest.raises(ValueError, match="elastic"):
        NewmarkPrior(modes.linear_solid(_bent_block(1.0, "newmark", steps=2)[0]), len(X), dt, relax=True)


def test_relaxing_prior_model_steps_its_carried_internal_variables():
    """A ``model.prior_relax`` LinearPriorModel on the viscous 12 mm bend with a random network:
    with its remainders zero it is the relaxing linearised FE model; stepping the carried state
    [N, D + 6 + 9 T] one call at a time (eager and scripted) gives the batched rollout; steps and
    windows from the states of its own rollout mid-way (carrying the internal variables along the
    data, ``trajectory_internal_variables``) follow it exactly; export's layout names the
    internal variables."""
    torch = pytest.importorskip("torch")
    from thermognn.train.data import Graph, TrajectoryTensors
    from thermognn.train.hybrid import LinearPriorModel, _RolloutPhase, carried_layout
    from thermognn.train.model import TIGNN
    from thermognn.train.prior import NewmarkPrior
    from thermognn.train.rollout import one_step_errors

    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph(steps=9, prony=((0.4, 4e-3),))
    ref = torch.as_tensor(X)
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True).double()
    net.set_stats({"z_std": z.reshape(-1, 12).std(0) + 1e-3, "f_std": torch.full((3,), 0.1),
                   "dzdt_std": torch.full((12,), 3e-2)})
    # (the network sees positions only: one seeing σ takes G at a step's end from the σ of the
    # last H, so a step from a stored state differs from the rollout's by more than round-off)
    model = LinearPriorModel(net, NewmarkPrior(linear, len(X), dt, relax=True), ref, order=2)
    lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))

    graph = Graph(ref, edges, node_type, torch.zeros(0, 3, dtype=torch.long))
    fe = [TrajectoryTensors("fe", z, f, torch.arange(len(f)) * dt)]
    saved = _zero_remainders(net)
    with torch.enable_grad():
        zero = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
        zero_step, _ = one_step_errors(model, graph, fe, layout, dt)
    assert _rel(zero, lin) < 1e-12 and _rel(zero[..., 6:12], lin[..., 6:12]) < 1e-10
    net.load_state_dict(saved)
    # evaluate's linearised FE one step (linear_fe: the prior alone) is the zero network's, whatever the weights
    linear_step, _ = one_step_errors(model, graph, fe, layout, dt, linear_fe=True)
    assert all(abs(linear_step[g] - zero_step[g]) < 1e-9 * zero_step[g] for g in zero_step), (linear_step, zero_step)
    assert min(linear_step.values()) > 1e-4
    with torch.enable_grad():
        batched = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
        assert _rel(batched[..., 3:6], lin[..., 3:6]) > 1e-6              # the network corrects something
        for stepper in (model, torch.jit.script(model)):
            states = [stepper.carry(z[0], f[0], edges, node_type, ref)]  # [N, D + 6 + 9]
            assert states[0].shape == (len(X), 12 + 6 + 9)
            for k in range(1, len(f)):
                states.append(stepper.step(states[-1], f[k], edges, node_type, ref, torch.tensor(dt)))
            assert _rel(torch.stack(states)[..., :12], batched) < 1e-9
        own = [TrajectoryTensors("own", batched, f, torch.arange(len(f)) * dt)]
        errors, _ = one_step_errors(model, graph, own, layout, dt)
        assert max(errors.values()) < 1e-8, errors
        windows = _RolloutPhase(model, own, window=3)
        assert float(windows.loss([(0, 3), (0, 6)], graph.copies(2))[0]) < 1e-18
    names = [g[0] for g in json.loads(carried_layout(layout.to_json(), model.prior.internal_columns()))]
    assert names == ["q", "v", "sigma", "a", "G", "prony_force_1", "prony_stress_1"]


def _zero_remainders(net) -> dict:
    """Zero the last layers of a LinearPriorModel's network (its remainders vanish: the model is
    the linearised FE model); returns its weights before, to restore with ``load_state_dict``."""
    import torch

    with torch.no_grad():
        saved = {k: v.clone() for k, v in net.state_dict().items()}
        for p in [*net.decoder.net[-1].parameters(), *net.port.parameters()]:
            p.zero_()
    return saved


def _bent_block_graph(**options):
    """The damped 12 mm bend (Newmark, dt 2 ms; ``options`` as ``_bent_block`` takes them, e.g.
    steps, prony) with what a graph network needs: (layout, its trajectory, dt, reference
    positions X [N, 3], the linearised solid, node types (base clamped), mesh edges, z [S, N, D]
    and loads f [S, N, 3] as tensors)."""
    import torch

    from thermognn.core.schema import Mesh

    s, layout, traj = _bent_block(1.0, "newmark", **options)
    dt, X = 2e-3, s.nodes
    node_type = torch.as_tensor(np.where(X[:, 2] < 1e-10, 1, 0))
    edges = torch.as_tensor(Mesh(X, s.cells[:, :4], node_type.numpy()).edges())
    return (layout, traj, dt, X, modes.linear_solid(s), node_type, edges, torch.as_tensor(traj.z),
            torch.as_tensor(traj.force))


def test_a_validation_rollout_that_runs_away_is_stopped_there_and_counted_diverged():
    """``validation_error`` stops a rollout whose state passes ``RUNAWAY_FACTOR`` times its
    trajectory's largest in any group (``runaway_bound``) and counts it diverged (inf), as the
    prior's non-finite state is: a runaway's later steps are the dearest (session 86's bunny law:
    2882 s validating 4.4e9). The bound stops the batched rollout of a ``model=linear_prior`` model
    and a graph network's own step alike, at the first step past it; a rollout within it is
    untouched (the damped 12 mm bend)."""
    torch = pytest.importorskip("torch")
    from thermognn.train.data import Graph, TrajectoryTensors
    from thermognn.train.hybrid import LinearPriorModel
    from thermognn.train.model import TIGNN
    from thermognn.train.prior import RAN_AWAY, NewmarkPrior
    from thermognn.train.rollout import RUNAWAY_FACTOR, rollout, runaway_bound, trajectory_error, validation_error

    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph()
    ref = torch.as_tensor(X, dtype=torch.float32)
    graph = Graph(ref, edges, node_type, torch.zeros(0, 3, dtype=torch.long))
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True)
    net.set_stats({"dzdt_std": torch.full((12,), 1e-2)})
    model = LinearPriorModel(net, NewmarkPrior(linear, len(X), dt), torch.as_tensor(X))
    times = torch.arange(len(f)) * dt
    data = TrajectoryTensors("bend", z, f, times)
    pred = rollout(model, graph, z[0], f, dt)
    reach = float((z[..., :3] - ref).abs().max())
    assert float((pred[..., :3] - ref).abs().max()) < RUNAWAY_FACTOR * reach      # this one stays within
    assert torch.equal(rollout(model, graph, z[0], f, dt, bound=runaway_bound(z, ref, layout)), pred)
    errors = trajectory_error(pred, z, layout)
    assert validation_error(model, graph, [data], layout, dt) == pytest.approx(
        sum(errors.values()) / len(errors), rel=1e-12)

    # the same loads against data whose displacements are 1e-6 of the bend's: the models'
    # rollouts pass 10 times their largest at the first step, and stop there
    small = TrajectoryTensors("small", torch.cat([ref + (z[..., :3] - ref) * 1e-6, z[..., 3:] * 1e-6], -1), f, times)
    assert validation_error(model, graph, [data, small], layout, dt) == math.inf
    bound = runaway_bound(small.z, ref, layout)
    assert bound[:3].tolist() == pytest.approx([RUNAWAY_FACTOR * 1e-6 * reach] * 3, rel=1e-12)
    for stepped, dtype in ((model, z.dtype), (net, torch.float32)):    # the batched rollout, a network's own step
        with pytest.raises(RuntimeError, match=f"{RAN_AWAY} at step 1: column [0-9]+ reached .* past "):
            rollout(stepped, graph, z[0].to(dtype), f.to(dtype), dt, bound=bound)
    # one column past its bound is enough, whichever group it is in: here the stress alone
    sigma = layout.slice("sigma")
    only_stress = runaway_bound(z, ref, layout)
    only_stress[sigma] = 1e-6 * float(z[..., sigma].abs().max())
    with pytest.raises(RuntimeError, match=f"{RAN_AWAY} at step 1: column ({'|'.join(map(str, range(6, 12)))}) "):
        rollout(model, graph, z[0], f, dt, bound=only_stress)
    small32 = TrajectoryTensors("small", small.z.float(), f.float(), times)
    assert validation_error(net, graph, [small32], layout, dt) == math.inf


def test_linear_prior_model_is_the_linearised_fe_model_and_its_carried_step_its_rollout():
    """thermognn/train/hybrid.py (``model.prior=linear``) on the damped 12 mm bend: with the
    network's remainders zero (its last layers zeroed) the model's rollout is the linearised FE
    model's (LinearSolid.rollout_states) to round-off; with a random network, stepping the
    carried state [N, D + 6] (q, v, σ, Newmark's a, the last G: what export and serve step) one
    call at a time, also scripted (TorchScript), gives the batched rollout training uses; the
    one-step error from the states of its own rollout vanishes."""
    torch = pytest.importorskip("torch")
    from thermognn.train.data import Graph, TrajectoryTensors
    from thermognn.train.hybrid import LinearPriorModel, _RolloutPhase
    from thermognn.train.model import TIGNN
    from thermognn.train.rollout import one_step_errors, trajectory_error
    from thermognn.train.prior import NewmarkPrior

    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph()
    ref = torch.as_tensor(X, dtype=torch.float32)
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True)
    net.set_stats({"dzdt_std": torch.full((12,), 1e-2)})       # remainders of ~1e-2 N, Pa
    model = LinearPriorModel(net, NewmarkPrior(linear, len(X), dt), torch.as_tensor(X))

    # rollout (validation, evaluate) steps with the weights frozen, so no step's solve hangs on
    # their graph to the end, and gives them back trainable: the same states as the batched rollout
    from thermognn.train.rollout import rollout
    with torch.enable_grad():
        batched = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
    stepped = rollout(model, Graph(ref, edges, node_type, torch.zeros(0, 3, dtype=torch.long)), z[0], f, dt)
    assert torch.equal(stepped, batched.detach().to(z.dtype)) and all(p.requires_grad for p in model.parameters())

    saved = _zero_remainders(net)
    with torch.enable_grad():
        pred = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
    lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))
    assert _rel(pred, lin) < 1e-12 and _rel(pred[..., 3:6], lin[..., 3:6]) < 1e-10
    # one step from each state of its own rollout, with the Newmark acceleration recovered from
    # the velocities there (evaluate's one-step error), is that rollout's step; from the FE's not
    graph = Graph(ref, edges, node_type, torch.zeros(0, 3, dtype=torch.long))
    times = torch.arange(len(f)) * dt
    with torch.enable_grad():
        own, _ = one_step_errors(model, graph, [TrajectoryTensors("lin", lin, f, times)], layout, dt)
        fe, _ = one_step_errors(model, graph, [TrajectoryTensors("fe", z, f, times)], layout, dt)
    assert max(own.values()) < 1e-8 and min(fe.values()) > 1e-4, (own, fe)
    # training rollouts in windows (train.rollout_window) tile the trajectory; a window from a
    # state mid-way takes the data's Newmark acceleration there and so follows the linear model's
    # own rollout exactly; a window as long as the trajectory is the whole rollout
    own = [TrajectoryTensors("lin", lin, f, times)]
    windows = _RolloutPhase(model, own, window=3)
    assert windows.samples == [(0, 0), (0, 3), (0, 6)] and _RolloutPhase(model, own).samples == [(0, 0)]
    with torch.enable_grad():
        assert float(windows.loss([(0, 3), (0, 6)], graph.copies(2))[0]) < 1e-18
        assert float(windows.loss([(0, 0)], graph.copies(1))[0]) < 1e-18
        fe_windows = _RolloutPhase(model, [TrajectoryTensors("fe", z, f, times)], window=100)
        whole = _RolloutPhase(model, [TrajectoryTensors("fe", z, f, times)])
        assert fe_windows.window == whole.window == len(f) - 1
        assert float(fe_windows.loss([(0, 0)], graph.copies(1))[0]) == float(whole.loss([(0, 0)], graph.copies(1))[0]) > 0
        # train.rollout_scale=trajectory: each group's error relative to the RMS of its own
        # trajectory, whatever the others' sizes (with "data": one scale for all), so a whole
        # trajectory's loss is the sum of its squared whole-rollout errors (trajectory_error, q as
        # the displacement), times (S + 1) / S as its RMS counts the rest state it starts from
        fe = TrajectoryTensors("fe", z, f, times)
        louder = TrajectoryTensors("louder", torch.cat([z[..., :3], 10 * z[..., 3:]], -1), f, times)
        assert all(float(sc.std()) == 0 for _, sc in _RolloutPhase(model, [louder, fe]).scales)
        own_scale = _RolloutPhase(model, [louder, fe], scale="trajectory")
        assert all(float(sc[0] / sc[1]) == pytest.approx(10.0) for _, sc in own_scale.scales[1:])
        S, Xt = len(f) - 1, torch.as_tensor(X)
        displacement = lambda s: torch.cat([s[..., :3] - Xt, s[..., 3:]], -1)  # noqa: E731
        assert float(displacement(z[0]).abs().max()) < 1e-9 * float(displacement(z).abs().max())  # from rest
        pred = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, S, True)[0]
        errors = trajectory_error(displacement(pred), displacement(z), layout)
        assert float(own_scale.loss([(1, 0)], graph.copies(1))[0]) == pytest.approx(
            (S + 1) / S * sum(e ** 2 for e in errors.values()), rel=1e-9)
        # train.rollout_weights: each group's term times its weight (here q, v, sigma: 0, 1, 3)
        weighted = _RolloutPhase(model, [louder, fe], scale="trajectory", weights=(0.0, 1.0, 3.0))
        assert float(weighted.loss([(1, 0)], graph.copies(1))[0]) == pytest.approx(
            (S + 1) / S * (errors["v"] ** 2 + 3 * errors["sigma"] ** 2), rel=1e-9)
        # train.stress_remainder_weight: plus that weight times the network's stress remainder H
        # at the true states 1, 4, 7, ... (here zero) against the exact one, sigma - the prior's
        # stress of the true displacement, relative to the trajectory's sigma scale
        fitted = _RolloutPhase(model, [louder, fe], scale="trajectory", stress_weight=2.0, mesh=graph.copies)
        total, rollout_part, _ = fitted.loss([(1, 0)], graph.copies(1))
        assert rollout_part == pytest.approx(float(own_scale.loss([(1, 0)], graph.copies(1))[0]), rel=1e-12)
        states = z[1::3].double()
        exact = states[..., 6:12] - model.prior.stress(states[..., :3] - Xt)
        assert float(exact.abs().max()) > 0
        assert float(total) == pytest.approx(
            rollout_part + 2.0 * float((exact / own_scale.scales[2][1][1]).pow(2).mean()), rel=1e-9)
        # evaluate's stress split: the linearised model's rollout has no H (its sigma is the prior's
        # stress of its displacement); the data against itself has the exact H and no gap
        from thermognn.train.evaluation import stress_split
        alone = stress_split(model, [lin], [fe])
        assert alone["learned_H"] < 1e-9 and alone["exact_H"] > 0 and alone["prior_stress_gap"] > 0
        itself = stress_split(model, [z], [fe])
        assert itself["learned_H"] == pytest.approx(1.0, rel=1e-12) and itself["prior_stress_gap"] < 1e-12
        assert itself["exact_H"] == pytest.approx(alone["exact_H"], rel=1e-12)

    net.load_state_dict(saved)                                 # a network that corrects something
    with torch.enable_grad():
        batched = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
        assert _rel(batched[..., 3:6], lin[..., 3:6]) > 1e-6
        scripted = torch.jit.script(model)
        for stepper in (model, scripted):
            carried = stepper.carry(z[0], f[0], edges, node_type, ref)           # [N, D + 6]
            assert carried.shape == (len(X), 18)
            states = [carried]
            for k in range(1, len(f)):
                states.append(stepper.step(states[-1], f[k], edges, node_type, ref, torch.tensor(dt)))
            stepped = torch.stack(states)[..., :12]
            assert _rel(stepped, batched) < 1e-9 and _rel(stepped[..., 3:6], batched[..., 3:6]) < 1e-8   # round-off

    # anchored: the remainders vanish at the unloaded reference state, as the true ones do
    rest = torch.cat([torch.as_tensor(X), torch.zeros(len(X), 9, dtype=torch.float64)], 1).unsqueeze(0)
    zero = torch.zeros_like(rest[:, :, 0:3])
    with torch.enable_grad():
        G, H = model.remainders(rest, zero, edges, node_type, ref, False)
        assert float(H.abs().max()) > 1e-6
        model.anchor(edges, node_type, ref)
        G, H = model.remainders(rest, zero, edges, node_type, ref, False)
    assert float(G.abs().max()) == 0.0 and float(H.abs().max()) == 0.0


def test_second_order_remainders_make_gentle_loads_exactly_linear():
    """``model.prior_order=2`` (LinearPriorModel.network_remainders): the network's remainders are
    its second difference along the ray from the unloaded rest state, so for any weights they
    start at second order in the load, as the true G = K u − f_int(u) and H = σ − Σ u do. On the
    damped 12 mm bend with a random network: along a ray of states and loads, halving the step
    quarters G and H (order 1, anchored: halves them); under loads scaled by ε the rollout
    differs from the linearised FE model's by O(ε) relative (order 1: by a share that does not
    shrink); the scripted model, saved and loaded, steps as the eager
    one; r(z₀, 0) kept by ``anchor`` is the one evaluated afresh."""
    torch = pytest.importorskip("torch")
    from thermognn.train.hybrid import LinearPriorModel
    from thermognn.train.model import TIGNN
    from thermognn.train.prior import NewmarkPrior

    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph()
    ref = torch.as_tensor(X)
    lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))

    def model_of(order):
        torch.manual_seed(0)
        net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True).double()
        net.set_stats({"z_std": z.reshape(-1, 12).std(0) + 1e-3, "f_std": torch.full((3,), 0.1),
                       "dzdt_std": torch.full((12,), 3e-2)})
        m = LinearPriorModel(net, NewmarkPrior(linear, len(X), dt), ref, positions_only=False, order=order)
        with torch.enable_grad():
            m.anchor(edges, node_type, ref)
        return m

    rest = torch.cat([ref, torch.zeros(len(X), 9, dtype=torch.float64)], 1).unsqueeze(0)    # [1, N, 12]
    ray = (z[-1:] - rest, f[-1:])                                                           # state and load
    for order, ratio in ((1, 0.5), (2, 0.25)):
        model = model_of(order)
        with torch.enable_grad():
            G1, H1 = model.remainders(rest + 1e-3 * ray[0], 1e-3 * ray[1], edges, node_type, ref, False)
            G2, H2 = model.remainders(rest + 2e-3 * ray[0], 2e-3 * ray[1], edges, node_type, ref, False)
        assert float(G1.norm() / G2.norm()) == pytest.approx(ratio, rel=0.02), order
        assert float(H1.norm() / H2.norm()) == pytest.approx(ratio, rel=0.02), order
        gaps = []
        for eps in (1.0, 1e-2, 1e-3):
            with torch.enable_grad():
                pred = model.rollouts(z[:1], eps * f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
            gaps.append(_rel(pred[..., 3:6], eps * lin[..., 3:6]))     # (the linear model scales with the load)
        assert gaps[0] > 1e-4, gaps                                  # the network corrects something
        if order == 1:
            assert gaps[2] > 0.3 * gaps[1], gaps
        else:
            assert gaps[2] == pytest.approx(0.1 * gaps[1], rel=0.05) and gaps[1] < 0.2 * gaps[0], gaps
            with torch.enable_grad():      # r(z₀, 0) as ``anchor`` kept it, and evaluated afresh
                kept = model.remainders(z[-1:], f[-1:], edges, node_type, ref, False)
                fresh = model.remainders(z[-1:], f[-1:], edges, node_type, ref, True)
            assert _rel(kept[0], fresh[0].detach()) < 1e-12 and _rel(kept[1], fresh[1].detach()) < 1e-12
    buffer = io.BytesIO()
    torch.jit.save(torch.jit.script(model), buffer)          # as export writes it, with what anchor kept
    buffer.seek(0)
    scripted = torch.jit.load(buffer)
    with torch.enable_grad():
        carried = model.carry(z[0], f[0], edges, node_type, ref)
        a = model.step(carried, f[1], edges, node_type, ref, torch.tensor(dt))
        b = scripted.step(carried, f[1], edges, node_type, ref, torch.tensor(dt))
    assert _rel(b, a) < 1e-12


def _two_bent_bodies(corotated: bool):
    """A random second-order ``LinearPriorModel`` (float64, unanchored, as in training) on the
    damped 12 mm bend with the linearised prior or the corotated one (2 sweeps), and two bodies to
    roll out 3 steps: (net, model, graph tensors of two mesh copies, z0 [2, N, D], loads
    [2, 4, N, 3], 3)."""
    import torch

    from thermognn.train.hybrid import LinearPriorModel
    from thermognn.train.model import TIGNN
    from thermognn.train.prior import CorotatedNewmarkPrior, NewmarkPrior

    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph()
    ref = torch.as_tensor(X)
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True).double()
    net.set_stats({"z_std": z.reshape(-1, 12).std(0) + 1e-3, "f_std": torch.full((3,), 0.1),
                   "dzdt_std": torch.full((12,), 3e-2)})
    if corotated:
        mu, kappa = linear.shear_modulus, linear.bulk_modulus
        tets = _bent_block(1.0, "newmark")[0].cells[:, :4]
        prior = CorotatedNewmarkPrior(linear, len(X), dt, X, tets, kappa - 2 * mu / 3, mu, sweeps=2)
    else:
        prior = NewmarkPrior(linear, len(X), dt)
    model = LinearPriorModel(net, prior, ref, positions_only=False, order=2)
    N = len(X)
    mesh = (torch.cat([edges, edges + N], 1), torch.cat([node_type, node_type]), torch.cat([ref, ref]))
    z0, forces = torch.stack([z[2], z[5]]), torch.stack([f[2:6], f[5:9]])          # [2, N, D], [2, 4, N, 3]
    return net, model, mesh, z0, forces, 3


def test_second_order_rollouts_take_the_rest_rates_once_with_the_same_gradients():
    """A rollout of ``model.prior_order=2`` evaluates r(z₀, 0) once for all its steps
    (``LinearPriorModel.rest_rates_once``), not at every step: on the damped 12 mm bend with a
    random network, unanchored and with gradients as in training, two bodies' states and the
    weights' gradients are those of steps that each evaluate it afresh."""
    torch = pytest.importorskip("torch")
    net, model, mesh, z0, forces, steps = _two_bent_bodies(corotated=False)

    def states_and_gradients(once):
        net.zero_grad()
        with torch.enable_grad():
            if once:
                pred = model.rollouts(z0, forces, *mesh, steps, True)[:, 1:]
            else:
                u, v, a, G, H, h = model.begin(z0, forces[:, 0], *mesh, True)
                out = []
                for s in range(1, steps + 1):
                    u, v, a, G, H, h = model.advance(u, v, a, G, H, h, forces[:, s], *mesh, True)
                    out.append(model.state(u, v, H, h))
                pred = torch.stack(out, 1)
            pred[..., 3:6].pow(2).sum().backward()
        return pred.detach(), torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None])

    (a, ga), (b, gb) = states_and_gradients(True), states_and_gradients(False)
    assert float((a - b).norm() / b.norm()) < 1e-12
    assert float(gb.norm()) > 0 and float((ga - gb).norm() / gb.norm()) < 1e-10


def test_recomputed_rollouts_give_the_same_states_and_gradients():
    """``train.rollout_recompute`` (``LinearPriorModel.roll`` with ``recompute``: each step's graph
    recomputed in the backward pass, what lets the shell train on whole 40-step trajectories in
    2 GiB instead of over 24): on the damped 12 mm bend with the corotated prior and a random
    second-order network, two bodies' states and the weights' gradients through
    ``loss.backward()`` are those of the rollout that keeps every step's graph."""
    torch = pytest.importorskip("torch")
    net, model, mesh, z0, forces, steps = _two_bent_bodies(corotated=True)

    def states_and_gradients(recompute):
        net.zero_grad()
        with torch.enable_grad():
            r0 = model.rest_rates_once(2, *mesh, True)
            start = model.begin(z0, forces[:, 0], *mesh, True, r0)
            pred = model.roll(*start, forces, *mesh, steps, True, r0, recompute)
            pred[:, 1:, :, 3:12].pow(2).sum().backward()
        return pred.detach(), torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None])

    (a, ga), (b, gb) = states_and_gradients(True), states_and_gradients(False)
    assert float((a - b).norm() / b.norm()) < 1e-12
    assert float(gb.norm()) > 0 and float((ga - gb).norm() / gb.norm()) < 1e-10


@pytest.mark.parametrize("prony", [(), ((0.4, 4e-3),)])
def test_corotated_solid_is_the_linearised_one_frozen_and_nearer_the_fe_where_cells_turn(prony):
    """``thermognn.core.corotated`` on the FE solid's own data (the bent block, Rayleigh damping,
    elastic and viscous): ``linear_solid`` carries the law's moduli at rest, from which the P1
    cells' K_e assemble to its stiffness K (and K_iso) to round-off; with the rotations frozen the
    corotated rollout is the linearised model's (u, v and the node-averaged σ); turning with the
    cells it re-simulates the 1 N bend nearer the FE in u, v and σ than the linearised model, and
    at 1 mN it is the linearised model to the load's order (1e-3 of its response)."""
    from shapes import assembled  # tests/shapes.py

    from thermognn.core.corotated import CorotatedSolid, element_stiffness

    errors = {}
    for load in (1e-3, 1.0):
        s, layout, traj = _bent_block(load, steps=12, prony=prony)
        linear = modes.linear_solid(s)
        mu, kappa = 2.0e4, 2.0e5                             # C10 = 1e4 Pa, D1 = 1e-5 1/Pa
        assert linear.shear_modulus == pytest.approx(mu) and linear.bulk_modulus == pytest.approx(kappa)
        tets = s.cells[:, :4]
        if load == 1.0:
            idx = np.flatnonzero(linear.free)
            for Ke, stored in zip(element_stiffness(s.nodes, tets, kappa - 2 * mu / 3, mu),
                                  (linear.stiffness, linear.stiffness_iso)):
                if stored is None:
                    continue
                full = assembled(s.nodes, tets, Ke)
                stored = stored.toarray() if hasattr(stored, "toarray") else stored
                assert np.abs(full[np.ix_(idx, idx)] - stored).max() < 1e-9 * np.abs(stored).max()
            frozen = CorotatedSolid.of(linear, s.nodes, tets, frozen=True)
            plain = linear.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3)
            assert np.abs(frozen.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3) - plain).max() \
                < 1e-9 * np.abs(plain).max()
        corotated = CorotatedSolid.of(linear, s.nodes, tets)
        for name, model in (("linear", linear), ("corotated", corotated)):
            pred = model.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3)        # [S, N, D]
            errors[load, name] = {g: np.linalg.norm(pred[..., layout.slice(g)] - traj.z[..., layout.slice(g)])
                                  / np.linalg.norm(traj.z[..., layout.slice(g)] - (s.nodes if g == "q" else 0))
                                  for g in ("q", "v", "sigma")}
        assert corotated.count.unconverged == 0
    for g in ("q", "v", "sigma"):
        assert errors[1.0, "corotated"][g] < 0.6 * errors[1.0, "linear"][g], (g, errors)
        assert errors[1e-3, "corotated"][g] < 1e-2 * errors[1.0, "corotated"][g] + 1e-3, (g, errors)


def _corotated_bend():
    """The damped 12 mm bend (``_bent_block_graph``) as a corotated prior takes it: (``make``,
    which builds its CorotatedNewmarkPrior from the bend's moduli and cells with the prior's
    keyword options, the graph tuple, its cells [T, 4], u, v [S, N, 3], σ [S, N, 6])."""
    import torch

    from thermognn.train.prior import CorotatedNewmarkPrior

    graph = _bent_block_graph()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    mu, kappa = linear.shear_modulus, linear.bulk_modulus
    tets = _bent_block(1.0, "newmark")[0].cells[:, :4]
    make = lambda **options: CorotatedNewmarkPrior(linear, len(X), dt, X, tets, kappa - 2 * mu / 3, mu,  # noqa: E731
                                                   **options)
    return make, graph, tets, z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., 6:12]


def test_the_corotated_solid_reports_where_it_turns_a_cell_inside_out():
    """``CorotatedSolid.first_inversion``: the first state of a rollout with a cell of det F <= 0
    and how many there (a node pushed through the opposite face of its cell; rest and a 10 %
    squeeze turn none), and the clause ``train`` and ``evaluate`` print for it."""
    from thermognn.core.corotated import CorotatedSolid
    from thermognn.train.evaluation import inversion_clause

    _, _, _, X, linear, *_ = _bent_block_graph()
    tets = _bent_block(1.0, "newmark")[0].cells[:, :4]
    solid = CorotatedSolid.of(linear, X, tets)
    squeezed = X * np.array([1.0, 1.0, 0.9])
    a, b, c, d = tets[0]
    normal = np.cross(X[c] - X[b], X[d] - X[b])
    normal /= np.linalg.norm(normal)
    crushed = X.copy()
    crushed[a] -= 2.0 * np.dot(X[a] - X[b], normal) * normal            # a mirrored through face bcd
    assert solid.first_inversion(np.stack([X, squeezed])) is None
    step, cells = solid.first_inversion(np.stack([X, squeezed, crushed, crushed]))
    assert step == 2 and 1 <= cells <= int((tets == a).any(1).sum())
    assert inversion_clause({"inverted": []}) == ""
    assert inversion_clause({"inverted": [("traj_14", 5, 1), ("traj_45", 7, 3)]}) == (
        " (it turns cells inside out on traj_14 from step 5 (1 cell), traj_45 from step 7 (3 cells):"
        " its rollout is meaningless there)")


def test_training_windows_that_turn_a_cell_inside_out_are_left_out_of_the_loss():
    """A rollout window of the corotated prior that turns a cell inside out (here the bend's
    loads x 100) has left the prior's physics: ``_RolloutPhase`` leaves it out of the loss (and
    counts it), so in a batch beside a sound window the loss is that window's alone, and alone
    the loss is zero and still back-propagates; the linearised prior has no cells to turn."""
    torch = pytest.importorskip("torch")
    from thermognn.train.data import Graph, TrajectoryTensors
    from thermognn.train.hybrid import LinearPriorModel, _RolloutPhase
    from thermognn.train.model import TIGNN
    from thermognn.train.prior import NewmarkPrior

    make, graph, _, _, _, _ = _corotated_bend()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    g = Graph(torch.as_tensor(X, dtype=torch.float32), edges, node_type, torch.zeros(0, 3, dtype=torch.long))
    times = torch.arange(len(f)) * dt
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True)
    net.set_stats({"dzdt_std": torch.full((12,), 1e-2)})
    model = LinearPriorModel(net, make(sweeps=2), torch.as_tensor(X), order=2)
    trajs = [TrajectoryTensors("sound", z, f, times), TrajectoryTensors("crushing", z, 100.0 * f, times)]
    phase = _RolloutPhase(model, trajs, window=3, scale="trajectory")
    with torch.enable_grad():
        sound = float(phase.loss([(0, 0)], g.copies(1))[0])
        assert phase.left_out == 0 and sound > 0
        both = float(phase.loss([(0, 0), (1, 0)], g.copies(2))[0])
        assert phase.left_out == 1 and both == pytest.approx(sound, rel=1e-9)
        crushed = phase.loss([(1, 0)], g.copies(1))[0]
        assert phase.left_out == 2 and float(crushed) == 0.0
        crushed.backward()                                   # a batch left out still steps the optimiser
    x = torch.as_tensor(X).unsqueeze(0)
    assert not bool(model.prior.inverted(x).any())
    assert not bool(NewmarkPrior(linear, len(X), dt).inverted(x).any())


def test_corotated_prior_is_the_corotated_fe_model_and_with_the_exact_remainders_the_fe_step():
    """``CorotatedNewmarkPrior`` (``model.prior_corotated``) on the damped 12 mm bend: its polar
    rotations match the SVD's and are differentiable at rest (F = I); with G = H = 0 it steps as
    ``CorotatedSolid`` with as many sweeps (u, v, σ to round-off); with the remainders it
    recovers from the FE trajectory it reproduces that trajectory to the sweeps' convergence
    (8 sweeps: to 1e-8, 1e-7 in v); those remainders are smaller than the linearised prior's (it need not
    learn the rotations). In a LinearPriorModel it steps its carried state as its batched
    rollout, scripted too."""
    torch = pytest.importorskip("torch")
    from thermognn.core.corotated import CorotatedSolid
    from thermognn.core.kinematics import polar_rotations
    from thermognn.train.prior import NewmarkPrior, polar_rotation

    gen = torch.Generator().manual_seed(0)
    F = torch.eye(3, dtype=torch.float64) + 0.2 * torch.randn(64, 3, 3, generator=gen, dtype=torch.float64)
    F = F[torch.linalg.det(F) > 0.2]
    assert float((polar_rotation(F) - torch.as_tensor(polar_rotations(F.numpy()))).abs().max()) < 1e-12
    rest = torch.eye(3, dtype=torch.float64).unsqueeze(0).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda A: polar_rotation(A), (rest,))

    make, graph, s_tets, u, v, sigma = _corotated_bend()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    prior = make(sweeps=8)
    G, H = prior.remainders(u, v, sigma, f)
    U, V, Sig = _prior_rollout(prior, u, v, f, G, H)
    assert _rel(U, u) < 1e-8 and _rel(V, v) < 1e-7 and _rel(Sig, sigma) < 1e-8
    G_lin, H_lin = NewmarkPrior(linear, len(X), dt).remainders(u, v, sigma, f)
    assert float(G.norm()) < 0.5 * float(G_lin.norm()) and float(H.norm()) < 0.5 * float(H_lin.norm())
    prior = make(sweeps=3)
    U, V, Sig = _prior_rollout(prior, u, v, f, torch.zeros_like(G), None)
    fe = torch.as_tensor(CorotatedSolid.of(linear, X, s_tets, max_sweeps=3, tol=0.0)
                         .rollout_states(traj.z, traj.force, X, layout, dt))
    assert _rel(U, fe[..., 0:3] - torch.as_tensor(X)) < 1e-10 and _rel(V, fe[..., 3:6]) < 1e-10
    assert _rel(Sig, fe[..., 6:12]) < 1e-10
    threads = torch.get_num_threads()                                 # a batch steps as its samples alone,
    torch.set_num_threads(2)                                          # with two threads too (solve_each)
    try:
        G2 = torch.cat([G[2:3], 2 * G[2:3]])
        pair = prior.step(prior.gather(u[1:3]), prior.gather(v[1:3]), prior.gather(v[1:3]), prior.gather(f[2:4]),
                          G2, G2, prior.internal_variables(prior.gather(u[1:3])))[0]
        alone = torch.cat([prior.step(prior.gather(u[k:k + 1]), prior.gather(v[k:k + 1]), prior.gather(v[k:k + 1]),
                                      prior.gather(f[k + 1:k + 2]), G2[k - 1:k], G2[k - 1:k],
                                      prior.internal_variables(prior.gather(u[k:k + 1])))[0] for k in (1, 2)])
    finally:
        torch.set_num_threads(threads)
    assert _rel(pair, alone) < 1e-12
    bad = prior.gather(u[1:2]) * float("nan")                          # a state gone non-finite
    with pytest.raises(RuntimeError, match="corotated prior: a non-finite state"):
        prior.step(bad, bad, bad, prior.gather(f[1:2]), G[:1], G[1:2], prior.internal_variables(bad))

    model, batched = _carried_steps_follow_rollouts(prior, graph)
    assert _rel(batched[..., 3:6], fe[..., 3:6]) > 1e-6                     # the network corrects something
    ref = torch.as_tensor(X, dtype=torch.float32)
    with torch.enable_grad():               # rollouts back-propagate through the rotations and the solves
        loss = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, 3, True)[0, -1, :, 3:6].square().sum()
        loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.net.parameters() if p.requires_grad)


def _carried_steps_follow_rollouts(prior, graph, width: int = 0, inputs: str = "positions", cut_loads: str = "end",
                                   optimized: bool = True):
    """A LinearPriorModel on ``prior`` with a tiny seeded network seeing ``inputs``
    (``model.prior_inputs``) and a cut step's sub-steps loaded as ``cut_loads`` says
    (``model.prior_cut_loads``), on the bent block's ``graph`` (``_bent_block_graph``): its carried
    step, eager and scripted (with TorchScript's graph-executor optimisation ``optimized``, as a
    program loading the exported file with torch's defaults steps it; off is serve's), follows its
    batched rollout (carried states [N, 12 + 6 + width]); returns (model, the batched
    rollout [S, N, 12])."""
    import torch

    from thermognn.train.hybrid import LinearPriorModel
    from thermognn.train.model import TIGNN

    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    ref = torch.as_tensor(X, dtype=torch.float32)
    torch.manual_seed(0)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True)
    net.set_stats({"dzdt_std": torch.full((12,), 1e-2)})
    model = LinearPriorModel(net, prior, torch.as_tensor(X), positions_only=inputs == "positions", order=2,
                             correction=inputs == "correction", cut_loads=cut_loads)
    with torch.enable_grad(), torch.jit.optimized_execution(optimized):
        batched = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]
        for stepper in (model, torch.jit.script(model)):
            states = [stepper.carry(z[0], f[0], edges, node_type, ref)]
            assert states[0].shape == (len(X), 12 + 6 + width + (3 if cut_loads == "linear" else 0))
            for k in range(1, len(f)):
                states.append(stepper.step(states[-1], f[k], edges, node_type, ref, torch.tensor(dt)))
            assert float((torch.stack(states)[..., :12] - batched).norm() / batched.norm()) < 1e-9
    return model, batched


def test_relaxing_corotated_prior_is_the_relaxing_corotated_fe_model():
    """``CorotatedNewmarkPrior(relax=True)`` (``model.prior_corotated`` with ``model.prior_relax``)
    on the viscous 12 mm bend (two Prony terms, damped): each cell's isochoric stress history in
    its rotated frame gives the force K_iso,e of the history exactly (closed form), so with G = H = 0
    it steps as the relaxing ``CorotatedSolid`` with as many sweeps (u, v to round-off; its σ, whose
    history the force balances, within a few per cent of that model's, which differences each step's
    strain in its own frame); with the exact remainders it reproduces the FE trajectory, and those
    are a tenth of the relaxing linearised prior's. Its per-cell variables pack into nodal columns
    and back exactly, and a LinearPriorModel on it steps its carried state as its rollouts, scripted
    too."""
    torch = pytest.importorskip("torch")
    from thermognn.core.corotated import CorotatedSolid, element_stiffness
    from thermognn.train.prior import CorotatedNewmarkPrior, NewmarkPrior

    terms = ((0.4, 4e-3), (0.2, 2e-2))
    graph = _bent_block_graph(steps=12, prony=terms)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    tets = _bent_block(1.0, "newmark", steps=2, prony=terms)[0].cells[:, :4]
    mu, kappa = linear.shear_modulus, linear.bulk_modulus
    make = lambda sweeps: CorotatedNewmarkPrior(linear, len(X), dt, X, tets, kappa - 2 * mu / 3, mu,  # noqa: E731
                                                sweeps=sweeps, relax=True)
    u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., 6:12]
    prior = make(3)
    assert prior.n_terms == 2 and prior.internal_columns() == [("prony_cells_1", prior.cell_columns),
                                                                ("prony_cells_2", prior.cell_columns)]
    # the force of a cell's isochoric stress is K_iso,e of its displacement
    d = 1e-3 * torch.randn(1, len(X), 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    Fd = prior.deformation_gradients(torch.as_tensor(X).unsqueeze(0) + d)
    K_iso = torch.as_tensor(element_stiffness(X, tets, kappa - 2 * mu / 3, mu)[1])
    assert _rel(prior.cell_force(prior.deviatoric_stress(torch.eye(3, dtype=torch.float64).expand_as(Fd), Fd)),
               torch.einsum("tij,btj->bti", K_iso, d[:, torch.as_tensor(tets)].reshape(1, len(tets), 12))) < 1e-12

    G0 = torch.zeros(len(f), prior.n_free, dtype=torch.float64)
    U, V, Sig = _prior_rollout(prior, u, v, f, G0, None)
    fe = torch.as_tensor(CorotatedSolid.of(linear, X, tets, max_sweeps=3, tol=0.0)
                         .rollout_states(traj.z, traj.force, X, layout, dt))
    assert _rel(U, fe[..., 0:3] - torch.as_tensor(X)) < 1e-12 and _rel(V, fe[..., 3:6]) < 1e-12
    lin = torch.as_tensor(linear.rollout_states(traj.z, traj.force, X, layout, dt))
    assert _rel(Sig, fe[..., 6:12]) < 0.05 < _rel(fe[..., 6:12], lin[..., 6:12])      # measured 0.034; 0.20
    prior8 = make(8)
    G, H = prior8.remainders(u, v, sigma, f)
    U, V, Sig = _prior_rollout(prior8, u, v, f, G, H)
    assert _rel(U, u) < 1e-6 and _rel(V, v) < 1e-6 and _rel(Sig, sigma) < 1e-6      # the sweeps' convergence
    G_lin, H_lin = NewmarkPrior(linear, len(X), dt, relax=True).remainders(u, v, sigma, f)
    assert float(G.norm()) < 0.2 * float(G_lin.norm()) and float(H.norm()) < 0.2 * float(H_lin.norm())
    h = torch.randn(2, 2, 6 * len(tets), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    packed = prior.pack_internal(h)                                         # [2, N, 2 cell_columns]
    assert packed.shape == (2, len(X), 2 * prior.cell_columns) and torch.equal(prior.unpack_internal(packed), h)

    _carried_steps_follow_rollouts(prior, graph, width=2 * prior.cell_columns)


def test_corotated_step_solves_sparse_on_the_cpu_as_dense():
    """On the CPU the corotated prior factorises each sweep's system by sparse LU (scipy;
    ``SparseSolve``), on a GPU and in TorchScript densely: on the relaxing viscous bend the two
    give the same step, and the same gradients through the solve and the rotations (to
    round-off); the sparse pattern holds the mass and every cell's pairs."""
    torch = pytest.importorskip("torch")
    from thermognn.train.prior import CorotatedNewmarkPrior

    terms = ((0.4, 4e-3), (0.2, 2e-2))
    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph(steps=12, prony=terms)
    tets = _bent_block(1.0, "newmark", steps=2, prony=terms)[0].cells[:, :4]
    mu, kappa = linear.shear_modulus, linear.bulk_modulus
    prior = CorotatedNewmarkPrior(linear, len(X), dt, X, tets, kappa - 2 * mu / 3, mu, sweeps=3, relax=True)
    Xt = torch.as_tensor(X)
    u, v, forces = prior.gather(z[..., 0:3] - Xt), prior.gather(z[..., 3:6]), prior.gather(f)

    def step(sparse: bool):
        prior.sparse_cpu = sparse
        G = (1e-3 * torch.randn(2, prior.n_free, generator=torch.Generator().manual_seed(0),
                                dtype=torch.float64)).requires_grad_(True)
        u0 = u[5:7].clone().requires_grad_(True)                      # two states mid-way: a batch
        h = prior.internal_variables(u0)
        a = prior.initial_acceleration(u0, v[5:7], forces[5:7], G)
        u1, v1, _, h1 = prior.step(u0, v[5:7], a, forces[6:8], G, 2 * G, h)
        loss = u1.square().sum() + 3.0 * v1.sum() + 1e-12 * h1.square().sum()
        return (u1, v1) + torch.autograd.grad(loss, (G, u0))

    dense, sparse = step(False), step(True)
    assert all(_rel(s, d) < 1e-12 for s, d in zip(sparse, dense)), [_rel(s, d) for s, d in zip(sparse, dense)]
    A = prior.pattern.matrix(np.ones(len(prior.pattern.indices))).toarray()
    assert A[np.asarray(linear.mass.toarray() != 0)].all()
    assert int(prior.pair_slot.max()) < len(prior.pattern.indices) == int((A != 0).sum())


def test_material_stress_prior_is_the_neo_hookean_law_and_the_fe_stress_exactly():
    """``model.prior_stress=material``: :func:`neo_hookean_cauchy` against closed forms (rest,
    uniform dilation, simple shear) and smooth at F = I; a corotated prior taking its stress from
    the bent block's own neo-Hookean law leaves no stress remainder of the FE data (H to round-off,
    where the corotated linear stress leaves some), and with the force remainder G alone its
    rollout is the FE trajectory, σ included."""
    torch = pytest.importorskip("torch")
    from thermognn.train.prior import neo_hookean_cauchy

    c10, d1 = 1.0e4, 1.0e-5                                            # _bent_block's material
    eye = torch.eye(3, dtype=torch.float64)
    assert float(neo_hookean_cauchy(eye, c10, d1).abs().max()) == 0.0
    s = 1.01                                                           # dilation: pressure 2 (J - 1) / D1
    assert torch.allclose(neo_hookean_cauchy(s * eye, c10, d1), 2.0 / d1 * (s**3 - 1.0) * eye, rtol=1e-12)
    g = 0.3                                                            # simple shear x += g y: J = 1, σ = 2 C10 dev(B)
    F = eye.clone()
    F[0, 1] = g
    expected = 2.0 * c10 * torch.tensor([[2 * g**2 / 3, g, 0.0], [g, -g**2 / 3, 0.0], [0.0, 0.0, -g**2 / 3]],
                                        dtype=torch.float64)
    assert torch.allclose(neo_hookean_cauchy(F, c10, d1), expected, rtol=1e-12, atol=1e-9)
    rest = eye.unsqueeze(0).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda A: neo_hookean_cauchy(A, c10, d1), (rest,))

    make, graph, _, u, v, sigma = _corotated_bend()
    f = graph[-1]
    linear_stress, law = make(sweeps=8), make(sweeps=8, neo_hookean=(c10, d1))
    G, H = law.remainders(u, v, sigma, f)
    G_lin, H_lin = linear_stress.remainders(u, v, sigma, f)
    assert _rel(G, G_lin) == 0.0                                        # the force is the corotated one still
    assert float(H.norm()) < 1e-10 * float(sigma.norm()) < float(H_lin.norm())
    U, V, Sig = _prior_rollout(law, u, v, f, G, None)                 # no H: σ from the law of U
    assert _rel(U, u) < 1e-8 and _rel(V, v) < 1e-7 and _rel(Sig, sigma) < 1e-8


@pytest.mark.parametrize("law,prony", [
    (("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}), ()),
    (("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}), ((0.4, 4e-3),)),
    (("ogden", {"mu": [2.0e4], "alpha": [8.0], "D": [1.0e-5]}), ((0.4, 4e-3),)),
])
def test_hyperelastic_solid_is_the_fe_solid_and_one_newton_iteration_its_linearly_implicit_step(law, prony):
    """``thermognn.core.hyperelastic`` (numpy, no dolfinx) on the FE solid's own data (the 1 N
    bend: Rayleigh αM and βK, elastic and viscous; neo-Hookean, and Ogden through the FE's
    regularised eigenvalues): iterated to the tolerance it re-simulates the FE rollout to
    round-off in u, v and the node-averaged σ; with one Newton iteration a step (the linearly
    implicit step) it is close but not exact, and a second iteration closes most of the gap, as
    the budget does with dolfinx (``benchmarks/newton_budget.py``)."""
    from thermognn.core.hyperelastic import HyperelasticSolid

    s, layout, traj = _bent_block(1.0, steps=12, prony=prony, law=law)
    linear = modes.linear_solid(s)
    material = {"law": law[0], **law[1], "prony": [{"g": g, "tau": t} for g, t in prony]}
    errors = {}
    for budget in (0, 1, 2):
        solid = HyperelasticSolid.of(linear, s.nodes, s.cells[:, :4], material, iterations=budget)
        pred = solid.rollout_states(traj.z, traj.force, s.nodes, layout, 2e-3)
        errors[budget] = {g: np.linalg.norm(pred[..., layout.slice(g)] - traj.z[..., layout.slice(g)])
                          / np.linalg.norm(traj.z[..., layout.slice(g)] - (s.nodes if g == "q" else 0))
                          for g in ("q", "v", "sigma")}
        if budget == 0:
            assert solid.newton_iterations >= 2 * solid.steps        # a nonlinear bend: more than one a step
    for g in ("q", "v", "sigma"):
        assert errors[0][g] < 1e-8, (g, errors)
        assert 1e-8 < errors[1][g] < 0.1, (g, errors)
        assert errors[2][g] < 0.2 * errors[1][g], (g, errors)
    with pytest.raises(ValueError, match="scene.material.law 'mooney' is not reproduced"):
        HyperelasticSolid.of(linear, s.nodes, s.cells[:, :4], {"law": "mooney"})


@pytest.mark.parametrize("law,prony", [
    (("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}), ()),
    (("ogden", {"mu": [2.0e4], "alpha": [8.0], "D": [1.0e-5]}), ((0.4, 4e-3),)),
])
def test_law_prior_is_the_budgeted_fe_solid_and_its_remainders_of_the_data_vanish(law, prony):
    """``HyperelasticNewmarkPrior`` (``model.prior_law``, torch) on the FE solid's own data (the
    damped 1 N bend; neo-Hookean, and viscous Ogden): with G = H = 0 and k Newton iterations a step
    it is the numpy ``HyperelasticSolid`` with the same budget (u, v, σ to round-off; k = 1, the
    linearly implicit step, is not the FE's), converged it is the FE rollout, so the exact
    remainders of the data vanish; its sparse solve is the dense one; a LinearPriorModel on it
    steps its carried state as its rollouts, scripted too; the config names what it cannot combine."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.hyperelastic import HyperelasticSolid, law_from_config
    from thermognn.train.hybrid import prior_settings
    from thermognn.train.law_prior import HyperelasticNewmarkPrior

    graph = _bent_block_graph(steps=12, prony=prony, law=law)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    tets = _bent_block(1.0, "newmark", steps=2, prony=prony, law=law)[0].cells[:, :4]
    material = {"law": law[0], **law[1], "prony": [{"g": g, "tau": t} for g, t in prony]}
    lam, mu = linear.lame()
    make = lambda k: HyperelasticNewmarkPrior(linear, len(X), dt, X, tets, lam, mu,  # noqa: E731
                                              law_from_config(material)[0], iterations=k)
    u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., 6:12]
    G0 = torch.zeros(len(f), int(linear.free.sum()), dtype=torch.float64)
    for k in (1, 2):
        prior = make(k)
        assert prior.n_terms == len(prony)
        U, V, Sig = _prior_rollout(prior, u, v, f, G0, None)
        fe = torch.as_tensor(HyperelasticSolid.of(linear, X, tets, material, iterations=k)
                             .rollout_states(traj.z, traj.force, X, layout, dt))
        assert _rel(U, fe[..., 0:3] - torch.as_tensor(X)) < 1e-10 and _rel(V, fe[..., 3:6]) < 1e-9
        assert _rel(Sig, fe[..., 6:12]) < 1e-9
        if k == 1:
            assert 1e-4 < _rel(V, v) < 0.05                                  # measured 2.3e-3
    prior = make(6)
    U, V, Sig = _prior_rollout(prior, u, v, f, G0, None)
    assert _rel(U, u) < 1e-12 and _rel(V, v) < 1e-12 and _rel(Sig, sigma) < 1e-12
    assert int(prior.shortened) == 0                      # the data's steps are taken whole
    G, H = prior.remainders(u, v, sigma, f)
    assert float(G.abs().max()) < 1e-10 * float(f.abs().max()) and float(H.abs().max()) < 1e-12 * float(sigma.abs().max())
    # what the budget leaves (train.fit_target=budget): the remainders that land each budgeted step
    # from a data state on the next; stepped from rest with them, the budgeted prior is the FE rollout
    from types import SimpleNamespace

    from thermognn.train.hybrid import budget_remainders
    for k in (1, 2):
        prior = make(k)
        model = SimpleNamespace(prior=prior, reference_positions=torch.as_tensor(X))
        (Gb,), (miss,) = budget_remainders(model, [SimpleNamespace(z=z, force=f)])
        assert miss < 1e-10
        assert float(prior.remainders(u, v, sigma, f)[1].abs().max()) < 1e-12 * float(sigma.abs().max())  # H kept
        assert float(Gb.norm()) > 1e-7 * float(f.norm())          # not round-off (k = 1: 1.6e-6 of the loads)
        U, V, Sig = _prior_rollout(prior, u, v, f, prior.gather(Gb), None)
        assert _rel(U, u) < 1e-9 and _rel(V, v) < 1e-8 and _rel(Sig, sigma) < 1e-9, (k, _rel(U, u), _rel(V, v))
    # the CPU's sparse LU and the dense solve (TorchScript, GPU) step alike
    prior = make(2)
    uf, vf = prior.gather(u[3:4]), prior.gather(v[3:4])
    h = prior.internal_variables(uf)
    a = prior.initial_acceleration(uf, vf, prior.gather(f[3:4]), G0[:1])
    sparse_step = prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)[0]
    prior.sparse_cpu = False
    assert _rel(prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)[0], sparse_step) < 1e-12
    # ... and so does the dense path's block-tridiagonal factor (the shell's and the bunny's; forced
    # here, where a dense LU is as cheap), by its solve and by the step start it keeps
    dense_blocks = prior.band_blocks
    prior.set_band(float("inf"))
    assert prior.band_blocks >= 2 and prior.band_width < prior.n_free
    b = torch.randn(2, prior.n_free, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    pairs = prior.tangent_pairs(prior.cells(uf), 1.0, 1.0, None).expand(2, -1)
    assert _rel(prior.solve(pairs, b), prior.law_solve(pairs, b)) < 1e-12
    prior.forget()
    assert _rel(prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)[0], sparse_step) < 1e-12
    assert prior.memo_band_X.shape == (1, prior.band_blocks, prior.band_width, prior.band_width)
    # ... and its one level of nested dissection (the liver's: two halves and a separator), forced too
    prior.set_band(0.0, float("inf"))
    m, sep = prior.dissection_half, prior.dissection_separator
    assert prior.band_blocks == 0 and m > 0 and 0 < sep < prior.n_free and 2 * m + sep >= prior.n_free
    assert _rel(prior.solve(pairs, b), prior.law_solve(pairs, b)) < 1e-12
    prior.forget()
    assert _rel(prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)[0], sparse_step) < 1e-12
    assert prior.memo_sep_lu.shape == (1, sep, sep) and prior.memo_band_X.shape == (1, 2 * m, sep)
    prior.set_band(0.0)                                   # nothing below no flops: the dense LU
    assert prior.band_blocks == 0 == dense_blocks and prior.dissection_half == 0
    # the law's stresses kept for the last F met without a gradient (``law``): by value, never stale
    F1, F2 = prior.cells(uf), prior.cells(1.01 * uf)
    kept = prior.law(F1)[0]
    assert prior.law(F1.clone())[0] is kept and torch.equal(kept, prior.pk2(F1)[0])
    assert torch.equal(prior.law(F2)[1], prior.pk2(F2)[1]) and prior.law(F1)[0] is not kept
    assert prior.law(F1.clone().requires_grad_())[0].requires_grad          # training's: evaluated, not kept
    # ... and so are the cells' F for the last displacements met without a gradient (``cells``)
    u1 = 1.01 * uf
    F3 = prior.cells(u1)
    assert prior.cells(u1.clone()) is F3 and torch.equal(F3, F2)
    u1.mul_(1.5)                                                            # changed in place: not stale
    assert torch.equal(prior.cells(u1), prior.deformation_gradients(prior.positions(u1)))
    assert prior.cells(uf.clone().requires_grad_()).requires_grad           # training's: formed, not kept
    prior.forget()
    assert prior.memo_law_F.numel() == 0 == prior.memo_cells_u.numel()
    # a second step from the same start (a model step's, with the network's G1) reuses the first
    # one's start and factors, by identity on the sparse path and by value on the dense one: the
    # same step as from scratch; a start changed in place, or another one, is not reused
    G1 = 1e-3 * float(f.abs().max()) * torch.randn(1, G0.shape[1], dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    for sparse_cpu in (True, False):
        prior.sparse_cpu = sparse_cpu
        prior.forget()
        first = prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)
        assert (prior._start_memo[0][0] is uf) if sparse_cpu else prior.memo_key.numel() > 0    # kept
        again = prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G1, h)
        prior.forget()
        fresh = prior.step(uf, vf, a, prior.gather(f[4:5]), G0[:1], G1, h)
        assert _rel(again[0] - first[0], fresh[0] - first[0]) < 1e-9 and _rel(again[1], fresh[1]) < 1e-12
        assert _rel(again[3], fresh[3]) < 1e-12 if prior.n_terms else True
        moved = uf.clone()
        prior.step(moved, vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)
        moved.mul_(1.01)                                      # in place: the kept start is stale
        in_place = prior.step(moved, vf, a, prior.gather(f[4:5]), G0[:1], G1, h)
        prior.forget()
        assert _rel(in_place[0], prior.step(moved, vf, a, prior.gather(f[4:5]), G0[:1], G1, h)[0]) < 1e-12
    prior.forget()
    prior.sparse_cpu = True
    # a load far beyond the data's (a haptic tool's contact, issue 4's extreme inputs): the Newton
    # updates that would turn cells inside out are shortened, so the step stays finite with every
    # cell's J > 0 (where the whole update inverts cells); the data's steps above were taken whole
    from thermognn.train.prior import DIVERGED
    kick = 3e3 * prior.gather(f[4:5])
    min_J = lambda u1: float(torch.linalg.det(prior.cells(u1)).min())  # noqa: E731
    prior.j_floor = float("-inf")                         # the updates unshortened (NaN still refused)
    try:
        whole = prior.step(uf, vf, a, kick, G0[:1], G0[:1], h)[0]
        assert not min_J(whole) > 0.0
    except RuntimeError as exc:                           # or the second iteration found it non-finite
        assert DIVERGED in str(exc)
    prior.j_floor = 0.05
    for sparse_cpu in (True, False):
        prior.sparse_cpu = sparse_cpu
        prior.forget()
        prior.shortened.zero_()
        u1, v1, a1, h1 = prior.step(uf, vf, a, kick, G0[:1], G0[:1], h)
        assert all(bool(torch.isfinite(x).all()) for x in (u1, v1, a1, h1)) and min_J(u1) > 0.0
        assert int(prior.shortened) > 0                   # counted, for evaluate to name the rollout
        from thermognn.train.evaluation import shortened_sentence
        assert "traj_9 (3)" in shortened_sentence(["traj_8", "traj_9"], [0, 3]) and not shortened_sentence(["a"], [0])
    prior.forget()
    prior.sparse_cpu = True
    from thermognn.train.prior import DIVERGED
    with pytest.raises(RuntimeError, match="law prior: a non-finite state") as diverged:   # what training catches
        prior.step(uf * float("nan"), vf, a, prior.gather(f[4:5]), G0[:1], G0[:1], h)
    assert DIVERGED in str(diverged.value)
    prior.set_band(float("inf"))                          # scripted, it steps by the block factor
    _carried_steps_follow_rollouts(prior, graph, width=len(prony) * prior.cell_columns)
    prior.set_band(0.0, float("inf"))                     # ... and by the dissection
    _carried_steps_follow_rollouts(prior, graph, width=len(prony) * prior.cell_columns)

    settings = prior_settings(OmegaConf.create({"prior": "linear", "prior_law": True, "prior_newton": 2}))
    assert settings["law"] == 2
    with pytest.raises(ConfigError, match="model.prior_law = true steps the dataset's own law"):
        prior_settings(OmegaConf.create({"prior_law": True, "prior_corotated": True}))
    with pytest.raises(ConfigError, match="model.prior_newton = 0, expected an integer >= 1"):
        prior_settings(OmegaConf.create({"prior_law": True, "prior_newton": 0}))


def _ogden_bend_priors(steps: int):
    """The FE's damped 1 N bend of a viscous Ogden block (``_bent_block_graph``, ``steps`` steps),
    its Prony terms, and ``build(dt=the data's, iterations=1, **options)``: a
    HyperelasticNewmarkPrior of its law on its mesh (options: ``max_iterations``, ``newton_rtol``,
    ``step_cuts``)."""
    from thermognn.core.hyperelastic import law_from_config
    from thermognn.train.law_prior import HyperelasticNewmarkPrior

    law, prony = ("ogden", {"mu": [2.0e4], "alpha": [8.0], "D": [1.0e-5]}), ((0.4, 4e-3),)
    graph = _bent_block_graph(steps=steps, prony=prony, law=law)
    dt, X, linear = graph[2], graph[3], graph[4]
    tets = _bent_block(1.0, "newmark", steps=2, prony=prony, law=law)[0].cells[:, :4]
    material = {"law": law[0], **law[1], "prony": [{"g": g, "tau": t} for g, t in prony]}
    lam, mu = linear.lame()

    def build(step: float = dt, iterations: int = 1, **options):
        return HyperelasticNewmarkPrior(linear, len(X), step, X, tets, lam, mu, law_from_config(material)[0],
                                        iterations=iterations, **options)
    return graph, prony, build


def _ogden_bend_fields(steps: int):
    """``_ogden_bend_priors`` with the data's fields: (graph, prony, build, (u, v [S, N, 3] m, m/s,
    σ [S, N, 6] Pa, f [S, N, 3] N, zero remainders G0 [S, n] N))."""
    import torch

    graph, prony, build = _ogden_bend_priors(steps=steps)
    X, linear, z, f = graph[3], graph[4], graph[7], graph[8]
    u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., 6:12]
    G0 = torch.zeros(len(f), int(linear.free.sum()), dtype=torch.float64)
    return graph, prony, build, (u, v, sigma, f, G0)


def test_law_prior_iterates_past_its_budget_until_the_step_converges():
    """``model.prior_newton_max`` (``HyperelasticNewmarkPrior(max_iterations=...)``) on the FE
    solid's own data (the damped 1 N bend, viscous Ogden): one Newton iteration a step and up to 8
    more while the last update still moves the state is the converged FE rollout to round-off,
    where one iteration always is not; it took more than one iteration a step but fewer than 8
    (``newton_taken``), and at rest it stops at its budget. With the most equal to the budget it is
    the fixed budget to the bit. What the budget leaves (``budget_loads``) is a fixed budget's.
    A LinearPriorModel on it steps its carried state as its rollouts, scripted too; the config
    records it and names what it cannot be."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import model_step
    from thermognn.train.hybrid import prior_settings

    graph, prony, build = _ogden_bend_priors(steps=12)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    make = lambda k, most=None: build(iterations=k, max_iterations=most)  # noqa: E731
    u, v, sigma = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6], z[..., 6:12]
    G0 = torch.zeros(len(f), int(linear.free.sum()), dtype=torch.float64)
    fixed, adaptive = make(1), make(1, 8)
    U1, V1, _ = _prior_rollout(fixed, u, v, f, G0, None)
    U, V, Sig = _prior_rollout(adaptive, u, v, f, G0, None)
    assert _rel(V1, v) > 1e-4                                              # one iteration a step: not the FE's
    assert _rel(U, u) < 1e-11 and _rel(V, v) < 1e-10 and _rel(Sig, sigma) < 1e-10
    taken, steps, unconverged, cut = adaptive.newton_taken.tolist()
    assert steps == len(f) - 1 and steps < taken < 8 * steps and unconverged == 0 and cut == 0
    assert fixed.newton_taken.tolist() == [len(f) - 1, len(f) - 1, 0, 0]
    looser = build(iterations=1, max_iterations=8, newton_rtol=1e-3)
    V3 = _prior_rollout(looser, u, v, f, G0, None)[1]                     # a looser tolerance: fewer, less exact
    assert looser.newton_taken.tolist()[0] < taken and _rel(V, v) < _rel(V3, v) < _rel(V1, v)
    short = make(1, 2)                                                    # 2 at most: not converged, counted
    _prior_rollout(short, u, v, f, G0, None)
    assert short.newton_taken.tolist()[2] > 0
    from thermognn.train.evaluation import newton_sentence
    assert newton_sentence(1, 8, 42, 10, 0) == ("the law prior took 4.20 Newton iterations a step (1 at least, 8 at "
                                                "most a solve, over 10 prior steps)")
    assert "; 3 steps had not converged after 8: those rollouts are not the law's" in newton_sentence(1, 8, 60, 10, 3)
    same = make(1, 1)
    assert torch.equal(_prior_rollout(same, u, v, f, G0, None)[1], V1)   # most = budget: the fixed budget
    rest = make(2, 8)                                                     # at rest nothing moves: 2 iterations
    n = G0.shape[1]
    zero = torch.zeros(1, n, dtype=torch.float64)
    h = rest.internal_variables(zero)
    rest.step(zero, zero, zero, zero, zero, zero, h)
    assert rest.newton_taken.tolist() == [2, 1, 0, 0]
    e_fixed, _ = make(2).budget_loads(fixed.gather(u), fixed.gather(v), fixed.gather(f))
    e_most, _ = make(2, 8).budget_loads(fixed.gather(u), fixed.gather(v), fixed.gather(f))
    assert torch.equal(e_fixed, e_most)                                  # a fixed budget's misses
    _carried_steps_follow_rollouts(make(1, 8), graph, width=len(prony) * adaptive.cell_columns)

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 2}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 6}))
    assert settings["law"] == 2 and settings["law_max"] == 6 and settings["law_rtol"] == 1e-8
    assert "law_max" not in prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 2}))   # = the budget
    assert "law_max" not in prior_settings(OmegaConf.create({**cfg, "prior_newton_max": None}))
    assert "(2 Newton iterations, up to 6 until converged to 1e-08)" in describe_step(model_step({"prior": settings}))
    loose = prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 6, "prior_newton_rtol": 1e-4}))
    assert loose["law_rtol"] == 1e-4 and "converged to 0.0001" in describe_step(model_step({"prior": loose}))
    with pytest.raises(ConfigError, match=r"model.prior_newton_rtol = 0, expected a number in \(0, 1\)"):
        prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 6, "prior_newton_rtol": 0}))
    with pytest.raises(ConfigError, match=r"model.prior_newton_rtol = 0.001 needs model.prior_newton_max > "):
        prior_settings(OmegaConf.create({**cfg, "prior_newton_rtol": 1e-3}))
    with pytest.raises(ConfigError, match=r"model.prior_newton_max = 1, expected >= model.prior_newton = 2"):
        prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 1}))
    with pytest.raises(ValueError, match="most Newton iterations a step: 1, expected >= its iterations"):
        make(2, 1)


#: a Newton tolerance no update meets: 2 iterations to it never converge, so every step is cut
NEVER = 1e-300


def _bend_cut_once():
    """The damped 1 N bend's viscous Ogden priors (``_ogden_bend_priors``, 8 steps): (graph,
    prony, build, its displacements u and velocities v [S, N, 3], remainders G [S, n] that change
    over the rollout (~1e-3 of the loads), the prior that cuts every step once (2 iterations to
    NEVER, cuts 1), the prior built for Δt/2 with the same iterations)."""
    import torch

    graph, prony, build = _ogden_bend_priors(steps=8)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    u, v = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6]
    G = 1e-3 * float(f.abs().max()) * torch.randn(len(f), int(linear.free.sum()), dtype=torch.float64,
                                                   generator=torch.Generator().manual_seed(1))
    cut = build(dt, max_iterations=2, newton_rtol=NEVER, step_cuts=1)
    half = build(dt / 2, max_iterations=2, newton_rtol=NEVER)
    return graph, prony, build, u, v, G, cut, half


def test_law_prior_cuts_a_step_that_has_not_converged_into_the_fe_s_half_steps():
    """``model.prior_step_cuts`` (``HyperelasticNewmarkPrior(step_cuts=...)``) on the FE solid's own
    data (the damped 1 N bend, viscous Ogden): a step still not converged after its most
    iterations is stepped again from its start as two halves, down to Δt / 2^cuts, as the FE
    cuts its steps. Told to converge to round-off in 2 iterations it never does, so every step is
    cut to the floor: it is then, to round-off, two steps of the prior built for Δt/2 (its Newmark
    constants and Prony decays) under the step's end load, with the remainders G interpolated
    linearly over the step, and ``newton_taken`` counts the cuts. Steps that converge are never
    cut (the same rollout as without). A LinearPriorModel on it steps its carried state as its
    rollouts, scripted too; the config records it and names what it cannot be."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import model_step
    from thermognn.train.evaluation import newton_sentence
    from thermognn.train.hybrid import prior_settings

    graph, prony, build, u, v, G, cut, half = _bend_cut_once()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    make = lambda step, most, rtol=None, cuts=0: build(  # noqa: E731
        step, max_iterations=most, newton_rtol=rtol, step_cuts=cuts)
    never = NEVER
    U, V, _ = _prior_rollout(cut, u, v, f, G, None)
    # (measured 6.0 %: the bend's load ramps over its 8 steps, and every step cut here holds it at its end)
    assert torch.isfinite(U).all() and _rel(V, v) < 0.1
    uf, vf = half.gather(u[:1]), half.gather(v[:1])
    h = half.internal_variables(uf)
    a = half.initial_acceleration(uf, vf, half.gather(f[:1]), G[:1])
    assert _rel(a, cut.initial_acceleration(uf, vf, cut.gather(f[:1]), G[:1])) < 1e-12   # (dt-free)
    us, vs = [uf], [vf]
    for k in range(1, len(f)):
        f1, Gm = half.gather(f[k:k + 1]), 0.5 * (G[k - 1:k] + G[k:k + 1])
        uf, vf, a, h = half.step(uf, vf, a, f1, G[k - 1:k], Gm, h)
        uf, vf, a, h = half.step(uf, vf, a, f1, Gm, G[k:k + 1], h)
        us, vs = us + [uf], vs + [vf]
    assert _rel(U, half.scatter(torch.cat(us))) < 1e-10 and _rel(V, half.scatter(torch.cat(vs))) < 1e-9
    steps = len(f) - 1
    # each step: the full step's 2, then the two halves' 2 each; none converged at the floor
    assert cut.newton_taken.tolist() == [6 * steps, steps, steps, steps]
    assert cut.dt == dt and cut.c0 == make(dt, 2).c0                  # the step's own constants put back
    # in a batch only the samples that have not converged are cut: a step of the data beside one
    # under 300 times its load, which 8 iterations do not converge
    batch = make(dt, 8, cuts=2)
    ub, vb = torch.cat([us[3], us[3]]), torch.cat([vs[3], vs[3]])
    hb = batch.internal_variables(ub)
    ab = batch.initial_acceleration(ub, vb, batch.gather(f[3:4]), G[3:4])
    fb = torch.cat([batch.gather(f[4:5]), 300.0 * batch.gather(f[4:5])])
    both = batch.step(ub, vb, ab, fb, G[3:4], G[4:5], hb)
    assert batch.newton_taken.tolist()[3] == 1
    for k in (0, 1):
        batch.forget()
        alone = batch.step(ub[k:k + 1], vb[k:k + 1], ab[k:k + 1], fb[k:k + 1], G[3:4], G[4:5], hb[k:k + 1])
        assert all(_rel(x[k:k + 1], y) < 1e-11 for x, y in zip(both, alone)), k
    assert batch.newton_taken.tolist()[3] == 2                         # the second alone: cut again
    # steps that converge are never cut: the rollout without cuts, to the bit
    plain, cutting = make(dt, 8), make(dt, 8, cuts=4)
    assert torch.equal(_prior_rollout(plain, u, v, f, G, None)[1], _prior_rollout(cutting, u, v, f, G, None)[1])
    assert cutting.newton_taken.tolist()[3] == 0
    _carried_steps_follow_rollouts(make(dt, 2, never, cuts=2), graph, width=len(prony) * cut.cell_columns)

    sentence = newton_sentence(1, 2, 6 * steps, steps, steps, steps, step_cuts=1)
    assert f"; it cut {steps} steps that had not converged after 2 into sub-steps (down to Δt/2)" in sentence
    assert f"; {steps} steps had not converged after 2 (at Δt/2): those rollouts are not the law's" in sentence
    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 8}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_step_cuts": 4}))
    assert settings["law_cuts"] == 4 and model_step({"prior": settings})["law_cuts"] == 4
    assert ", halved down to Δt/16 where not)" in describe_step(model_step({"prior": settings}))
    assert "law_cuts" not in prior_settings(OmegaConf.create({**cfg, "prior_step_cuts": 0}))
    assert "law_cuts" not in prior_settings(OmegaConf.create(cfg))
    with pytest.raises(ConfigError, match=r"model.prior_step_cuts = 5, expected an integer 0 to 4"):
        prior_settings(OmegaConf.create({**cfg, "prior_step_cuts": 5}))
    with pytest.raises(ConfigError, match=r"model.prior_step_cuts = 2 needs model.prior_law = true and "
                                          r"model.prior_newton_max > model.prior_newton"):
        prior_settings(OmegaConf.create({**cfg, "prior_newton_max": 1, "prior_step_cuts": 2}))
    with pytest.raises(ValueError, match="the law prior's step cuts: 1, expected 0 to 4, and more than 0 only with"):
        make(dt, 1, cuts=1)


def test_law_prior_keeps_its_tangent_while_it_contracts():
    """``model.prior_tangent = kept`` (``HyperelasticNewmarkPrior(tangent="kept")``) on the FE
    solid's own data (the damped 1 N bend, viscous Ogden): iterating each step with one tangent's
    factors, kept between iterations and steps and formed afresh only where an update no longer
    halves the residual, converges to the FE rollout as fresh tangents do (to round-off at a tight
    tolerance), forming fewer tangents than there are steps; a looser tolerance stops sooner, less
    exactly. A load 30 times the data's, which the kept tangent does not contract, forms fresh
    ones and lands on the fresh tangents' step; never forming one there, its chords do not
    converge within the most, and the step is taken again with fresh tangents. Along a rollout
    under that load, a step whose Newton update from a chord's iterate does not contract is taken
    again from its predictor with fresh tangents, and every step lands where theirs does (or
    neither converges). At rest, exactly or within float32 round-off, it forms no tangent past
    its first. A second step from the same start (a model step's,
    with its network's remainders) starts where the first ended and lands where a step from
    scratch does. Steps with gradients (training) form fresh tangents, to the bit; a batch of
    another size forms its own; ``forget`` drops it. A LinearPriorModel on it steps its carried
    state as its rollouts, scripted too (the dense factors); the config records it and names what
    it cannot be."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import model_step
    from thermognn.train.hybrid import prior_settings

    graph, prony, build, (u, v, sigma, f, G0) = _ogden_bend_fields(steps=12)
    n = G0.shape[1]
    steps = len(f) - 1
    kept = build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept")
    U, V, Sig = _prior_rollout(kept, u, v, f, G0, None)
    assert _rel(U, u) < 1e-11 and _rel(V, v) < 1e-10 and _rel(Sig, sigma) < 1e-10         # the FE's rollout
    taken, counted, unconverged, cut = kept.newton_taken.tolist()
    assert counted == steps and unconverged == 0 and cut == 0 and taken >= 2 * steps   # chords: 2 at least
    assert 1 <= int(kept.tangents_formed) < steps                                       # tangents kept
    fresh = build(iterations=1, max_iterations=8)
    V_fresh = _prior_rollout(fresh, u, v, f, G0, None)[1]
    assert _rel(V_fresh, v) < 1e-10 and int(fresh.tangents_formed) >= fresh.newton_taken.tolist()[0]
    loose = build(iterations=1, max_iterations=40, newton_rtol=1e-4, tangent="kept")
    V_loose = _prior_rollout(loose, u, v, f, G0, None)[1]
    V_one = _prior_rollout(build(iterations=1), u, v, f, G0, None)[1]
    assert loose.newton_taken.tolist()[0] < taken and _rel(V, v) < _rel(V_loose, v) < _rel(V_one, v)

    # from a state of the data, under 30 times its next load
    s0 = 3
    uf, vf = kept.gather(u[s0:s0 + 1]), kept.gather(v[s0:s0 + 1])
    h = kept.internal_variables(uf)
    a = kept.initial_acceleration(uf, vf, kept.gather(f[s0:s0 + 1]), G0[:1])
    strong = 30.0 * kept.gather(f[s0 + 1:s0 + 2])
    formed = int(kept.tangents_formed)
    hard = kept.step(uf, vf, a, strong, G0[:1], G0[:1], h)
    assert int(kept.tangents_formed) > formed
    exact = build(iterations=1, max_iterations=40).step(uf, vf, a, strong, G0[:1], G0[:1], h)
    assert _rel(hard[0], exact[0]) < 1e-9 and _rel(hard[1], exact[1]) < 1e-8
    # at rest, unloaded, and at rest with float32 round-off in the displacement (an exported
    # model's carried state, 1e-9 m): no tangent is formed past the first, and no step is cut short
    rest = build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept")
    zero = torch.zeros(1, n, dtype=torch.float64)
    noise = 1e-9 * torch.randn(1, n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    for start in (zero, zero, noise, noise):
        rest.step(start, zero, zero, zero, zero, zero, rest.internal_variables(start))
    assert int(rest.tangents_formed) == 1 and rest.newton_taken.tolist()[2] == 0
    assert rest.newton_taken.tolist()[0] <= 8
    # 30 times the data's loads from each state of the fresh tangents' rollout: where a Newton update
    # from a chord's iterate does not contract either, the step is taken again as fresh tangents take
    # it, from its predictor; each step then lands where theirs does, or neither converges
    fresh40, agile = build(iterations=1, max_iterations=40, newton_rtol=1e-12), build(
        iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept")
    again_fresh = []
    retry = agile.fresh_iterations
    agile.fresh_iterations = lambda *args: (again_fresh.append(1), retry(*args))[1]
    uf30, vf30 = fresh40.gather(u[:1]), fresh40.gather(v[:1])
    h30 = fresh40.internal_variables(uf30)
    a30 = fresh40.initial_acceleration(uf30, vf30, fresh40.gather(30.0 * f[:1]), G0[:1])
    for k in range(1, len(f)):
        load = fresh40.gather(30.0 * f[k:k + 1])
        counts = fresh40.newton_taken.tolist()[2], agile.newton_taken.tolist()[2]
        mine = agile.step(uf30, vf30, a30, load, G0[:1], G0[:1], h30)
        uf30, vf30, a30, h30 = fresh40.step(uf30, vf30, a30, load, G0[:1], G0[:1], h30)
        fresh40.forget()
        if fresh40.newton_taken.tolist()[2] == counts[0]:                  # fresh tangents converged
            assert agile.newton_taken.tolist()[2] == counts[1] and _rel(mine[0], uf30) < 1e-9, k
    assert again_fresh
    # the same start again under remainders ~1e-6 of the loads: from where the first step ended
    G1 = 1e-6 * float(strong.abs().max()) * torch.randn(1, n, dtype=torch.float64,
                                                         generator=torch.Generator().manual_seed(2))
    before = kept.newton_taken.tolist()[0]
    again = kept.step(uf, vf, a, strong, G0[:1], G1, h)
    warm = kept.newton_taken.tolist()[0] - before
    kept.forget()
    assert kept.kept_batch == 0 and kept.kept_end.numel() == 0
    before = kept.newton_taken.tolist()[0]
    cold = kept.step(uf, vf, a, strong, G0[:1], G1, h)
    assert warm < kept.newton_taken.tolist()[0] - before and _rel(again[0], cold[0]) < 1e-9
    # with gradients: fresh tangents, the fresh prior's step to the bit
    fresh1 = build(iterations=1, max_iterations=40, newton_rtol=1e-12)
    ug = uf.clone().requires_grad_(True)
    assert all(torch.equal(x, y) for x, y in zip(kept.step(ug, vf, a, strong, G0[:1], G1, h),
                                                  fresh1.step(ug, vf, a, strong, G0[:1], G1, h)))
    # a batch of two: its own tangents; then one sample alone forms one again
    ub, vb, ab, hb = (torch.cat([x, x]) for x in (uf, vf, a, h))
    gentle = kept.gather(f[s0 + 1:s0 + 2])
    both = kept.step(ub, vb, ab, torch.cat([gentle, 2.0 * gentle]), G0[:2], G0[:2], hb)
    assert kept.kept_batch == 2
    for k, load in enumerate((gentle, 2.0 * gentle)):
        alone = fresh1.step(uf, vf, a, load, G0[:1], G0[:1], h)
        assert _rel(both[0][k:k + 1], alone[0]) < 1e-9 and _rel(both[1][k:k + 1], alone[1]) < 1e-8
    formed = int(kept.tangents_formed)
    kept.step(uf, vf, a, gentle, G0[:1], G0[:1], h)
    assert kept.kept_batch == 1 and int(kept.tangents_formed) > formed
    # a kept tangent that never forms a fresh one (any contraction accepted): from the gentle
    # step's tangent the strong load's chords do not converge within the most, and the step is
    # taken again with fresh tangents, which land it
    kept.kept_contraction = float("inf")
    before = kept.newton_taken.tolist()
    chords = kept.step(uf, vf, a, strong, G0[:1], G0[:1], h)
    after = kept.newton_taken.tolist()
    assert after[0] - before[0] > 40 and after[2] == before[2] and _rel(chords[0], exact[0]) < 1e-9
    kept.kept_contraction = 0.5
    _carried_steps_follow_rollouts(build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept"), graph,
                                   width=len(prony) * kept.cell_columns)

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 16, "prior_newton_rtol": 1e-7}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_tangent": "kept"}))
    assert settings["law_tangent"] == "kept" and model_step({"prior": settings})["law_tangent"] == "kept"
    assert ", its tangent kept while it contracts)" in describe_step(model_step({"prior": settings}))
    assert "law_tangent" not in prior_settings(OmegaConf.create({**cfg, "prior_tangent": "fresh"}))
    with pytest.raises(ConfigError, match=r"model.prior_tangent = 'old', expected fresh \| kept"):
        prior_settings(OmegaConf.create({**cfg, "prior_tangent": "old"}))
    with pytest.raises(ConfigError, match=r"model.prior_tangent = kept needs model.prior_law = true and "
                                          r"model.prior_newton_max > model.prior_newton"):
        prior_settings(OmegaConf.create({"prior": "linear", "prior_law": True, "prior_tangent": "kept"}))
    with pytest.raises(ValueError, match=r"the law prior's tangent: 'kept', expected one of fresh \| kept, and kept "):
        build(iterations=1, tangent="kept")


def test_law_prior_mixes_its_chord_updates_by_anderson():
    """``model.prior_anderson`` (``HyperelasticNewmarkPrior(tangent="kept", anderson=m)``) on the FE
    solid's own data (the damped 1 N bend, viscous Ogden): each chord update mixed with up to m
    earlier ones of the same tangent (Anderson's method) converges to the FE rollout as plain
    chords do, forming fewer tangents (a mixed update may contract less before one is formed);
    a step under a load 3 times the data's, from a state of the data, lands where fresh tangents
    land it; a batch of two loads steps each as alone; at rest the mixing stays finite and forms no
    tangent past the first. The mixing itself, from one earlier iterate: the new iterate mixes the
    two iterates' chord images with the weights whose updates mix to the least norm; a sample
    whose updates do not change mixes nothing. Scripted, the
    carried step follows the rollouts; the config records it, export serves 2, and the values it
    cannot take are named."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import SERVED_LAW_STEP, model_step, served_law_step
    from thermognn.train.hybrid import prior_settings

    graph, prony, build, (u, v, sigma, f, G0) = _ogden_bend_fields(steps=12)
    n = G0.shape[1]
    plain = build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept")
    mixed = build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept", anderson=2)
    assert plain.kept_contraction == 0.5 and mixed.kept_contraction == 0.7
    _prior_rollout(plain, u, v, f, G0, None)
    U, V, Sig = _prior_rollout(mixed, u, v, f, G0, None)
    assert _rel(U, u) < 1e-11 and _rel(V, v) < 1e-10 and _rel(Sig, sigma) < 1e-10         # the FE's rollout
    assert mixed.newton_taken.tolist()[1:] == [len(f) - 1, 0, 0]
    assert 1 <= int(mixed.tangents_formed) < int(plain.tangents_formed)
    # from a state of the data under 3 times its next load, a tangent kept from the data's load
    s0 = 3
    fresh = build(iterations=1, max_iterations=40, newton_rtol=1e-12)
    uf, vf = fresh.gather(u[s0:s0 + 1]), fresh.gather(v[s0:s0 + 1])
    h = fresh.internal_variables(uf)
    a = fresh.initial_acceleration(uf, vf, fresh.gather(f[s0:s0 + 1]), G0[:1])
    gentle, strong = fresh.gather(f[s0 + 1:s0 + 2]), 3.0 * fresh.gather(f[s0 + 1:s0 + 2])
    exact = fresh.step(uf, vf, a, strong, G0[:1], G0[:1], h)
    mixed.step(uf, vf, a, gentle, G0[:1], G0[:1], h)
    hard = mixed.step(uf, vf, a, strong, G0[:1], G0[:1], h)
    assert _rel(hard[0], exact[0]) < 1e-9 and _rel(hard[1], exact[1]) < 1e-8
    # a batch of two: per sample, as alone
    ub, vb, ab, hb = (torch.cat([x, x]) for x in (uf, vf, a, h))
    both = mixed.step(ub, vb, ab, torch.cat([gentle, strong]), G0[:2], G0[:2], hb)
    for k, load in enumerate((gentle, strong)):
        alone = fresh.step(uf, vf, a, load, G0[:1], G0[:1], h)
        assert _rel(both[0][k:k + 1], alone[0]) < 1e-9 and _rel(both[1][k:k + 1], alone[1]) < 1e-8
    # at rest, and at rest with float32 round-off in the displacement
    rest = build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept", anderson=2)
    zero = torch.zeros(1, n, dtype=torch.float64)
    noise = 1e-9 * torch.randn(1, n, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    for start in (zero, zero, noise, noise):
        out = rest.step(start, zero, zero, zero, zero, zero, rest.internal_variables(start))
        assert all(bool(torch.isfinite(x).all()) for x in out)
    assert int(rest.tangents_formed) == 1 and rest.newton_taken.tolist()[2] == 0
    # the mixing, from one earlier iterate, on a linear residual r(x) = A x − b with the chord's
    # update d = K⁻¹ r(x) (subtracted from x), γ the least-squares fit of d1 by d1 − d0
    gen = torch.Generator().manual_seed(5)
    A = torch.eye(4, dtype=torch.float64) + 0.3 * torch.rand(4, 4, dtype=torch.float64, generator=gen)
    K = torch.eye(4, dtype=torch.float64) + 0.1 * torch.rand(4, 4, dtype=torch.float64, generator=gen)
    b = torch.rand(4, dtype=torch.float64, generator=gen)
    x0, x1 = torch.zeros(4, dtype=torch.float64), torch.rand(4, dtype=torch.float64, generator=gen)
    d0, d1 = torch.linalg.solve(K, A @ x0 - b), torch.linalg.solve(K, A @ x1 - b)
    move = mixed.anderson_update(d1[None], (x1 - x0)[None, :, None], (d1 - d0)[None, :, None])[0]
    gamma = float((d1 - d0) @ d1 / ((d1 - d0) @ (d1 - d0)))
    assert torch.allclose(move, d1 + gamma * ((x1 - x0) - (d1 - d0)), rtol=1e-12, atol=0.0)
    # the new iterate mixes the two iterates' chord images x − d with the weights whose updates
    # mix to the least norm
    assert torch.allclose(x1 - move, (1 - gamma) * (x1 - d1) + gamma * (x0 - d0), rtol=0.0, atol=1e-12)
    assert float(((1 - gamma) * d1 + gamma * d0).norm()) <= float(d1.norm())
    still = mixed.anderson_update(d1[None], torch.zeros(1, 4, 1, dtype=torch.float64),
                                  torch.zeros(1, 4, 1, dtype=torch.float64))
    assert torch.equal(still[0], d1)
    # scripted (serve's dense factors, the executor's optimisation off as serve steps it)
    _carried_steps_follow_rollouts(build(iterations=1, max_iterations=40, newton_rtol=1e-12, tangent="kept",
                                         anderson=2), graph, width=len(prony) * mixed.cell_columns, optimized=False)

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 16, "prior_newton_rtol": 1e-7,
           "prior_tangent": "kept"}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_anderson": 2}))
    assert settings["law_anderson"] == 2 and model_step({"prior": settings})["law_anderson"] == 2
    assert ", its chord updates Anderson-mixed with up to 2 earlier ones" in describe_step(model_step({"prior": settings}))
    assert "law_anderson" not in prior_settings(OmegaConf.create(cfg))
    assert SERVED_LAW_STEP["prior_anderson"] == 2
    assert served_law_step({"prior": {"law": 1, "law_max": 16, "law_rtol": 1e-7, "law_tangent": "kept",
                                      "law_search": 6}}) == {"prior_anderson": 2}
    assert served_law_step({"prior": {**settings, "law_search": 6}}) == {}
    for bad, said in ((5, "model.prior_anderson = 5, expected an integer 0 to 4"),
                      (True, "model.prior_anderson = True, expected an integer 0 to 4"),
                      (1.5, "model.prior_anderson = 1.5, expected an integer 0 to 4")):
        with pytest.raises(ConfigError, match=re.escape(said)):
            prior_settings(OmegaConf.create({**cfg, "prior_anderson": bad}))
    with pytest.raises(ConfigError, match=r"model.prior_anderson = 2 needs model.prior_tangent = kept"):
        prior_settings(OmegaConf.create({**cfg, "prior_tangent": "fresh", "prior_anderson": 2}))
    with pytest.raises(ValueError, match=r"the law prior's Anderson mixing: 2, expected 0 \(none\) to 4 earlier chord "
                                         r"updates, and more than 0 only with the tangent kept"):
        build(iterations=1, max_iterations=8, anderson=2)


def test_correction_inputs_are_what_the_budgeted_step_moved_from_its_predictor():
    """``model.prior_inputs = correction``: the network sees, in place of the velocity, the step's
    correction from its predictor w = (u1 − u0) / Δt − v0. Along the FE data it is Newmark's
    Δt ((1/2 − β) a0 + β a1) with the data's accelerations; the rollouts feed the network exactly
    what ``trajectory_inputs`` gives of the states they reach (the network's output zeroed, so the
    predicted step is the step); ``step_inputs`` (the fit's) is what the model's step from each
    true state feeds it, not the data's next state; w = 0 at a start; the carried step follows
    the rollouts, scripted too; the config names the values."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.hyperelastic import law_from_config
    from thermognn.train.hybrid import LinearPriorModel, prior_settings
    from thermognn.train.law_prior import HyperelasticNewmarkPrior
    from thermognn.train.model import TIGNN

    law = ("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    graph = _bent_block_graph(steps=8, law=law)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    tets = _bent_block(1.0, "newmark", steps=2, law=law)[0].cells[:, :4]
    lam, mu = linear.lame()
    prior = HyperelasticNewmarkPrior(linear, len(X), dt, X, tets, lam, mu,
                                     law_from_config({"law": law[0], **law[1]})[0], iterations=1)
    ref = torch.as_tensor(X, dtype=torch.float32)
    net = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, velocity_edges=True)
    net.set_stats({"dzdt_std": torch.full((12,), 1e-30)})           # the network's output: zero
    model = LinearPriorModel(net, prior, torch.as_tensor(X), positions_only=False, order=2, correction=True)
    assert model.correction and not LinearPriorModel(net, prior, torch.as_tensor(X), correction=True).correction
    seen = model.trajectory_inputs(z)                                                # [S, N, 12]
    assert torch.equal(seen[..., 0:3], z[..., 0:3]) and torch.equal(seen[..., 6:], z[..., 6:])
    w, a = prior.gather(seen[..., 3:6]), model.accelerations(z, f)                  # [S, n]
    newmark = dt * ((0.5 - prior.beta) * a[:-1] + prior.beta * a[1:])
    assert float(w[0].abs().max()) == 0.0
    assert float((w[1:] - newmark).norm() / newmark.norm()) < 1e-9
    assert float(w[1:].norm()) > 1e-3 * float(prior.gather(z[1:, :, 3:6]).norm())  # not the velocity's round-off
    fed = []
    remainders = model.remainders
    model.remainders = lambda x, *rest: (fed.append(x.detach().clone()), remainders(x, *rest))[1]  # noqa: E731
    with torch.enable_grad():
        states = model.rollouts(z[:1], f.unsqueeze(0), edges, node_type, ref, len(f) - 1, False)[0]   # [S, N, 12]
    assert float(fed[0][..., 3:6].abs().max()) == 0.0                              # begin: no step behind it
    fed_w = torch.cat(fed[1:])[..., 3:6]                                            # one call a step
    assert float((fed_w - model.trajectory_inputs(states)[1:, :, 3:6]).norm() / fed_w.norm()) < 1e-12
    # the fit's inputs (step_inputs): what the model's step from each true state shows the network
    fed.clear()
    h = model.trajectory_internal_variables(z)
    u, v, H = model.unpack(z, h)
    with torch.enable_grad():
        for s in range(len(f) - 1):
            model.advance(u[s:s + 1], v[s:s + 1], a[s:s + 1], torch.zeros_like(u[:1]), H[s:s + 1], h[s:s + 1],
                          f[s + 1:s + 2], edges, node_type, ref, False)
    del model.remainders
    inputs = model.step_inputs(z, f, torch.zeros_like(z[..., 0:3]))                # [S, N, 12]
    assert _rel(torch.cat(fed), inputs[1:]) < 1e-10 and _rel(torch.cat(fed)[..., 3:6], inputs[1:, :, 3:6]) < 1e-9
    assert float(inputs[0, :, 3:6].abs().max()) == 0.0 and torch.equal(inputs[0, :, 0:3], z[0, :, 0:3])
    assert float((inputs[1:, :, 3:6] - seen[1:, :, 3:6]).norm()) > 1e-3 * float(seen[1:, :, 3:6].norm())  # the budget's w
    net.set_stats({"dzdt_std": torch.full((12,), 1e-2)})
    _carried_steps_follow_rollouts(prior, graph, inputs="correction")
    assert prior_settings(OmegaConf.create({"prior": "linear", "prior_inputs": "correction"}))["inputs"] == "correction"
    assert "inputs" not in prior_settings(OmegaConf.create({"prior": "linear", "prior_inputs": "state"}))
    with pytest.raises(ConfigError, match=r"^model.prior_inputs = 'speed', expected positions \| state \| correction$"):
        prior_settings(OmegaConf.create({"prior": "linear", "prior_inputs": "speed"}))


def test_budget_fit_leaves_out_a_trajectory_no_load_lands():
    """``train.fit_target = budget`` on a trajectory whose last state no budgeted step reaches (its
    cells turned inside out, which every Newton update is shortened to avoid): the load
    corrections stall (``BUDGET_STALLED`` in a row without progress, not all of
    ``BUDGET_CORRECTIONS``), the miss stays far above ``BUDGET_MISS_TOL``, and the fit leaves that
    trajectory out, by name, keeping the FE's own; with none left, a one-line error."""
    torch = pytest.importorskip("torch")
    from types import SimpleNamespace

    from thermognn.core.errors import DataError
    from thermognn.core.hyperelastic import law_from_config
    from thermognn.train.hybrid import BUDGET_MISS_TOL, budget_fit_trajectories
    from thermognn.train.law_prior import BUDGET_STALLED, HyperelasticNewmarkPrior

    law = ("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph(steps=4, law=law)
    tets = _bent_block(1.0, "newmark", steps=2, law=law)[0].cells[:, :4]
    lam, mu = linear.lame()
    prior = HyperelasticNewmarkPrior(linear, len(X), dt, X, tets, lam, mu,
                                     law_from_config({"law": law[0], **law[1]})[0], iterations=1)
    Xt = torch.as_tensor(X)
    inverted = z.clone()
    inverted[-1, :, 0:3] = Xt.mean(0) - (Xt - Xt.mean(0))           # every free cell turned inside out
    model = SimpleNamespace(prior=prior, reference_positions=Xt)
    fe, bad = SimpleNamespace(z=z, force=f, name="fe"), SimpleNamespace(z=inverted, force=f, name="inverted")
    H = [torch.zeros(len(z), len(X), 6, dtype=torch.float64)] * 2
    kept, G, H_kept, unreached = budget_fit_trajectories(model, [bad, fe], H)
    assert [t.name for t in kept] == ["fe"] and len(G) == len(H_kept) == 1 and G[0].shape == (len(z), len(X), 3)
    assert [n for n, _ in unreached] == ["inverted"] and unreached[0][1] > 1e3 * BUDGET_MISS_TOL
    calls = []
    step = prior.step
    prior.step = lambda *a: (calls.append(1), step(*a))[1]                          # noqa: E731
    e, miss = prior.budget_loads(prior.gather(inverted[..., 0:3] - Xt), prior.gather(inverted[..., 3:6]), prior.gather(f))
    assert miss > 1e3 * BUDGET_MISS_TOL and BUDGET_STALLED < len(calls) < 10 and bool(torch.isfinite(e).all())
    del prior.step
    with pytest.raises(DataError, match=r"^train.fit_target = budget: no load lands the 1-iteration step on the data "
                                        r"in any training trajectory \(raise model.prior_newton\)$"):
        budget_fit_trajectories(model, [bad], H[:1])


def test_law_prior_line_search_converges_a_step_its_undamped_newton_does_not():
    """``model.prior_line_search`` (``HyperelasticNewmarkPrior(line_search=...)``) on the FE solid's
    own data (the damped 1 N bend, stiff viscous Ogden, α = 8): from a state of the data under 100
    times its next load, 40 undamped Newton updates do not converge (each would crush a cell and
    is shortened by ``admissible``, and the next overshoots again), where updates halved until
    they lower the residual norm converge in a few, to a step end whose residual is round-off of
    the load; so too from a start whose predictor inverts a cell. Along the data's rollout no
    update needs shortening: the same rollout as without the search, to the bit. Scripted (its
    dense LU) it takes the same step; the config records it, ``rollout.prior_line_search``
    steps a trained model so, and both name what they cannot be."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import law_phrase, model_step, with_law_rollout
    from thermognn.train.hybrid import prior_settings

    from scripted_prior import PriorStep  # tests/scripted_prior.py

    graph, prony, build = _ogden_bend_priors(steps=8)
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    u, v = z[..., 0:3] - torch.as_tensor(X), z[..., 3:6]
    n = int(linear.free.sum())
    G0 = torch.zeros(len(f), n, dtype=torch.float64)
    plain, searched = (build(iterations=1, max_iterations=40, newton_rtol=1e-10, line_search=k) for k in (0, 6))
    assert all(torch.equal(x, y) for x, y in zip(_prior_rollout(plain, u, v, f, G0, None),
                                                 _prior_rollout(searched, u, v, f, G0, None)))
    assert int(searched.searched) == 0 and searched.newton_taken.tolist() == plain.newton_taken.tolist()
    s0 = 3
    uf, vf = plain.gather(u[s0:s0 + 1]), plain.gather(v[s0:s0 + 1])
    h = plain.internal_variables(uf)
    a = plain.initial_acceleration(uf, vf, plain.gather(f[s0:s0 + 1]), G0[:1])
    load = 100.0 * plain.gather(f[s0 + 1:s0 + 2])
    for prior in (plain, searched):
        prior.newton_taken.zero_()
        prior.searched.zero_()
        prior.shortened.zero_()
    plain.step(uf, vf, a, load, G0[:1], G0[:1], h)
    taken, _, unconverged, _ = plain.newton_taken.tolist()
    assert taken == 40 and unconverged == 1 and int(plain.shortened) > 30     # (measured: 39 shortened)
    u1 = searched.step(uf, vf, a, load, G0[:1], G0[:1], h)[0]
    taken, _, unconverged, _ = searched.newton_taken.tolist()
    assert taken < 20 and unconverged == 0 and int(searched.searched) > 0   # (measured: 9, 3 searched)
    predictor, _, extra, damping0, _ = searched.step_origin(uf, vf, a, h)
    residual = searched.step_residual(u1, vf, a, predictor, extra, load + searched.body_force + damping0)[0]
    assert float(residual.norm()) < 1e-8 * float(load.norm())
    stepper = torch.jit.script(PriorStep(build(iterations=1, max_iterations=40, newton_rtol=1e-10, line_search=6)))
    with torch.jit.optimized_execution(False):                   # (serve's setting; the optimiser's plan: minutes)
        scripted = stepper(uf, vf, a, load, G0[:1], G0[:1], h)[0]
    assert stepper.prior.newton_taken.tolist() == searched.newton_taken.tolist()
    assert float((scripted - u1).norm() / u1.norm()) < 1e-12                  # dense LU, scripted
    # a start whose predictor u0 + Δt v0 inverts a cell (100 times the data's velocity): its residual
    # is not finite, so any finite one lowers it; searched, the step converges, undamped it does not
    fast = 100.0 * vf
    assert float(torch.linalg.det(searched.cells(uf + dt * fast)).amin()) < 0.0
    a_fast = searched.initial_acceleration(uf, fast, searched.gather(f[s0:s0 + 1]), G0[:1])
    for prior, converges in ((plain, False), (searched, True)):
        prior.newton_taken.zero_()
        end = prior.step(uf, fast, a_fast, searched.gather(f[s0 + 1:s0 + 2]), G0[:1], G0[:1], h)[0]
        assert bool(torch.isfinite(end).all()) and (prior.newton_taken.tolist()[2] == 0) == converges
        assert float(torch.linalg.det(searched.cells(end)).amin()) > 0.0             # no cell inverted

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 8}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_line_search": 6}))
    assert settings["law_search"] == 6 and model_step({"prior": settings})["law_search"] == 6
    assert ", its updates line-searched (up to 6 halvings))" in describe_step(model_step({"prior": settings}))
    assert "law_search" not in prior_settings(OmegaConf.create(cfg))
    assert "law_search" not in prior_settings(OmegaConf.create({**cfg, "prior_line_search": 0}))
    with pytest.raises(ConfigError, match=r"model.prior_line_search = 13, expected an integer 0 to 12"):
        prior_settings(OmegaConf.create({**cfg, "prior_line_search": 13}))
    with pytest.raises(ConfigError, match=r"model.prior_line_search = True, expected an integer 0 to 12"):
        prior_settings(OmegaConf.create({**cfg, "prior_line_search": True}))
    with pytest.raises(ConfigError, match=r"model.prior_line_search = 2 needs model.prior_law = true"):
        prior_settings(OmegaConf.create({"prior": "linear", "prior_line_search": 2}))
    with pytest.raises(ValueError, match="the law prior's line search: -1, expected 0"):
        build(iterations=1, line_search=-1)
    trained = {"prior": prior_settings(OmegaConf.create(cfg))}
    ckpt, note = with_law_rollout(trained, {"prior_line_search": 6})
    assert ckpt["prior"]["law_search"] == 6 and note.endswith(
        "its updates line-searched (6 halvings) (trained: 1 to 8 Newton iterations to 1e-08)")
    assert law_phrase(ckpt["prior"]).endswith(", its updates line-searched (6 halvings)")
    assert "law_search" not in with_law_rollout(ckpt, {"prior_line_search": 0})[0]["prior"]
    with pytest.raises(ConfigError, match=r"rollout.prior_line_search = 20, expected an integer 0 to 12"):
        with_law_rollout(trained, {"prior_line_search": 20})



def test_law_prior_line_search_starts_where_the_crushing_predictor_was_shortened():
    """A step whose FE predictor u0 + Δt v0 inverts a cell (one node moved through its opposite
    face) starts from that predictor shortened (``step_origin``, ``admissible``); the line search
    searches the first update from there, so no trial passes through inverted cells. Searched from
    the predictor as it stands (before session 95), a first iterate far worse than it (every other
    node kicked outwards, so the search halves back towards the base) came out inverted after 40
    iterations; from the shortened one the step converges with every cell sound. (The rest start,
    which takes the first update from u0 where the predictor's residual dwarfs u0's, is switched
    off here so that the search is what is tested.)"""
    torch = pytest.importorskip("torch")

    graph, _, build = _ogden_bend_priors(steps=8)
    _, _, dt, X, linear, _, _, z, f = graph
    prior = build(iterations=1, max_iterations=40, newton_rtol=1e-10, line_search=6)
    prior.rest_start_ratio = 0.0
    s0 = 3
    u = z[..., 0:3] - torch.as_tensor(X)
    u0 = prior.gather(u[s0:s0 + 1])
    h = prior.internal_variables(u0)
    P = torch.as_tensor(X) + u[s0]                                         # [N, 3] m: the start's positions
    a, b, c, d = (int(i) for i in prior.cell_nodes[8])
    normal = torch.linalg.cross(P[c] - P[b], P[d] - P[b])
    normal = normal / normal.norm()
    velocity = torch.zeros(1, len(X), 3, dtype=torch.float64)
    velocity[0, a] = -2.0 * torch.dot(P[a] - P[b], normal) * normal / dt   # Δt v0: node a mirrored through bcd
    v0 = prior.gather(velocity)
    G0 = torch.zeros(1, len(v0[0]), dtype=torch.float64)
    a0 = prior.initial_acceleration(u0, v0, prior.gather(f[s0:s0 + 1]), G0)
    cells_J = lambda w: float(torch.linalg.det(prior.cells(w)).amin())     # noqa: E731
    predictor, _, extra, damping0, shortened = prior.step_origin(u0, v0, a0, h)
    assert cells_J(u0 + dt * v0) < 0.0 < cells_J(shortened)
    kick = torch.zeros(1, len(X), 3, dtype=torch.float64)
    free = prior.free_nodes()
    kick[0, free] = 2.0 * (P[free] - P.mean(0))
    kick[0, a] = 0.0
    worse = shortened + prior.gather(kick)                                 # a first iterate far worse
    fixed = prior.gather(f[s0 + 1:s0 + 2]) + prior.body_force + damping0
    end, taken, unconverged = prior.searched_iterate(worse, u0, v0, a0, predictor, extra, fixed)
    assert cells_J(end) > 0.5 and not bool(unconverged.any()) and taken < 40, (cells_J(end), taken)

def test_law_prior_loads_a_cut_steps_sub_steps_between_the_step_s_loads():
    """``model.prior_cut_loads = linear`` (``HyperelasticNewmarkPrior.step(..., f0)``) on the FE
    solid's own data (the damped 1 N bend, viscous Ogden, its load ramping over its 8 steps): a cut
    step's sub-steps are loaded at their own end linearly between the step's start and end loads,
    as the FE loads its sub-steps within a ramp, where ``end`` holds the step's end load. Told to
    converge to round-off in 2 iterations every step is cut once: it is then, to round-off, two
    steps of the prior built for Δt/2 under the loads halfway and at the end. A LinearPriorModel
    with it carries the last load (3 more columns) and steps its carried state as its rollouts,
    scripted too; the config records it and names what it cannot be."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import law_phrase, model_step, with_law_rollout
    from thermognn.train.hybrid import prior_settings

    graph, prony, build, u, v, G, cut, half = _bend_cut_once()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    uc, vc = cut.gather(u[:1]), cut.gather(v[:1])
    hc = cut.internal_variables(uc)
    ac = cut.initial_acceleration(uc, vc, cut.gather(f[:1]), G[:1])
    uf, vf, a, h = uc, vc, ac, hc
    held = cut.step(uc, vc, ac, cut.gather(f[2:3]), G[1:2], G[2:3], hc)   # (a step of the ramp, held)
    for k in range(1, len(f)):
        f0, f1 = cut.gather(f[k - 1:k]), cut.gather(f[k:k + 1])
        uc, vc, ac, hc = cut.step(uc, vc, ac, f1, G[k - 1:k], G[k:k + 1], hc, f0)
        Gm = 0.5 * (G[k - 1:k] + G[k:k + 1])
        uf, vf, a, h = half.step(uf, vf, a, 0.5 * (f0 + f1), G[k - 1:k], Gm, h)
        uf, vf, a, h = half.step(uf, vf, a, f1, Gm, G[k:k + 1], h)
        assert _rel(uc, uf) < 1e-10 and _rel(vc, vf) < 1e-9, k
    assert cut.newton_taken.tolist()[3] == len(f)                 # every step cut (and the held one)
    ramped = cut.step(cut.gather(u[:1]), cut.gather(v[:1]), cut.initial_acceleration(
        cut.gather(u[:1]), cut.gather(v[:1]), cut.gather(f[:1]), G[:1]), cut.gather(f[1:2]), G[:1], G[1:2],
        cut.internal_variables(cut.gather(u[:1])), cut.gather(f[:1]))
    assert _rel(ramped[1], held[1]) > 1e-3                         # (a ramp's loads matter)
    _carried_steps_follow_rollouts(build(dt, max_iterations=2, newton_rtol=NEVER, step_cuts=1), graph,
                                   width=len(prony) * cut.cell_columns, cut_loads="linear", optimized=False)

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 8, "prior_step_cuts": 4}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_cut_loads": "linear"}))
    assert settings["law_cut_loads"] == "linear" and model_step({"prior": settings})["law_cut_loads"] == "linear"
    assert ", its sub-steps loaded linearly between the step's loads)" in describe_step(model_step({"prior": settings}))
    assert "law_cut_loads" not in prior_settings(OmegaConf.create(cfg))
    assert "law_cut_loads" not in prior_settings(OmegaConf.create({**cfg, "prior_cut_loads": "end"}))
    with pytest.raises(ConfigError, match=r"model.prior_cut_loads = 'ramp', expected end \| linear"):
        prior_settings(OmegaConf.create({**cfg, "prior_cut_loads": "ramp"}))
    with pytest.raises(ConfigError, match=r"model.prior_cut_loads = linear needs model.prior_law = true and "
                                          r"model.prior_step_cuts > 0"):
        prior_settings(OmegaConf.create({**cfg, "prior_step_cuts": 0, "prior_cut_loads": "linear"}))
    trained = {"prior": prior_settings(OmegaConf.create(cfg))}
    ckpt, note = with_law_rollout(trained, {"prior_cut_loads": "linear"})
    assert ckpt["prior"]["law_cut_loads"] == "linear" and "its sub-steps loaded between the step's loads" in note
    assert law_phrase(ckpt["prior"]).endswith("cut down to Δt/16, its sub-steps loaded between the step's loads")


def test_law_prior_substeps_take_every_step_as_the_data_s_fe_sub_steps():
    """``rollout.prior_substeps`` (``HyperelasticNewmarkPrior(substeps=k)``), for data generated
    with ``scene.time.substeps=k`` (the FE's steps of Δt/k, loads linear between the stored ones;
    test_generate checks that FE against the FE at Δt/k): on the viscous Ogden bend every step is
    taken as k sub-steps, to round-off the prior built for Δt/k stepped k times under the loads
    and remainders linear between the step's; scripted too. The config records it (and the carried
    start load it needs), training refuses it, and what it cannot be is named."""
    torch = pytest.importorskip("torch")
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.core.state import describe_step
    from thermognn.train.checkpoint import law_phrase, model_step, with_law_rollout
    from thermognn.train.hybrid import prior_settings

    from scripted_prior import PriorStep  # tests/scripted_prior.py

    graph, prony, build, u, v, G, cut, half = _bend_cut_once()
    layout, traj, dt, X, linear, node_type, edges, z, f = graph
    for k, fine in ((2, half), (4, build(dt / 4, max_iterations=2, newton_rtol=NEVER))):
        sub = build(dt, max_iterations=2, newton_rtol=NEVER, substeps=k)
        us = sub.gather(u[:1])
        hs = sub.internal_variables(us)
        vs, as_ = sub.gather(v[:1]), sub.initial_acceleration(us, sub.gather(v[:1]), sub.gather(f[:1]), G[:1])
        uf, vf, a, h = us, vs, as_, hs
        for s in range(1, len(f)):
            f0, f1 = sub.gather(f[s - 1:s]), sub.gather(f[s:s + 1])
            start = (us, vs, as_, hs)
            us, vs, as_, hs = sub.step(us, vs, as_, f1, G[s - 1:s], G[s:s + 1], hs, f0)
            for j in range(1, k + 1):
                w0, w1 = (j - 1) / k, j / k
                uf, vf, a, h = fine.step(uf, vf, a, f0 + w1 * (f1 - f0), G[s - 1:s] + w0 * (G[s:s + 1] - G[s - 1:s]),
                                         G[s - 1:s] + w1 * (G[s:s + 1] - G[s - 1:s]), h)
            assert _rel(us, uf) < 1e-10 and _rel(vs, vf) < 1e-9, (k, s)
        assert sub.newton_taken.tolist()[:2] == [2 * k * (len(f) - 1), len(f) - 1]
        if k == 2:                                       # scripted, the same step
            stepper = torch.jit.script(PriorStep(build(dt, max_iterations=2, newton_rtol=NEVER, substeps=2)))
            with torch.jit.optimized_execution(False), torch.no_grad():
                got = stepper.prior.step(*start[:3], f1, G[s - 1:s], G[s:s + 1], start[3], f0)
            assert _rel(got[0], us) < 1e-12 and _rel(got[1], vs) < 1e-12
    with pytest.raises(ValueError, match=r"sub-steps: 3, expected one of \[1, 2, 4, 8, 16\]"):
        build(dt, substeps=3)

    cfg = {"prior": "linear", "prior_law": True, "prior_newton": 1, "prior_newton_max": 8, "prior_step_cuts": 4}
    settings = prior_settings(OmegaConf.create({**cfg, "prior_substeps": 4}))
    assert settings["law_substeps"] == 4 and settings["law_cut_loads"] == "linear"
    assert "(4 sub-steps a step, each with 1 Newton iteration, up to 8" in describe_step(model_step({"prior": settings}))
    assert "halved down to Δt/64 where not" in describe_step(model_step({"prior": settings}))
    assert "law_substeps" not in prior_settings(OmegaConf.create(cfg))
    with pytest.raises(ConfigError, match=r"model.prior_substeps = 3, expected one of \[1, 2, 4, 8, 16\]"):
        prior_settings(OmegaConf.create({**cfg, "prior_substeps": 3}))
    with pytest.raises(ConfigError, match=r"model.prior_substeps = 2 needs model.prior_law = true"):
        prior_settings(OmegaConf.create({"prior": "linear", "prior_substeps": 2}))
    ckpt, note = with_law_rollout({"prior": prior_settings(OmegaConf.create(cfg))}, {"prior_substeps": 4})
    assert ckpt["prior"]["law_substeps"] == 4 and note.startswith("the law prior's step 4 sub-steps a step")
    assert law_phrase(ckpt["prior"]) == ("4 sub-steps a step (loaded between its loads), each 1 to 8 Newton "
                                         "iterations to 1e-08, cut down to Δt/64")


def test_the_law_priors_energy_balance_conserves_an_elastic_law_and_a_viscous_one_absorbs():
    """``evaluate``'s energy of a law prior (``law_energy_along``: the law's kinetic + strain energy,
    the loads' trapezoidal work W and what the body absorbed, W − ΔE) on the FE's bend, stepped to
    convergence: undamped and elastic (neo-Hookean, the Rayleigh terms taken out) the body holds
    the loads' work up to Newmark's drift over the law's curvature; with the FE's Rayleigh damping
    or a Prony term (viscous Ogden, undamped) it absorbs energy at every step and never gives back
    more than the loads put in (passive); the FE's own data of the damped bend, under its own law,
    too. The elastic law's drift is the integrator's: under a third of it at half the time step."""
    torch = pytest.importorskip("torch")
    from thermognn.core.hyperelastic import law_from_config
    from thermognn.train.evaluation import PASSIVE_TOL, law_energy_along
    from thermognn.train.law_prior import HyperelasticNewmarkPrior

    neo = ("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    ogden = ("ogden", {"mu": [2.0e4], "alpha": [8.0], "D": [1.0e-5]})
    rows = {}
    # (the elastic bend again at half the time step: 32 steps of 1 ms, the load ramped over 4 ms)
    for name, law, prony, damped, dt, steps in (("elastic", neo, (), False, 2e-3, 16), ("half", neo, (), False, 1e-3, 32),
                                                ("damped", neo, (), True, 2e-3, 16),
                                                ("viscous", ogden, ((0.4, 4e-3),), False, 2e-3, 16)):
        s, _, traj = _bent_block(1.0, "newmark", steps=steps, dt=dt, prony=prony, law=law)
        linear, X = modes.linear_solid(s), torch.as_tensor(s.nodes)
        if not damped:
            linear = dataclasses.replace(linear, rayleigh=(0.0, 0.0))
        material = {"law": law[0], **law[1], "prony": [{"g": g, "tau": t} for g, t in prony]}
        prior = HyperelasticNewmarkPrior(linear, len(X), dt, s.nodes, s.cells[:, :4], *linear.lame(),
                                         law_from_config(material)[0], iterations=1, max_iterations=12,
                                         newton_rtol=1e-12)
        z, f = torch.as_tensor(traj.z), torch.as_tensor(traj.force)
        G0 = torch.zeros(len(f), prior.n_free, dtype=torch.float64)
        U, V, _ = _prior_rollout(prior, z[..., 0:3] - X, z[..., 3:6], f, G0, None)
        rows[name] = law_energy_along(prior, X, torch.cat([U + X, V], -1), f)
        if name == "damped":
            rows["data"] = law_energy_along(prior, X, z, f)
    drift = {k: np.abs(rows[k][:, 5]).max() / rows[k][:, 4].max() for k in ("elastic", "half")}
    assert drift["half"] < drift["elastic"] / 3.0, drift      # the integrator's, O(Δt²): measured 4.26e-4, 1.11e-4
    for name, r in rows.items():
        E, W, absorbed, error = r[:, 0], r[:, 4], r[:, 5], r[:, 3]
        assert np.isfinite(r[:, [0, 3, 4, 5]]).all() and np.isnan(r[:, 1:3]).all()
        assert abs(E[0]) < 1e-9 * W.max() and W[0] == 0.0 and W[-1] > 0.0           # from rest, loaded
        assert np.allclose(error[1:], -np.diff(absorbed), rtol=0.0, atol=1e-12 * W.max())
        if name in ("elastic", "half"):
            assert np.abs(absorbed).max() < 1e-3 * W.max(), np.abs(absorbed).max() / W.max()     # measured 4.3e-4
        else:
            assert absorbed.min() >= -PASSIVE_TOL * W.max() and absorbed[-1] > 0.02 * W.max(), (name, absorbed / W.max())
            # (measured: 0.13 of the work at the end, damped and its data; 0.16 viscous)


def test_law_prior_time_rules_keep_or_damp_a_released_bodys_energy():
    """``model.prior_rule`` / ``model.prior_hht`` (``HyperelasticNewmarkPrior.set_rule``,
    ``set_hht``) on the bent block's elastic neo-Hookean law without Rayleigh damping, released
    from its bent state at rest and stepped unloaded (the stiff block's modes at Δt = 2 ms):
    the data's Newmark rule loses 0.9 % of the body's energy (``body_energy``, kinetic +
    stored) in 25 steps; the energy rule keeps it within 1e-5 at every step (its discrete
    gradient by Simpson's rule); HHT's dissipation takes out more than Newmark; set back to
    Newmark (hht 0) the prior steps as one built so, to the bit; scripted (as export does), either
    rule takes the eager step; what either cannot be is named."""
    torch = pytest.importorskip("torch")
    import dataclasses

    from thermognn.core.hyperelastic import law_from_config
    from thermognn.train.law_prior import HyperelasticNewmarkPrior

    law = ("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    layout, traj, dt, X, linear, node_type, edges, z, f = _bent_block_graph(steps=8, law=law)
    tets = _bent_block(1.0, "newmark", steps=2, law=law)[0].cells[:, :4]
    lam, mu = linear.lame()
    free = dataclasses.replace(linear, rayleigh=(0.0, 0.0))

    def build(**options):
        return HyperelasticNewmarkPrior(free, len(X), dt, X, tets, lam, mu, law_from_config({"law": law[0], **law[1]})[0],
                                        iterations=1, max_iterations=20, newton_rtol=1e-13, **options)

    def energies(prior, steps=25):
        u = prior.gather(z[-1:, :, 0:3] - torch.as_tensor(X))                    # bent, at rest, released
        v, zero = torch.zeros_like(u), torch.zeros_like(u)
        h = prior.internal_variables(u)
        a = prior.initial_acceleration(u, v, zero, zero)
        out = [float(prior.body_energy(u, v))]
        with torch.no_grad():
            for _ in range(steps):
                u, v, a, h = prior.step(u, v, a, zero, zero, zero, h)
                out.append(float(prior.body_energy(u, v)))
        return torch.tensor(out, dtype=torch.float64)

    newmark, energy, hht = energies(build()), energies(build(rule="energy")), energies(build(hht=0.2))
    E0 = float(newmark[0])
    assert E0 > 0 and float(energy[0]) == E0 == float(hht[0])
    assert float((energy - E0).abs().max()) < 1e-4 * E0                            # kept, every step
    assert float((newmark - E0).abs().max()) > 100.0 * float((energy - E0).abs().max())
    assert float(hht[-1]) < 0.98 * E0 and float(hht[-1]) < float(newmark[-1])      # damped
    back = build(hht=0.2)
    back.set_hht(0.0)
    assert torch.equal(energies(back), newmark)
    for rule, hht_ in (("energy", 0.0), ("newmark", 0.2)):                     # scripted (export), same step
        from scripted_prior import PriorStep  # tests/scripted_prior.py

        eager = build(rule=rule, hht=hht_)
        u = eager.gather(z[-1:, :, 0:3] - torch.as_tensor(X))
        v, zero = torch.zeros_like(u), torch.zeros_like(u)
        h = eager.internal_variables(u)
        a = eager.initial_acceleration(u, v, zero, zero)
        with torch.no_grad():
            want = eager.step(u, v, a, zero, zero, zero, h)
        stepper = torch.jit.script(PriorStep(build(rule=rule, hht=hht_)))
        with torch.jit.optimized_execution(False), torch.no_grad():
            got = stepper(u, v, a, zero, zero, zero, h)
        assert all(float((g - w).norm()) <= 1e-12 * float(w.norm()) + 1e-300 for g, w in zip(got[:3], want[:3]))
    with pytest.raises(ValueError, match="time rule: 'leapfrog', expected one of newmark | energy"):
        build(rule="leapfrog")
    with pytest.raises(ValueError, match=r"HHT dissipation: 0.5, expected 0 to 0.3333"):
        build(hht=0.5)
    with pytest.raises(ValueError, match=r"energy rule needs .* without Rayleigh damping"):
        HyperelasticNewmarkPrior(linear, len(X), dt, X, tets, lam, mu, law_from_config({"law": law[0], **law[1]})[0],
                                 iterations=1, rule="energy")
    with pytest.raises(ValueError, match="HHT dissipation 0.1 needs"):
        build(rule="energy").set_hht(0.1)
