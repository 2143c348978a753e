"""How much of the linearised FE baseline's error is the cells' rotation?

The solid linearised at rest (``/linear``, ``evaluate``'s baseline and ``model=linear_prior``'s
step) reads a rotation as strain. This script rolls out, beside it, the same solid *corotated*
per cell (``thermognn/core/corotated.py``, which ``evaluate`` reports too): each cell's linear
force measured in its rotated frame, f_e = R_e K_e (R_eᵀ x_e − X_e), its Prony history in that
frame, the data's Newmark step with R_e implicit (fixed-point sweeps, at most ``--sweeps``;
``--sweeps 1`` takes R_e at the start of each step, session 40's form), and its stress
``linear_cell_stress(corotated=True)`` node-averaged. With every R_e held at I it is the
linearised model exactly (checked first, printed as ``frozen-rotation check``). Printed first:
``rotation_report`` of those trajectories (what ``generate`` prints for its dataset); then per
trajectory and averaged: whole-rollout relative errors of q, v, σ for both models, and ms a step.

    .venv/bin/python benchmarks/corotated_baseline.py runs/s42_shell96/dataset.h5 [--split test] [--max K] [--sweeps S]

The moduli at rest (μ0, K0 [Pa]) are those ``/linear`` stores (datasets since session 42), else
the dataset's scene law's; the split is the training default (seed 0, 0.8/0.1/0.1, as
``thermognn train`` draws it; the one torch import). docs/accuracy.md, sessions 40 and 42.
Quasi-static data (no inertia) are refused.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from thermognn.core.corotated import MAX_SWEEPS, CorotatedSolid
from thermognn.core.kinematics import rotation_report
from thermognn.core.schema import Dataset


def moduli(ds: Dataset) -> tuple[float, float]:
    """(μ0, K0) [Pa] at rest: those ``/linear`` stores, else the dataset's scene law's
    (``Material.shear_modulus``, ``bulk_modulus``; the FE side's module, which needs UFL: this
    script runs in the project's venv)."""
    lin = ds.linear_solid()
    if lin.shear_modulus is not None and lin.bulk_modulus is not None:
        return lin.shear_modulus, lin.bulk_modulus
    from thermognn.generate.materials import material_from_config

    mat = material_from_config(ds.material)
    return mat.shear_modulus, mat.bulk_modulus


def whole(pred, truth):
    return float(np.linalg.norm(pred[1:] - truth[1:]) / np.linalg.norm(truth[1:]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--split", default="test", choices=["train", "val", "test"])
    ap.add_argument("--max", type=int, default=0, help="at most this many trajectories (0: all)")
    ap.add_argument("--sweeps", type=int, default=MAX_SWEEPS,
                    help=f"fixed-point sweeps a step at most (1: rotations from the step's start; default {MAX_SWEEPS})")
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
    sq, ss = L.slice("v"), L.slice("sigma")
    rep = rotation_report(X, tets, (ds.read(n) for n in names), L, lam, mu, lin.prony, dt)
    print(f"rotations ({len(names)} {args.split} trajectories): cells turn up to {rep['rotation_max_deg']:.0f}° "
          f"(RMS {rep['rotation_rms_deg']:.1f}° at the last step) and strain up to {100 * rep['strain_max']:.0f} % "
          f"(volume RMS {100 * rep['strain_rms']:.1f} % where it peaks); the linear stress of the data's own displacements "
          f"is off by {100 * rep['stress_plain']:.0f} % of its stress, corotated {100 * rep['stress_corotated']:.0f} %")
    corotated = CorotatedSolid(lin, X, tets, lam, mu, max_sweeps=args.sweeps)   # the element matrices, once
    rows = []
    for k, name in enumerate(names):
        traj = ds.read(name)
        z, force = traj.z, traj.force
        linear = lin.rollout_states(z, force, X, L, dt)
        if k == 0:                                                     # the frozen-rotation check
            frozen = CorotatedSolid(lin, X, tets, lam, mu, frozen=True).rollout_states(z, force, X, L, dt)
            print(f"frozen-rotation check: |z_frozen - z_linear| / |z_linear| = "
                  f"{np.linalg.norm(frozen - linear) / np.linalg.norm(linear):.2e}")
        t0 = time.perf_counter()
        pred = corotated.rollout_states(z, force, X, L, dt)
        ms = 1e3 * (time.perf_counter() - t0) / (z.shape[0] - 1)
        errors = lambda p: tuple(whole(p[..., sl], z[..., sl]) for sl in (slice(0, 3), sq, ss))  # noqa: E731
        row = {"name": name, "ms": ms, "corot": errors(pred), "linear": errors(linear)}
        rows.append(row)
        print(f"{name}: linear q/v/sigma {row['linear'][0]:.2e} / {100 * row['linear'][1]:.1f} % / "
              f"{100 * row['linear'][2]:.1f} %   corotated {row['corot'][0]:.2e} / {100 * row['corot'][1]:.1f} % / "
              f"{100 * row['corot'][2]:.1f} %   ({ms:.0f} ms a step)"
              + ("" if (crushed := corotated.first_inversion(pred[..., 0:3])) is None else
                 f"   corotated turns {crushed[1]} cell(s) inside out from step {crushed[0]}"), flush=True)
    for key in ("linear", "corot"):
        m = np.mean([r[key] for r in rows], axis=0)
        print(f"mean over {len(rows)} {args.split} trajectories, {key}: whole rollout q {m[0]:.2e}, v {100 * m[1]:.1f} %, "
              f"sigma {100 * m[2]:.1f} %")
    c = corotated.count
    print(f"corotated: {c.mean:.2f} sweeps a step on average, at most {c.most}, {c.unconverged} of {c.steps} steps "
          f"stopped at {args.sweeps} before the change fell below {corotated.tol:g}; "
          f"{np.mean([r['ms'] for r in rows]):.0f} ms a step")


if __name__ == "__main__":
    main()
