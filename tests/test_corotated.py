"""thermognn/core/corotated.py: the linearised solid corotated per cell, against invariants and
closed forms (numpy only; against the FE solid's own data, tests/test_fe_modes.py)."""

import math

import numpy as np
import pytest

from thermognn.core.corotated import CorotatedSolid, element_stiffness
from thermognn.core.linear import LinearSolid
from thermognn.core.state import state_layout

from shapes import assembled, cube, rotation  # tests/shapes.py

LAM, MU = 18.0e3, 2.0e3                     # [Pa]
RHO = 1000.0                                # [kg/m³]


def cube_solid(clamp_bottom: bool, rayleigh=(0.0, 0.0), prony=()):
    """The cube's linear solid (K and K_iso assembled from ``element_stiffness``, a lumped mass),
    free everywhere or clamped at z = 0; with its moduli, as ``generate`` stores them."""
    X, tets = cube()
    K, K_iso = element_stiffness(X, tets, LAM, MU)
    free = np.ones(3 * len(X), dtype=bool)
    if clamp_bottom:
        free[np.repeat(X[:, 2] < 1e-12, 3)] = False
    mass = np.eye(3 * len(X)) * RHO * 1e-3 / len(X)                     # lumped: ρ V / N per DOF [kg]
    sub = np.ix_(free, free)
    lin = LinearSolid(stiffness=assembled(X, tets, K)[sub], mass=mass[sub], free=free, rayleigh=rayleigh,
                      prony=tuple(prony), stiffness_iso=assembled(X, tets, K_iso)[sub] if prony else None,
                      shear_modulus=MU, bulk_modulus=LAM + 2.0 * MU / 3.0)
    return lin, X, tets


def test_element_stiffness_has_rigid_modes_and_the_uniform_strain_energy():
    """K_e annihilates the six rigid motions of a cell; a uniform strain ε stores the energy
    V (λ/2 (tr ε)² + μ ε:ε) over the cube; K_iso gives a pure dilatation no force."""
    X, tets = cube()
    K, K_iso = element_stiffness(X, tets, LAM, MU)
    Kg, Kg_iso = assembled(X, tets, K), assembled(X, tets, K_iso)
    W = np.array([[0.0, -0.3, 0.2], [0.3, 0.0, -0.1], [-0.2, 0.1, 0.0]])   # skew: an infinitesimal rotation
    for motion in (np.tile([1.0, -2.0, 0.5], len(X)), (X @ W.T).ravel()):
        assert np.abs(Kg @ motion).max() < 1e-9 * np.abs(Kg).max()
    eps = np.array([[1e-3, 2e-4, 0.0], [2e-4, -5e-4, 1e-4], [0.0, 1e-4, 3e-4]])
    u = (X @ eps.T).ravel()
    energy = 1e-3 * (0.5 * LAM * np.trace(eps) ** 2 + MU * np.sum(eps * eps))
    assert 0.5 * u @ Kg @ u == pytest.approx(energy, rel=1e-12)
    assert np.abs(Kg_iso @ (X * 1e-3).ravel()).max() < 1e-9 * np.abs(Kg_iso).max()


def test_corotated_force_is_rotation_free_and_balances_force_and_torque():
    """Under a rigid rotation (60°) the corotated force is zero where the linear K u is not; under
    any deformation its net force and net torque Σ x_a × f_a vanish (σ̃ and U = Rᵀ F commute for an
    isotropic material, so angular momentum is conserved), to round-off."""
    lin, X, tets = cube_solid(clamp_bottom=False)
    solid = CorotatedSolid.of(lin, X, tets)
    R0 = rotation([1.0, 2.0, 0.5], math.radians(60.0))
    x = X @ R0.T + [0.02, -0.01, 0.03]
    scale = LAM * 0.01                                                  # a force scale [N] (λ · area)
    assert np.abs(solid.elastic_force(solid.rotations(x), x)).max() < 1e-10 * scale
    assert np.abs(lin.stiffness @ (x - X).ravel()).max() > 1e-2 * scale
    rng = np.random.default_rng(0)
    x = (X + 0.01 * rng.standard_normal(X.shape)) @ R0.T
    f = solid.elastic_force(solid.rotations(x), x).reshape(-1, 3)
    assert np.abs(f).max() > 1e-3 * scale
    assert np.abs(f.sum(0)).max() < 1e-10 * np.abs(f).max()
    assert np.abs(np.cross(x, f).sum(0)).max() < 1e-10 * np.abs(f).max() * 0.1


