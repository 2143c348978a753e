"""What the linear prior's accuracy costs in time: a checkpoint trained with ``model.prior=linear``
(``thermognn train model=linear_prior ...``, ``thermognn/train/hybrid.py``) rolled out over its
test trajectories with 1 and 2 network calls per step (``model.prior_sweeps``, the same weights),
each error beside the ms per step, and the linearised FE model's rows (no learning) beside them;
plus the exported (TorchScript) carried-state step that ``serve`` runs, timed alone.

    .venv/bin/python benchmarks/hybrid_prior.py runs/block_prior [--dataset PATH] [--threads 2]

Errors: the mean per-snapshot relative L2 error per group (``evaluate``'s table) and the
whole-rollout error ||z_pred - z_gt|| / ||z_gt|| over all steps and nodes (the model-selection
metric). Step times: the mean over the test rollouts in this process, warmed up by one rollout.
Writes ``<run>/hybrid_prior.json``.

(Sessions 11-12 ran the experiments behind the prior with an earlier version of this script,
which also trained; ``git log -- benchmarks/hybrid_prior.py``.)
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="folder of the run (model.ckpt; out= of thermognn train)")
    ap.add_argument("--dataset", default=None, help="the dataset (default: the checkpoint's own path)")
    ap.add_argument("--sweeps", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from thermognn.core.io import atomic_path
    from thermognn.core.schema import Dataset
    from thermognn.export.exporter import build_exported, script
    from thermognn.train.checkpoint import load_checkpoint, model_from_checkpoint
    from thermognn.train.data import load_data
    from thermognn.train.evaluation import linear_baseline
    from thermognn.train.model import parameter_count
    from thermognn.train.rollout import rollout, rrmse_per_step, trajectory_error, trajectory_rrmse

    run = Path(args.run)
    ckpt = load_checkpoint(run / "model.ckpt")
    if not ckpt.get("prior"):
        raise SystemExit(f"{run / 'model.ckpt'}: not a model.prior=linear checkpoint")
    ds_path = Path(args.dataset or ckpt["dataset"])
    # states and loads in float64, as evaluate reads them for a prior model (session 15)
    data = load_data(ds_path, [0.8, 0.1, 0.1], 0, torch.float32, parts=(), state_dtype=torch.float64)
    data.split = {k: list(v) for k, v in ckpt["split"].items()}
    for n in data.split["test"]:
        data.read(n)
    test, layout, g = data.of("test"), data.layout, data.graph
    mean = lambda rows: {k: float(np.mean([r[k] for r in rows])) for k in layout.names}  # noqa: E731

    rows = {}
    for sweeps in args.sweeps:
        model = model_from_checkpoint({**ckpt, "prior": {**ckpt["prior"], "sweeps": sweeps}}, data.dataset).eval()
        rollout(model, g, test[0].z[0], test[0].force, data.dt)                  # warm-up
        per, whole, elapsed, steps = [], [], 0.0, 0
        for t in test:
            t0 = time.perf_counter()
            pred = rollout(model, g, t.z[0], t.force, data.dt)
            elapsed += time.perf_counter() - t0
            steps += pred.shape[0] - 1
            per.append(trajectory_rrmse(rrmse_per_step(pred, t.z, layout)))
            whole.append(trajectory_error(pred, t.z, layout))
        rows[f"hybrid, {sweeps} call(s)/step"] = {"snapshot": mean(per), "whole": mean(whole),
                                                   "ms_per_step": 1e3 * elapsed / steps}
    lin = linear_baseline(data, test)
    rows["linearised FE"] = lin

    # the exported step serve runs: the carried state, scripted, one call at a time
    exported = script(build_exported(ckpt, Dataset(ds_path)))
    f = torch.as_tensor(data.dataset.read(data.split["test"][0]).force, dtype=torch.float64)
    with warnings.catch_warnings(), torch.jit.optimized_execution(False):
        warnings.simplefilter("ignore")
        z = exported.z0.clone()
        for s in range(3):
            z = exported(z, f[min(s + 1, len(f) - 1)])
        t0 = time.perf_counter()
        for s in range(len(f) - 1):
            z = exported(z, f[s + 1])
        scripted_ms = 1e3 * (time.perf_counter() - t0) / (len(f) - 1)

    result = {"checkpoint": str(run / "model.ckpt"), "dataset": str(ds_path), "test": data.split["test"],
              "parameters": parameter_count(model), "epochs": ckpt.get("epoch"), "rows": rows,
              "scripted_ms_per_step": scripted_ms, "threads": args.threads}
    with atomic_path(run / "hybrid_prior.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    print(f"{run / 'model.ckpt'}: {parameter_count(model)} parameters, epoch {ckpt.get('epoch')}, "
          f"{len(test)} test trajectories, {args.threads} threads")
    print(f"{'':28s} per snapshot " + " / ".join(layout.names) + "      whole rollout " + " / ".join(layout.names))
    for name, r in rows.items():
        if "snapshot" not in r:
            print(f"{name:28s} {r.get('note', '')}")
            continue
        print(f"{name:28s} " + " / ".join(f"{r['snapshot'][k]:.3g}" for k in layout.names) + "      "
              + " / ".join(f"{r['whole'][k]:.3g}" for k in layout.names) + f"   {r['ms_per_step']:.2f} ms/step")
    print(f"exported (TorchScript) carried step, 1 call: {scripted_ms:.2f} ms/step")


if __name__ == "__main__":
    main()
