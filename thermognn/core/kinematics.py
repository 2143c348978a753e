"""Finite-rotation kinematics of P1 tetrahedra, and how far a linearised stress is from the data.

A solid linearised at rest measures strain as ε = sym(Grad u). Under a rigid rotation R of a
cell, F = R and ε = sym(R) − I ≠ 0: a linear stress σ = λ tr(ε) I + 2 μ ε sees stress in a body
that is not strained (for a rotation by θ about one axis, tr ε = 2 (cos θ − 1) ≈ −θ², a spurious
pressure of about K θ²). The corotational form removes it: with the polar decomposition F = R U
(``polar_rotations``), the strain is measured in the cell's rotated frame, ε̃ = sym(Rᵀ F) − I,
the volume change as J − 1 = det F − 1, and the stress rotated back::

    σ_cell = R (K (J − 1) I + 2 μ dev ε̃) Rᵀ,    K = λ + 2μ/3          [Pa]

(with a Prony series on its isochoric part 2 μ dev ε̃, relaxed as ``LinearSolid`` relaxes Σ u).
For small strains and rotations it is the linear stress; for a rigid rotation it is zero; and
unlike tr ε̃, J − 1 gives no pressure to an isochoric motion (a simple shear) at second order.

``rotation_report`` is ``generate``'s diagnostic of it: how far the cells of the data rotate and
strain (principal strains of U: large ones in a few cells are the material's own nonlinearity
under a point load, which corotation does not remove; docs/accuracy.md, session 47), and how far the linear stress of the data's *own* displacements is from the data's stress,
plain and corotated. Where the plain one is far off and the corotated one is not, the response
is geometrically nonlinear (large rotations), and a prior linearised at rest has to learn the
rotations (docs/accuracy.md, session 40: on the liver's test cases 231 % plain, 39 % corotated).

Numpy only (no torch, no dolfinx): ``generate`` and the benchmarks use it alike.
"""

from __future__ import annotations

import math
from typing import Iterable, Sequence

import numpy as np