@pytest.mark.parametrize("prony", [(), ((0.4, 0.05),)])
def test_frozen_rotations_are_the_linearised_solid(prony):
    """With every R_e = I (``frozen``) the corotated rollout is ``LinearSolid.rollout`` to
    round-off, Rayleigh damping and a Prony term included, and its stress the linear Σ u
    computed per cell (no stress operator here: σ from ``linear_cell_stress``)."""
    lin, X, tets = cube_solid(clamp_bottom=True, rayleigh=(3.0, 2e-3), prony=prony)
    solid = CorotatedSolid.of(lin, X, tets, frozen=True)
    S, n, dt = 12, lin.n_free, 5e-3
    ramp = np.minimum(1.0, np.arange(S) / 6)[:, None]
    forces = ramp * np.tile([0.5, 0.0, -0.2], len(X))[None, lin.free]  # [S, n] N
    U, V = solid.rollout(np.zeros(n), np.zeros(n), forces, dt)
    Ul, Vl = lin.rollout(np.zeros(n), np.zeros(n), forces, dt)
    assert np.abs(Ul).max() > 1e-4
    assert np.abs(U - Ul).max() < 1e-10 * np.abs(Ul).max() and np.abs(V - Vl).max() < 1e-10 * np.abs(Vl).max()
    assert solid.count.mean == 1.0


def test_a_rotated_body_at_rest_stays_put_and_a_free_one_keeps_its_momenta():
    """A free cube turned by 60° and left unloaded stays where it is, unstressed (the linearised
    solid springs back). Kicked with a spin and a random velocity it keeps its linear momentum
    (lumped mass: P = Σ m v) to round-off, and its angular momentum L = Σ m x × v as the
    trapezoidal rule keeps it, to second order in dt: its drift over the same 80 ms falls about
    4x when dt halves (the force itself is torque-free: the test above). The sweeps find each
    step's fixed point (none stops at the limit)."""
    lin, X, tets = cube_solid(clamp_bottom=False)
    layout = state_layout(("elastic", "inertia"))
    R0 = rotation([0.0, 1.0, 1.0], math.radians(60.0))
    solid = CorotatedSolid.of(lin, X, tets, tol=1e-12, max_sweeps=50)
    S, dt = 41, 2e-3
    z = np.zeros((S, len(X), layout.dim))
    z[0, :, 0:3] = X @ R0.T
    out = solid.rollout_states(z, np.zeros((S, len(X), 3)), X, layout, dt)
    assert np.abs(out[..., 0:3] - z[0, :, 0:3]).max() < 1e-12 and np.abs(out[..., 3:]).max() < 1e-6
    assert np.abs(lin.rollout_states(z, np.zeros((S, len(X), 3)), X, layout, dt)[-1, :, 0:3] - z[0, :, 0:3]).max() > 1e-3
    rng = np.random.default_rng(1)
    kick = 0.2 * rng.standard_normal((len(X), 3)) + np.cross([0.0, 0.0, 5.0], X)     # [N, 3] m/s
    m = RHO * 1e-3 / len(X)
    drift = {}
    for steps in (40, 80):
        z = np.zeros((steps + 1, len(X), layout.dim))
        z[0, :, 0:3], z[0, :, layout.slice("v")] = X @ R0.T, kick
        out = solid.rollout_states(z, np.zeros((steps + 1, len(X), 3)), X, layout, 0.08 / steps)
        x, v = out[..., 0:3], out[..., layout.slice("v")]
        P, L = m * v.sum(1), m * np.cross(x, v).sum(1)                  # [S, 3] each
        assert np.abs(x[-1] - x[0]).max() > 1e-3                        # it moved and turned
        assert np.abs(P - P[0]).max() < 1e-9 * np.abs(P[0]).max()
        drift[steps] = np.abs(L - L[0]).max() / np.abs(L[0]).max()
    assert drift[40] < 1e-3 and 3.0 < drift[40] / drift[80] < 5.0, drift
    assert solid.count.unconverged == 0 and solid.count.most > 1


def test_of_names_what_is_missing():
    lin, X, tets = cube_solid(clamp_bottom=True)
    lin.shear_modulus = None
    with pytest.raises(ValueError, match="no moduli at rest"):
        CorotatedSolid.of(lin, X, tets)
    lin.shear_modulus, lin.integrator = MU, "quasi_static"
    with pytest.raises(ValueError, match="'quasi_static' is not reproduced"):
        CorotatedSolid.of(lin, X, tets)
