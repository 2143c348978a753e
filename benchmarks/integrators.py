"""Integrators: what the implicit midpoint rule buys (energy balance, rollout error) and what it
costs (network calls and ms per step), on one dataset, the same network trained once per rule.

For a Hamiltonian scene (the shell) the learned dynamics conserve the learned energy E exactly in
continuous time; a discrete step does not. ``energy balance`` is sum |E_s - E_(s-1) - dt P| /
sum |E_s - E_(s-1)| over the test rollouts (P: the port's power), i.e. the share of the energy
change that no work explains: the integrator's drift.

    .venv/bin/thermognn generate scene=shell out=runs/shell scene.loads.n_trajectories=10
    .venv/bin/python benchmarks/integrators.py --dataset runs/shell/dataset.h5 scene=shell train.epochs=8
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def main(argv: list[str]) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", type=Path, required=True, help="HDF5 dataset from thermognn generate")
    parser.add_argument("--out", type=Path, default=Path("runs/integrators"))
    parser.add_argument("--integrators", nargs="+", default=["euler", "midpoint"])
    args, overrides = parser.parse_known_args(argv)

    from thermognn.core.config import load_config
    from thermognn.train import evaluate, train

    rows = {}
    for integrator in args.integrators:
        cfg = load_config([f"paths.dataset={args.dataset.resolve()}", f"out={args.out / integrator}",
                           f"model.integrator={integrator}", *overrides])
        t0 = time.perf_counter()
        train(cfg)
        res = evaluate(cfg)
        res["train_min"] = (time.perf_counter() - t0) / 60.0
        rows[integrator] = res
    groups = [k for k in next(iter(rows.values())) if k not in ("ms_per_step", "energy_balance", "train_min")]
    print(f"\nintegrators on {args.dataset} (test rollouts; overrides: {' '.join(overrides) or 'none'})")
    print(f"{'integrator':12s} " + " ".join(f"{g:>9s}" for g in groups)
          + f" {'energy bal':>10s} {'ms/step':>8s} {'train min':>9s}")
    for name, r in rows.items():
        print(f"{name:12s} " + " ".join(f"{r[g]:9.2e}" for g in groups)
              + f" {r['energy_balance']:10.2e} {r['ms_per_step']:8.1f} {r['train_min']:9.1f}")
    return rows


if __name__ == "__main__":
    main(sys.argv[1:])
