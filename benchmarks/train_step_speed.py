"""Wall time of one TIGNN step (forward + autograd dE/dz, dS/dz) on CPU, eager and TorchScript.

    .venv/bin/python benchmarks/train_step_speed.py [--threads 2] [--repeats 50] [--json out.json]
        [--dataset runs/tignn_beam/dataset.h5 ...]   # also time on the graphs of these datasets
        [model.edge_operators=true ...]               # config overrides for the model timed

TorchScript is timed twice: with the default (profiling, optimising) graph executor and inside
``torch.jit.optimized_execution(False)``, which for this autograd-in-forward model is as fast
as eager and is what a latency-bound caller should use.

Graphs: structured tet boxes of 150 nodes (6x5x5) and 756 nodes (12x9x7, the size of the TIGNN
beam), state D = 12 (q, v, sigma), the default model (conf/model/tignn.yaml) in both structures.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
import warnings

import torch

from thermognn.core.config import load_config
from thermognn.train.data import Graph
from thermognn.train.model import build_model, hyperparameters, parameter_count
from thermognn.train.synthetic import box_mesh


def graph_of(shape) -> Graph:
    mesh = box_mesh(*shape)
    return Graph(torch.as_tensor(mesh.nodes, dtype=torch.float32), torch.as_tensor(mesh.edges()),
                 torch.as_tensor(mesh.node_type.astype("int64")), torch.zeros(0, 3, dtype=torch.long))


def time_step(fn, repeats: int) -> tuple[float, float]:
    """(median, min) wall time of one call [ms]; the minimum is robust to other load on the CPU."""
    for _ in range(5):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times), min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=50)
    ap.add_argument("--json", default=None)
    ap.add_argument("--dataset", nargs="*", default=[], help="thermognn datasets whose graphs to time too")
    args, overrides = ap.parse_known_args()
    torch.set_num_threads(args.threads)
    cfg = load_config(overrides)
    results = []
    graphs = [graph_of(shape) for shape in ((6, 5, 5), (12, 9, 7))]
    for path in args.dataset:
        from thermognn.core.schema import Dataset
        from thermognn.train.data import load_graph

        graphs.append(load_graph(Dataset(path), torch.float32))
    for g in graphs:
        n = g.n_nodes
        z = torch.cat([g.ref_pos, torch.zeros(n, 9)], 1)
        f = torch.zeros(n, 3)
        dt = torch.tensor(0.01)
        for structure in ("hamiltonian", "generic"):
            hp = hyperparameters(cfg.model, 12, [3, 4, 5], structure == "hamiltonian")
            torch.manual_seed(0)
            model = build_model(hp).eval()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                scripted = torch.jit.script(model)
            args_ = (g.edge_index, g.node_type, g.ref_pos, dt)
            eager_ms = time_step(lambda: model.step(z, f, *args_), args.repeats)
            # unoptimised first: once the optimising executor has specialised a graph, it keeps it
            with torch.jit.optimized_execution(False):  # what a latency-bound caller (serve) should use
                plain_ms = time_step(lambda: scripted.step(z, f, *args_), args.repeats)
            script_ms = time_step(lambda: scripted.step(z, f, *args_), args.repeats)
            row = {"nodes": n, "edges": int(g.edge_index.shape[1]), "structure": structure,
                   "parameters": parameter_count(model), "eager_median_ms": round(eager_ms[0], 3),
                   "eager_min_ms": round(eager_ms[1], 3), "torchscript_median_ms": round(script_ms[0], 3),
                   "torchscript_min_ms": round(script_ms[1], 3),
                   "torchscript_unoptimized_median_ms": round(plain_ms[0], 3), "threads": args.threads}
            results.append(row)
            print(f"{n:4d} nodes {row['edges']:5d} edges {structure:11s} {row['parameters']:7d} params  "
                  f"eager {eager_ms[0]:7.2f} (min {eager_ms[1]:6.2f}) ms  "
                  f"torchscript {script_ms[0]:7.2f} (min {script_ms[1]:6.2f}) ms  "
                  f"torchscript, optimized_execution(False) {plain_ms[0]:7.2f} ms  ({args.threads} threads)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()
