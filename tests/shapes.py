"""Small closed-form geometry shared by the numpy-only tests (test_kinematics, test_corotated)."""

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
