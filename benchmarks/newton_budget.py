"""How many Newton iterations a step does the data's own FE model need?

``generate`` solves each time step to a tight residual (``solver.newton_rtol``, up to
``solver.max_iterations`` iterations, cutting the step where Newton fails). A real-time FE
solver takes a fixed budget instead: one iteration from the step's predictor is the linearly
implicit step (a single linear solve with the tangent at the predictor, as SOFA's implicit
Euler takes). This script re-solves a dataset's trajectories with the dataset's own scene (mesh,
law, Prony terms, Newmark rule, loads), stopping every step after exactly k iterations and
accepting that iterate, and prints each trajectory's whole-rollout relative errors of q, v and
σ against the stored data (the metric of ``evaluate`` and ``benchmarks/corotated_baseline.py``),
with the FE's time a step: what the physics itself costs at that accuracy. ``--iterations 0``
is the scene's own solver (to its tolerance, cutting steps where Newton fails: the data itself,
a check that the re-solve reproduces it, and its cost).

    .venv/bin/python benchmarks/newton_budget.py runs/s47_bunny48/dataset.h5 --iterations 1 2 3 0 [--split test] [--max K] [--names traj_14,traj_45]

Run with ``OMP_NUM_THREADS=1`` for the single-thread figures of docs/accuracy.md (session 49).
The split is the training default (seed 0, 0.8/0.1/0.1, as ``thermognn train`` draws it; its
one torch import); ``--names`` picks trajectories instead. A trajectory whose rollout fails
(a non-finite residual, or the LU) or blows up is reported as such, and its errors (huge) are
kept in the mean, as ``evaluate`` keeps a diverged rollout's.
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import yaml
from omegaconf import OmegaConf

from thermognn.core.schema import Dataset
from thermognn.generate.pipeline import build_solid, simulate
from thermognn.generate.scene import between_node_points, loadable_faces, scene_from_config
from thermognn.generate.solid import StepReport


def whole(pred: np.ndarray, truth: np.ndarray) -> float:
    """‖pred − truth‖ / ‖truth‖ over steps 1.. (the whole-rollout relative error)."""
    return float(np.linalg.norm(pred[1:] - truth[1:]) / np.linalg.norm(truth[1:]))


def fmt(column: str, error: float) -> str:
    """q relative (positions: small numbers), v and σ in %."""
    return f"{column} {error:.2e}" if column == "q" else f"{column} {100 * error:.3g} %"


def label(iterations: int) -> str:
    return f"{iterations} Newton iteration(s)" if iterations else "the scene's solver (converged)"


def fixed_budget(solid, iterations: int) -> None:
    """Make ``solid.newton`` stop after exactly ``iterations`` iterations and accept the iterate
    (it still stops earlier where the residual already meets the scene's tolerance)."""
    newton, limit = solid.newton, solid.opt.max_iterations

    def budgeted() -> StepReport:
        solid.opt.max_iterations = iterations
        try:
            report = newton()
        finally:
            solid.opt.max_iterations = limit
        if not report.ok and report.reason.startswith("Newton did not converge"):
            return StepReport(True, "", iterations)
        return report

    solid.newton = budgeted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--iterations", type=int, nargs="+", default=[1, 2, 0],
                    help="Newton iterations a step (0: the scene's own solver, to its tolerance)")
    ap.add_argument("--split", default="test", choices=["train", "val", "test"])
    ap.add_argument("--max", type=int, default=0, help="at most this many trajectories (0: all)")
    ap.add_argument("--names", default="", help="comma-separated trajectory names instead of the split")
    args = ap.parse_args()
    for name in ("UFL", "ffcx"):
        logging.getLogger(name).setLevel(logging.WARNING)
    ds = Dataset(args.dataset)
    if args.names:
        names = args.names.split(",")
    else:
        from thermognn.train.data import split_names                   # the split train draws (seed 0)

        names = split_names(ds, (0.8, 0.1, 0.1), 0)[args.split]
    if args.max:
        names = names[:args.max]
    spec = scene_from_config(OmegaConf.create(yaml.safe_load(ds.config_yaml)).scene)
    layout = ds.layout
    columns = [("q", layout.slice("q"))] + [(c, layout.slice(c)) for c in ("v", "sigma") if c in layout.names]
    for k in args.iterations:
        solid, ntype, normals = build_solid(spec)
        between = between_node_points(solid.nodes, ntype, loadable_faces(solid.nodes, solid.cells[:, :4], ntype)
                                      if spec.loads.between_nodes else None, spec.loads)
        if k:
            fixed_budget(solid, k)
        rows, seconds, steps = [], 0.0, 0
        for name in names:
            data = ds.read(name)
            t0 = time.perf_counter()
            traj, cost = simulate(solid, spec, layout, int(name.rsplit("_", 1)[1]), ntype, normals, between)
            seconds += time.perf_counter() - t0
            steps += cost.steps
            n = len(traj.z)
            if n < len(data.z):                                         # failed: hold its last state
                traj_z = np.concatenate([traj.z, np.repeat(traj.z[-1:], len(data.z) - n, axis=0)])
            else:
                traj_z = traj.z
            err = [whole(traj_z[..., sl], data.z[..., sl]) for _, sl in columns]
            rows.append(err)
            state = "" if traj.status == "ok" and max(err) < 1.0 else \
                f"   ({traj.status} at step {n}: {traj.reason})" if traj.status != "ok" else "   (blows up)"
            print(f"{label(k)}  {name}: " + " / ".join(fmt(c, e) for (c, _), e in zip(columns, err)) + state,
                  flush=True)
        sound = [r for r in rows if max(r) < 1.0]
        mean = np.mean(rows, axis=0)
        print(f"{label(k)} a step, {len(rows)} {args.split if not args.names else 'named'} trajectories: "
              f"mean whole rollout " + " / ".join(fmt(c, m) for (c, _), m in zip(columns, mean))
              + (f"; without the {len(rows) - len(sound)} that blow up " +
                 " / ".join(fmt(c, m) for (c, _), m in zip(columns, np.mean(sound, axis=0)))
                 if sound and len(sound) < len(rows) else "")
              + f"; {1e3 * seconds / max(steps, 1):.0f} ms a step (dolfinx, {len(spec.points)} nodes)", flush=True)


if __name__ == "__main__":
    main()
