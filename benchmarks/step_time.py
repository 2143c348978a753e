"""Quiet, interleaved step timing of beam checkpoints (issue: beat the published 84 ms a step).

Times one network step as ``evaluate`` reports it (with a stress readout, σ read off the
positions too) for each checkpoint given, on the first test trajectory of the reference split:
``--warmup`` steps each, then ``--rounds`` rounds of ``--steps`` steps, the checkpoints taking
turns within each round so that a slow spell of this shared VM lands on all of them alike.
Prints every round (ms a step), the fastest and the median round, and, next to them, the error
recorded for that checkpoint (``figures.json`` beside it, or ``eval/rrmse.json`` of its run):
every speed figure comes with its error.

    .venv/bin/python benchmarks/step_time.py models/tignn_beam/model.ckpt runs/s66_c6/model.ckpt
    .venv/bin/python benchmarks/step_time.py --threads 2 --rounds 5 models/tignn_beam/model.ckpt

Run it with nothing else busy: a training run beside it (even stopped, holding its memory) has
made the same checkpoint time 20-40 % slower here. The load average is printed with the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def recorded_error(ckpt: Path) -> str:
    """The per-snapshot error recorded beside a checkpoint ("q / v / σ"), or why there is none."""
    for path, per_snapshot in ((ckpt.parent / "figures.json", lambda d: d["per_snapshot"]),
                               (ckpt.parent / "eval" / "rrmse.json", lambda d: d)):
        if path.exists():
            e = per_snapshot(json.loads(path.read_text()))
            return f"q {e['q']:.2e} / v {100 * e['v']:.2f} % / σ {100 * e['sigma']:.2f} % ({path})"
    return "no recorded error (no figures.json or eval/rrmse.json beside it: run thermognn evaluate)"


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--dataset", type=Path, default=ROOT / "runs" / "tignn_beam" / "dataset.h5")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args(argv)
    for p in [*args.checkpoints, args.dataset]:
        if not p.exists():
            parser.error(f"{p}: no such file (the dataset comes from `thermognn import tignn`)")

    sys.path.insert(0, str(ROOT))
    from thermognn.core.config import load_config
    from thermognn.train.checkpoint import load_checkpoint, model_from_checkpoint, torch_dtype
    from thermognn.train.data import load_data
    from thermognn.train.tignn_import import PUBLISHED

    torch.set_num_threads(args.threads)
    ckpts = [load_checkpoint(p) for p in args.checkpoints]
    models = [model_from_checkpoint(c).eval() for c in ckpts]
    split = load_config(["scene=tignn_beam"]).train.split
    data = {}                                 # one copy per dtype the checkpoints use
    for c in ckpts:
        dtype = torch_dtype(c["dtype"])
        if dtype not in data:
            data[dtype] = load_data(args.dataset, split, 0, dtype, parts=("test",))

    def stepper(model, dtype):
        d = data[dtype]
        t, g = d.of("test")[0], d.graph
        z, f, dt = t.z[0], t.force[1], torch.tensor(d.dt, dtype=dtype)

        def one_step():                       # a step as evaluate reports it
            return model.reported_step(z, f, g.edge_index, g.node_type, g.ref_pos, dt)
        return one_step

    steps = [stepper(m, torch_dtype(c["dtype"])) for m, c in zip(models, ckpts)]
    for one_step in steps:
        for _ in range(args.warmup):
            one_step()
    ms: list[list[float]] = [[] for _ in steps]
    for _ in range(args.rounds):
        for i, one_step in enumerate(steps):
            t0 = time.perf_counter()
            for _ in range(args.steps):
                one_step()
            ms[i].append((time.perf_counter() - t0) / args.steps * 1e3)

    load = os.getloadavg()[0]
    print(f"ms a step, {args.threads} threads, {args.rounds} interleaved rounds of {args.steps} steps after "
          f"{args.warmup} warm-up steps; load average {load:.1f} on {os.cpu_count()} cores; published model "
          f"{PUBLISHED['ms_per_step']:.0f} ms (quoted)")
    for p, rounds in zip(args.checkpoints, ms):
        print(f"{p}: rounds " + " ".join(f"{x:.1f}" for x in rounds)
              + f"; fastest {min(rounds):.1f}, median {statistics.median(rounds):.1f} ms")
        print(f"    error: {recorded_error(p)}")
    if load > (os.cpu_count() or 1):
        print("warning: the load average exceeds the cores: these figures are contended; repeat on a quiet machine")


if __name__ == "__main__":
    main(sys.argv[1:])
