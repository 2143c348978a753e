"""How much of the linearised FE baseline's error is the cells' rotation?

The solid linearised at rest (``/linear``, ``evaluate``'s baseline and ``model=linear_prior``'s
step) reads a rotation as strain. This script rolls out, beside it, the same solid *corotated*
per cell (``thermognn/core/kinematics.py``): each cell's linear force measured in its rotated
frame, f_e = R_e K_e (R_eᵀ x_e − X_e), its Prony history in that frame, R_e taken at the start of
each step (linearly implicit: one factorisation of c0 M + Σ R_e K_e,dt R_eᵀ a step), the data's
Newmark step otherwise; and its stress ``linear_cell_stress(corotated=True)`` node-averaged. With
every R_e held at I it is the linearised model exactly (checked first, printed as
``frozen-rotation check``). Printed first: ``rotation_report`` of those trajectories (what
``generate`` prints for its dataset); then per trajectory and averaged: whole-rollout relative
errors of q, v, σ for both models, and ms a step.

    .venv/bin/python benchmarks/corotated_baseline.py runs/s40_liver96/dataset.h5 [--split test] [--max K]

The moduli at rest (μ0, K0 [Pa]) are the dataset's scene law's; the split is the
training default (seed 0, 0.8/0.1/0.1, as ``thermognn train`` draws it; the one torch import). docs/accuracy.md,
session 40. Rayleigh damping and quasi-static data (no inertia) are refused.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import yaml

from thermognn.core.kinematics import (deformation_gradients, linear_cell_stress, node_average, polar_rotations,
                                       rotation_report, shape_gradients)
from thermognn.core.schema import Dataset


def moduli(ds: Dataset) -> tuple[float, float]:
    """(μ0, K0) [Pa] of the dataset's scene law at rest (``Material.shear_modulus``, ``bulk_modulus``;
    the FE side's module, which needs UFL: this script runs in the project's venv)."""
    from thermognn.generate.materials import material_from_config

    mat = material_from_config(yaml.safe_load(ds.config_yaml)["scene"]["material"])
    return mat.shear_modulus, mat.bulk_modulus


def element_stiffness(X, tets, lam, mu):
    """K_e [T, 12, 12] N/m (DOFs node-major: 3 a + c) of λ tr ε I + 2 μ ε on P1 tets, and its
    isochoric part (λ = −2μ/3), the part a Prony series relaxes."""
    grad, vol = shape_gradients(X, tets)
    B = np.zeros((len(tets), 6, 12))
    for a in range(4):
        for c in range(3):
            col = 3 * a + c
            B[:, c, col] = grad[:, a, c]                                # ε_cc
        B[:, 3, 3 * a + 0], B[:, 3, 3 * a + 1] = grad[:, a, 1], grad[:, a, 0]   # γ_12
        B[:, 4, 3 * a + 0], B[:, 4, 3 * a + 2] = grad[:, a, 2], grad[:, a, 0]   # γ_13
        B[:, 5, 3 * a + 1], B[:, 5, 3 * a + 2] = grad[:, a, 2], grad[:, a, 1]   # γ_23

    def D(l, m):
        d = np.zeros((6, 6))
        d[:3, :3] = l
        d[np.arange(3), np.arange(3)] += 2 * m
        d[np.arange(3, 6), np.arange(3, 6)] = m
        return d

    Ke = lambda d: np.einsum("t,tri,rs,tsj->tij", vol, B, d, B)         # noqa: E731
    return Ke(D(lam, mu)), Ke(D(-2.0 * mu / 3.0, mu))


class Corotated:
    """The linearised solid with per-cell corotation (module docstring), over the free DOFs of
    ``lin`` (a ``LinearSolid``: its mass, free set, Newmark constants, Prony terms, body force)."""

    def __init__(self, lin, X, tets, lam, mu, dt, frozen=False):
        if any(float(r) != 0.0 for r in lin.rayleigh) or lin.integrator != "newmark":
            raise SystemExit("corotated baseline: Newmark without Rayleigh damping only")
        self.lin, self.X, self.tets, self.dt, self.frozen = lin, X, np.asarray(tets), dt, frozen
        self.K, self.K_iso = element_stiffness(X, tets, lam, mu)
        self.terms = lin.relaxation(dt)
        shrink = sum(g * (1.0 - c) for g, _, c in self.terms)
        self.K_dt = self.K - shrink * self.K_iso if self.terms else self.K
        dofs = (3 * self.tets[:, :, None] + np.arange(3)).reshape(len(tets), 12)  # [T, 12]
        self.dofs = dofs
        self.rows = np.repeat(dofs, 12, axis=1).ravel()
        self.cols = np.tile(dofs, (1, 12)).ravel()
        self.free = np.flatnonzero(lin.free)
        self.n = 3 * len(X)
        self.grad = shape_gradients(X, tets)[0]
        self.Xe = X[self.tets].reshape(len(tets), 12)

    def rotations(self, x):
        """Block-diagonal R_e [T, 12, 12] at positions x [N, 3] (I when frozen)."""
        R = np.broadcast_to(np.eye(3), (len(self.tets), 3, 3)) if self.frozen else \
            polar_rotations(deformation_gradients(x, self.tets, self.grad))
        Rb = np.zeros((len(self.tets), 12, 12))
        for a in range(4):
            Rb[:, 3 * a:3 * a + 3, 3 * a:3 * a + 3] = R
        return Rb

    def assemble(self, Ke):
        return sp.coo_matrix((Ke.ravel(), (self.rows, self.cols)), shape=(self.n, self.n)).tocsc()

    def scatter(self, fe):
        out = np.zeros(self.n)
        np.add.at(out, self.dofs.ravel(), fe.ravel())
        return out

    def rollout(self, u0, v0, forces):
        """Full-DOF displacements U [S, 3N] and velocities V [S, 3N] (clamped DOFs zero) from the
        data's u0, v0 [3N] under the nodal forces [S, 3N] (Newmark, as ``LinearSolid.rollout``)."""
        lin, dt, f = self.lin, self.dt, self.free
        M = lin.mass
        F = np.asarray(forces, float)[:, f]
        if lin.body_force is not None:
            F = F + np.asarray(lin.body_force)[None]
        b, g = float(lin.beta), float(lin.gamma)
        c0, c1 = 1.0 / (b * dt**2), 1.0 / (2.0 * b) - 1.0
        u_full, v = np.array(u0, float), np.array(v0, float)[f]
        x = lambda uf: (self.X.ravel() + uf).reshape(-1, 3)            # noqa: E731
        local = lambda Rb, uf: np.einsum("tji,tj->ti", Rb, x(uf)[self.tets].reshape(-1, 12)) - self.Xe  # noqa: E731
        Rb = self.rotations(x(u_full))
        d = local(Rb, u_full)
        h = [np.einsum("tij,tj->ti", self.K_iso, d) for _ in self.terms]   # internal forces, local frames
        f_int = self.scatter(np.einsum("tij,tj->ti", Rb, np.einsum("tij,tj->ti", self.K, d)))[f]
        solve_m = sla.factorized(sp.csc_matrix(M))
        a = solve_m(F[0] - f_int)
        U, V = [u_full.copy()], [self._full(v)]
        for s in range(1, F.shape[0]):
            Rb = self.rotations(x(u_full))
            d_old = local(Rb, u_full)
            hist = sum((gi * (decay * hi - weight * np.einsum("tij,tj->ti", self.K_iso, d_old))
                        for (gi, decay, weight), hi in zip(self.terms, h)), np.zeros_like(d_old))
            KR = np.einsum("tij,tjk,tlk->til", Rb, self.K_dt, Rb)       # R K_dt Rᵀ per cell
            # f_int(u_new) = Σ R K_dt (Rᵀ (X + u_new) − X) + Σ R hist = K_R u_new + offset
            offset = self.scatter(np.einsum("tij,tj->ti", Rb, np.einsum("tij,tj->ti", self.K_dt,
                                  np.einsum("tji,tj->ti", Rb, self.Xe) - self.Xe) + hist))[f]
            A = (c0 * M + self.assemble(KR)[f][:, f]).tocsc()
            pred = c0 * (u_full[f] + dt * v) + c1 * a
            u_new = np.zeros(self.n)
            u_new[f] = sla.spsolve(A, F[s] + M @ pred - offset)
            a_new = c0 * u_new[f] - pred
            v = v + dt * ((1 - g) * a + g * a_new)
            d_new = local(Rb, u_new)
            h = [decay * hi + weight * np.einsum("tij,tj->ti", self.K_iso, d_new - d_old)
                 for (_, decay, weight), hi in zip(self.terms, h)]
            u_full, a = u_new, a_new
            U.append(u_full.copy())
            V.append(self._full(v))
        return np.asarray(U), np.asarray(V)

    def _full(self, vf):
        out = np.zeros(self.n)
        out[self.free] = vf
        return out


