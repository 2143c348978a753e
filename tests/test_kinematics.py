"""thermognn/core/kinematics.py: finite rotations of P1 tets and the corotated linear stress,
against closed forms (numpy only; the match with generate's stress operator Σ u is checked in
tests/test_fe_modes.py)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from thermognn.core.kinematics import (deformation_gradients, linear_cell_stress, node_average, polar_rotations,
                                       rotation_angles, rotation_report, shape_gradients)
from thermognn.core.state import StateLayout

from shapes import cube, rotation  # tests/shapes.py

LAM, MU = 18.0e3, 2.0e3                     # [Pa]
K = LAM + 2.0 * MU / 3.0                    # bulk modulus [Pa]


def test_shape_gradients_and_deformation_gradient_of_an_affine_motion():
    X, tets = cube()
    grad, volume = shape_gradients(X, tets)
    assert np.allclose(grad.sum(1), 0.0) and volume.sum() == pytest.approx(1e-3)
    A = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.3], [0.05, 0.0, 1.2]])
    F = deformation_gradients(X @ A.T + [0.3, -0.2, 0.1], tets, grad)          # x = A X + c
    assert np.allclose(F, A, atol=1e-12)


def test_rigid_rotation_is_stress_free_only_when_corotated():
    """A rigid rotation by θ about z: every cell's polar rotation is it; the plain linear stress
    sees a pressure, tr σ = 3 K tr ε = 3 K · 2 (cos θ − 1); the corotated stress is zero."""
    X, tets = cube()
    theta = math.radians(40.0)
    R0 = rotation([0, 0, 1], theta)
    q = np.stack([X, X @ R0.T + [0.01, 0.0, -0.02]])                           # [S=2, N, 3]
    grad, _ = shape_gradients(X, tets)
    R = polar_rotations(deformation_gradients(q, tets, grad))
    assert np.allclose(R[1], R0, atol=1e-12) and np.allclose(R[0], np.eye(3), atol=1e-12)
    assert np.allclose(rotation_angles(R[1]), theta, atol=1e-9)
    plain = linear_cell_stress(q, X, tets, LAM, MU)
    assert np.allclose(np.trace(plain[1], axis1=-2, axis2=-1), 3 * K * 2 * (math.cos(theta) - 1), rtol=1e-9)
    corot = linear_cell_stress(q, X, tets, LAM, MU, corotated=True)
    assert np.abs(corot).max() < 1e-9 * K


def test_rotated_stretch_gives_the_rotated_linear_stress():
    """F = R0 diag(1 + e, 1, 1): corotated σ = R0 (λ e I + 2 μ e e1 ⊗ e1) R0ᵀ, exactly."""
    X, tets = cube()
    e = 0.03
    R0 = rotation([1, 2, 3], math.radians(70.0))
    F = R0 @ np.diag([1 + e, 1.0, 1.0])
    q = np.stack([X, X @ F.T])
    expected = R0 @ (LAM * e * np.eye(3) + 2 * MU * e * np.diag([1.0, 0, 0])) @ R0.T
    corot = linear_cell_stress(q, X, tets, LAM, MU, corotated=True)
    assert np.allclose(corot[1], expected, rtol=1e-10, atol=1e-9 * MU)


def test_prony_relaxation_in_the_rotated_frame():
    """A stretch applied at once and held while the body turns: the isochoric stress relaxes as
    1 − Σ ḡ_i (1 − e^(−t/τ_i)) in the body's frame, the volumetric stays, and both turn with it."""
    X, tets = cube()
    prony, dt, S = ((0.5, 0.05), (0.3, 0.4)), 0.01, 40
    e = 0.02
    Rs = [rotation([0, 1, 1], math.radians(2.0 * s)) for s in range(S)]
    q = np.stack([X @ (R @ np.diag([1 + e, 1.0, 1.0])).T for R in Rs])
    sig = linear_cell_stress(q, X, tets, LAM, MU, prony, dt, corotated=True)
    eps = np.diag([e, 0.0, 0.0])
    vol, dev = K * e * np.eye(3), 2 * MU * (eps - e / 3 * np.eye(3))
    for s in (0, 1, 10, S - 1):
        left = 1 - sum(g * (1 - math.exp(-s * dt / tau)) for g, tau in prony)
        expected = Rs[s] @ (vol + left * dev) @ Rs[s].T
        assert np.allclose(sig[s], expected, rtol=1e-9, atol=1e-9 * MU), s


