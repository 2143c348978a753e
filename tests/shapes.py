"""Small closed-form geometry and assembly shared by the tests (test_kinematics, test_corotated,
test_fe_modes)."""

import math

import numpy as np


def cube():
    """The cube of side 0.1 m in 6 tets around its diagonal (8 nodes): (X [8, 3] m, tets [6, 4])."""
    X = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)], dtype=float) * 0.1
    tets = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])
    return X, tets


def rotation(axis, theta):
    """Rodrigues: the rotation by theta [rad] about the unit vector axis [3]."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    A = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(theta) * A + (1 - math.cos(theta)) * A @ A


def assembled(X, tets, Ke):
    """Σ_e K_e over all 3N DOFs [3N, 3N] (dense), cell matrices Ke [T, 12, 12] node-major (3 a + c)."""
    n = 3 * len(X)
    out = np.zeros((n, n))
    dofs = (3 * np.asarray(tets)[:, :, None] + np.arange(3)).reshape(len(tets), 12)
    for e in range(len(tets)):
        out[np.ix_(dofs[e], dofs[e])] += Ke[e]
    return out