#: Voigt order of the stored stress: 11 22 33 12 13 23
VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def shape_gradients(X: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference gradients of the P1 shape functions, Grad φ_a [T, 4, 3] [1/m], and cell volumes
    [T] [m³], for nodes X [N, 3] [m] and cells ``tets`` [T, 4] (node indices)."""
    x = np.asarray(X, dtype=float)[np.asarray(tets)]                 # [T, 4, 3]
    edges = (x[:, 1:] - x[:, :1]).transpose(0, 2, 1)                # [T, 3, 3]: columns X_b − X_0
    inv = np.linalg.inv(edges)                                       # rows: Grad φ_1..3
    grad = np.concatenate([-inv.sum(1, keepdims=True), inv], 1)      # [T, 4, 3]
    volume = np.abs(np.linalg.det(edges)) / 6.0
    return grad, volume


class P1Cells:
    """P1 cells ``tets`` [T, 4] of nodes X [N, 3] [m] over the free DOFs ``free`` [3N] (bool): the
    bookkeeping the FE-free solids (``thermognn.core.corotated``, ``thermognn.core.hyperelastic``)
    share. Attributes: ``grad`` [T, 4, 3] 1/m and ``volume`` [T] m³ (``shape_gradients``), ``dofs``
    [T, 12] (node-major: 3 a + c), ``n_all`` = 3N; of a cell matrix's T 144 entries (row-major per
    cell), ``_keep`` those on pairs of free DOFs and their free row and column ``_rows``, ``_cols``."""

    def __init__(self, X: np.ndarray, tets: np.ndarray, free: np.ndarray) -> None:
        self.X, self.tets = np.asarray(X, dtype=float), np.asarray(tets)
        self.grad, self.volume = shape_gradients(self.X, self.tets)
        self.dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(len(self.tets), 12)   # [T, 12]
        self.free = np.asarray(free, dtype=bool)
        self.n_all = 3 * len(self.X)
        index = np.full(self.n_all, -1)
        index[self.free] = np.arange(int(self.free.sum()))
        rows = np.repeat(index[self.dofs], 12, axis=1).ravel()               # [T 144]: free index or −1
        cols = np.tile(index[self.dofs], (1, 12)).ravel()
        self._keep = (rows >= 0) & (cols >= 0)
        self._rows, self._cols = rows[self._keep], cols[self._keep]

    def scatter(self, fe: np.ndarray) -> np.ndarray:
        """Cell vectors [T, 12] summed into the free DOFs [n]."""
        out = np.zeros(self.n_all)
        np.add.at(out, self.dofs.ravel(), fe.ravel())
        return out[self.free]

    def nodal(self, rows: np.ndarray) -> np.ndarray:
        """Free-DOF rows [..., n] -> nodal vectors [..., N, 3] (zero at clamped DOFs)."""
        full = np.zeros(rows.shape[:-1] + (self.n_all,))
        full[..., self.free] = rows
        return full.reshape(rows.shape[:-1] + (-1, 3))

    def positions(self, u_free: np.ndarray) -> np.ndarray:
        """Nodal positions [N, 3] m of a free-DOF displacement [n] (clamped nodes at rest)."""
        return self.X + self.nodal(u_free)


def deformation_gradients(q: np.ndarray, tets: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """F = Σ_a x_a ⊗ Grad φ_a per cell, [..., T, 3, 3], for current positions q [..., N, 3] [m]."""
    x = np.asarray(q, dtype=float)[..., np.asarray(tets), :]          # [..., T, 4, 3]
    return np.einsum("...tai,taj->...tij", x, grad)


def polar_rotations(F: np.ndarray) -> np.ndarray:
    """R of the polar decomposition F = R U [..., 3, 3] (proper rotations, det R = +1; by SVD,
    F = W S Vᵀ, R = W Vᵀ with the sign of the smallest singular pair flipped where det < 0)."""
    W, _, Vt = np.linalg.svd(F)
    d = np.sign(np.linalg.det(W @ Vt))
    W = W.copy()
    W[..., :, 2] *= d[..., None]
    return W @ Vt


def rotation_angles(R: np.ndarray) -> np.ndarray:
    """Angle [rad] of each rotation R [..., 3, 3]: cos θ = (tr R − 1) / 2."""
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


def _relax(sig_vol: np.ndarray, sig_iso: np.ndarray, prony: Sequence[tuple[float, float]], dt: float) -> np.ndarray:
    """σ_vol + σ_iso with the isochoric history relaxed by a Prony series ((ḡ_i, τ_i [s]), ...)
    over steps dt [s] along axis 0: the internal variables start as if the first state were
    applied at once, h_i ← e^(−dt/τ_i) h_i + τ_i/dt (1 − e^(−dt/τ_i)) (σ_iso[s] − σ_iso[s − 1]),
    σ[s] = σ_vol[s] + σ_iso[s] + Σ_i ḡ_i (h_i − σ_iso[s]) (``LinearSolid.relaxation``)."""
    out = sig_vol + sig_iso
    for g, tau in prony:
        decay, weight = math.exp(-dt / tau), -math.expm1(-dt / tau) / (dt / tau)
        h = sig_iso[0].copy()
        for s in range(1, sig_iso.shape[0]):
            h = decay * h + weight * (sig_iso[s] - sig_iso[s - 1])
            out[s] += g * (h - sig_iso[s])
    return out


def linear_cell_stress(q: np.ndarray, X: np.ndarray, tets: np.ndarray, lam: float, mu: float,
                       prony: Sequence[tuple[float, float]] = (), dt: float = 1.0,
                       corotated: bool = False, volume_from_det: bool = True) -> np.ndarray:
    """Cauchy stress [S, T, 3, 3] [Pa] of the linear solid (Lamé λ, μ [Pa] at rest, optional
    Prony series on the isochoric part) along the positions q [S, N, 3] [m] of nodes X [N, 3]:
    plain, ε = sym(F) − I, or ``corotated``, ε̃ = sym(Rᵀ F) − I in each cell's rotated frame and
    the stress rotated back (module docstring; the relaxation runs in the rotated frame), its
    volume change J − 1, or with ``volume_from_det`` False tr ε̃: the stress whose divergence the
    corotated force K_e (Rᵀ x − X) is (``thermognn.core.corotated``'s own, for its rollouts)."""
    F = deformation_gradients(q, tets, shape_gradients(X, tets)[0])   # [S, T, 3, 3]
    return _cell_stress(F, polar_rotations(F) if corotated else None, lam, mu, prony, dt, volume_from_det)


def _cell_stress(F: np.ndarray, R: np.ndarray | None, lam: float, mu: float,
                 prony: Sequence[tuple[float, float]], dt: float, volume_from_det: bool = True) -> np.ndarray:
    """``linear_cell_stress`` from the cells' F [S, T, 3, 3], corotated by their polar rotations R
    (same shape) or plain (R None)."""
    corotated = R is not None
    local = np.swapaxes(R, -1, -2) @ F if corotated else F
    eps = 0.5 * (local + np.swapaxes(local, -1, -2)) - np.eye(3)
    tr = np.trace(eps, axis1=-2, axis2=-1)[..., None, None]
    dev = eps - tr / 3.0 * np.eye(3)
    # volume change: tr ε, or J − 1 where corotated (tr(U − I) is not the volume change at second
    # order: a simple shear, J = 1, would get a spurious pressure λ γ²/8 from it)
    dilatation = np.linalg.det(F)[..., None, None] - 1.0 if corotated and volume_from_det else tr
    sig = _relax((lam + 2.0 * mu / 3.0) * dilatation * np.eye(3), 2.0 * mu * dev, prony, dt)
    return R @ sig @ np.swapaxes(R, -1, -2) if corotated else sig


def node_average(cell: np.ndarray, tets: np.ndarray, volume: np.ndarray, n_nodes: int) -> np.ndarray:
    """Volume-weighted nodal average [..., N, 6] (Voigt) of cell tensors [..., T, 3, 3], as the
    dataset stores the stress (``Solid.node_average``)."""
    voigt = np.moveaxis(np.stack([cell[..., i, j] for i, j in VOIGT], -1), -2, 0)   # [T, ..., 6]
    out = np.zeros((n_nodes,) + voigt.shape[1:])                      # [N, ..., 6]
    weight = np.zeros(n_nodes)
    tets = np.asarray(tets)
    scaled = voigt * volume.reshape((-1,) + (1,) * (voigt.ndim - 1))
    for a in range(tets.shape[1]):
        np.add.at(out, tets[:, a], scaled)
        np.add.at(weight, tets[:, a], volume)
    out = np.moveaxis(out, 0, -2)                                     # [..., N, 6]
    return out / weight[:, None]


def rotation_report(X: np.ndarray, tets: np.ndarray, trajectories: Iterable, layout, lam: float, mu: float,
                    prony: Sequence[tuple[float, float]] = (), dt: float = 1.0) -> dict | None:
    """How geometrically nonlinear a dataset's motion is (module docstring). For each trajectory
    (schema ``Trajectory``: z [S, N, D]): the cells' rotations, and the whole-rollout relative
    error ‖σ_lin − σ‖ / ‖σ‖ over steps 1.. of the linear stress of the data's own positions,
    plain and corotated, against the data's stress (when the layout has ``sigma``).

    Returns {"rotation_max_deg": the largest rotation of any cell at any step, "rotation_rms_deg":
    the volume-weighted RMS over cells at each trajectory's last step, averaged, "strain_max": the
    largest principal strain |λ_k − 1| (stretches λ_k of U = Rᵀ F) of any cell at any step,
    "strain_rms": the volume-weighted RMS over cells of each cell's largest one, at the step where
    it peaks, averaged over the trajectories (where "strain_max" is far above it, the large
    strains are local, as in the cells under a point load), "stress_plain", "stress_corotated":
    the errors averaged over the trajectories (None without σ), "trajectories": count}, or None
    when there is nothing to measure."""
    X = np.asarray(X, dtype=float)
    grad, volume = shape_gradients(X, tets)
    w = volume / volume.sum()
    has_sigma = "sigma" in layout.names
    rot_max, rot_rms, strain_max, strain_rms, plain, corot, count = 0.0, [], 0.0, [], [], [], 0
    for traj in trajectories:
        z = np.asarray(traj.z, dtype=float)                           # [S, N, D]
        F = deformation_gradients(z[..., 0:3], tets, grad)          # [S, T, 3, 3]
        R = polar_rotations(F)
        theta = rotation_angles(R)                                    # [S, T]
        rot_max = max(rot_max, float(theta.max()))
        rot_rms.append(float(np.sqrt((w * theta[-1] ** 2).sum())))
        U = np.swapaxes(R, -1, -2) @ F                                # [S, T, 3, 3]: the stretch (symmetric)
        strain = np.abs(np.linalg.eigvalsh(0.5 * (U + np.swapaxes(U, -1, -2))) - 1.0).max(-1)   # [S, T]
        strain_max = max(strain_max, float(strain.max()))
        strain_rms.append(float(np.sqrt((w * strain ** 2).sum(-1)).max()))
        count += 1
        if has_sigma and z.shape[0] > 1:
            truth = z[1:, :, layout.slice("sigma")]
            norm = np.linalg.norm(truth)
            if norm > 0:
                for out, rotation in ((plain, None), (corot, R)):
                    cell = _cell_stress(F, rotation, lam, mu, prony, dt)
                    out.append(float(np.linalg.norm(node_average(cell, tets, volume, len(X))[1:] - truth) / norm))
    if not count:
        return None
    return {"rotation_max_deg": math.degrees(rot_max), "rotation_rms_deg": math.degrees(float(np.mean(rot_rms))),
            "strain_max": strain_max, "strain_rms": float(np.mean(strain_rms)),
            "stress_plain": float(np.mean(plain)) if plain else None,
            "stress_corotated": float(np.mean(corot)) if corot else None, "trajectories": count}