def test_node_average_and_the_report_on_a_turning_body():
    """node_average of a constant cell tensor is that tensor at every node; rotation_report of a
    body that turns 60° under a small stretch, its stress the corotated one: the largest rotation
    is 60°, the corotated stress error zero, the plain one of the order of the spurious pressure."""
    X, tets = cube()
    _, volume = shape_gradients(X, tets)
    T = np.tile(np.array([[1.0, 4, 5], [4, 2, 6], [5, 6, 3]]), (len(tets), 1, 1))
    assert np.allclose(node_average(T, tets, volume, len(X)), [1, 2, 3, 4, 5, 6])
    layout = StateLayout((("q", 3), ("v", 3), ("sigma", 6)))
    S = 8
    Rs = [rotation([1, 0, 0], math.radians(60.0 * s / (S - 1))) for s in range(S)]
    q = np.stack([X @ (R @ np.diag([1.01, 1.0, 1.0])).T for R in Rs])
    z = np.zeros((S, len(X), layout.dim))
    z[..., 0:3] = q
    z[..., layout.slice("sigma")] = node_average(linear_cell_stress(q, X, tets, LAM, MU, corotated=True),
                                                 tets, volume, len(X))
    report = rotation_report(X, tets, [SimpleNamespace(z=z)], layout, LAM, MU)
    assert report["rotation_max_deg"] == pytest.approx(60.0, abs=1e-6) and report["trajectories"] == 1
    assert report["stress_corotated"] < 1e-9 and report["stress_plain"] > 1.0
    # the stretch 1.01 along x in every cell: 1 % principal strain, everywhere (the turn is not strain)
    assert report["strain_max"] == pytest.approx(0.01, rel=1e-9) and report["strain_rms"] == pytest.approx(0.01, rel=1e-9)
    assert rotation_report(X, tets, [], layout, LAM, MU) is None


def test_the_report_tells_local_strains_from_uniform_ones():
    """strain_max is the largest principal strain |λ − 1| of any cell (compression counts),
    strain_rms the volume RMS of each cell's largest one where it peaks: of two equal tets, one
    squeezed (a node moved 30 % of the way to the opposite face) and one at rest, strain_max is
    the squeezed cell's, strain_rms that over √2; generate's rotations line prints both."""
    from thermognn.generate.modes import describe

    unit = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) * 0.05        # [m]
    X = np.concatenate([unit, unit + [0.2, 0.0, 0.0]])                                     # two bodies
    tets = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    grad, volume = shape_gradients(X, tets)
    layout = StateLayout((("q", 3), ("v", 3), ("sigma", 6)))
    z = np.zeros((2, len(X), layout.dim))
    z[..., 0:3] = X
    centroid = X[:3].mean(0)                                               # of the face opposite node 3
    z[1, 3, 0:3] = centroid + 0.7 * (X[3] - centroid)
    F = deformation_gradients(z[1:, :, 0:3], tets, grad)[0]                # [2, 3, 3]
    assert np.allclose(F[1], np.eye(3))
    expected = float(np.abs(np.linalg.svd(F[0], compute_uv=False) - 1.0).max())
    report = rotation_report(X, tets, [SimpleNamespace(z=z)], layout, LAM, MU)
    assert report["strain_max"] == pytest.approx(expected, rel=1e-9) and expected > 0.2
    assert report["strain_rms"] == pytest.approx(expected / math.sqrt(2.0), rel=1e-9)
    lines = describe(dict(modes=1, unresolved=0, dt=1.0, omega_1_dt=1.0, omega_max_dt=1.0, strain_unresolved=0.0,
                          rotations=dict(report, stress_plain=None)))
    assert (f"and strain up to {100 * expected:.0f} % (volume RMS {100 * expected / math.sqrt(2.0):.0f} % "
            f"where it peaks)") in lines[1]