def whole(pred, truth):
    return float(np.linalg.norm(pred[1:] - truth[1:]) / np.linalg.norm(truth[1:]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--split", default="test", choices=["train", "val", "test"])
    ap.add_argument("--max", type=int, default=0, help="at most this many trajectories (0: all)")
    args = ap.parse_args()
    ds = Dataset(args.dataset)
    lin, L, dt = ds.linear_solid(), ds.layout, ds.dt
    X, tets = ds.mesh.nodes, ds.mesh.tets
    mu, kappa = moduli(ds)
    lam = kappa - 2.0 * mu / 3.0
    from thermognn.train.data import split_names                       # the split train draws (seed 0)

    names = split_names(ds, (0.8, 0.1, 0.1), 0)[args.split]
    if args.max:
        names = names[:args.max]
    _, vol = shape_gradients(X, tets)
    sq, ss = L.slice("v"), L.slice("sigma")
    rep = rotation_report(X, tets, (ds.read(n) for n in names), L, lam, mu, lin.prony, dt)
    print(f"rotations ({len(names)} {args.split} trajectories): cells turn up to {rep['rotation_max_deg']:.0f}° "
          f"(RMS {rep['rotation_rms_deg']:.1f}° at the last step); the linear stress of the data's own displacements "
          f"is off by {100 * rep['stress_plain']:.0f} % of its stress, corotated {100 * rep['stress_corotated']:.0f} %")
    corotated = Corotated(lin, X, tets, lam, mu, dt)                  # the element matrices, once for all
    rows = []
    for k, name in enumerate(names):
        traj = ds.read(name)
        z, force = traj.z, traj.force
        u0, v0 = (z[0, :, 0:3] - X).ravel(), z[0, :, sq].ravel()
        forces = force.reshape(force.shape[0], -1)
        if k == 0:                                                     # the frozen-rotation check
            Uf, _ = Corotated(lin, X, tets, lam, mu, dt, frozen=True).rollout(u0, v0, forces)
            Ul, _ = lin.rollout(lin.free_rows(z[:1, :, 0:3] - X[None])[0], lin.free_rows(z[:1, :, sq])[0],
                                lin.free_rows(force), dt)
            print(f"frozen-rotation check: |U_frozen - U_linear| / |U_linear| = "
                  f"{np.linalg.norm(Uf[:, lin.free] - Ul) / np.linalg.norm(Ul):.2e}")
        t0 = time.perf_counter()
        U, V = corotated.rollout(u0, v0, forces)
        ms = 1e3 * (time.perf_counter() - t0) / (z.shape[0] - 1)
        S, N = z.shape[0], z.shape[1]
        q = X[None] + U.reshape(S, N, 3)
        sig = node_average(linear_cell_stress(q, X, tets, lam, mu, lin.prony, dt, corotated=True), tets, vol, N)
        linear = lin.rollout_states(z, force, X, L, dt)
        row = {"name": name, "ms": ms,
               "corot": (whole(q, z[..., 0:3]), whole(V.reshape(S, N, 3), z[..., sq]), whole(sig, z[..., ss])),
               "linear": (whole(linear[..., 0:3], z[..., 0:3]), whole(linear[..., sq], z[..., sq]),
                          whole(linear[..., ss], z[..., ss]))}
        rows.append(row)
        print(f"{name}: linear q/v/sigma {row['linear'][0]:.2e} / {100 * row['linear'][1]:.1f} % / "
              f"{100 * row['linear'][2]:.1f} %   corotated {row['corot'][0]:.2e} / {100 * row['corot'][1]:.1f} % / "
              f"{100 * row['corot'][2]:.1f} %   ({ms:.0f} ms a step)", flush=True)
    for key in ("linear", "corot"):
        m = np.mean([r[key] for r in rows], axis=0)
        print(f"mean over {len(rows)} {args.split} trajectories, {key}: whole rollout q {m[0]:.2e}, v {100 * m[1]:.1f} %, "
              f"sigma {100 * m[2]:.1f} %")


if __name__ == "__main__":
    main()
