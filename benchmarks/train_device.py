"""The same training run on several devices (``train.device``): seconds per epoch beside the
loss and validation error each reaches, and how far they are from the first device's.

    .venv/bin/python benchmarks/train_device.py [--devices cpu,cuda] [--out /tmp/train_device] \\
        [overrides ...]      # e.g. scene=shell model=linear_prior model.prior_corotated=true \\
                             #      paths.dataset=runs/shell/dataset.h5 train.epochs=0 train.rollout_epochs=1 ...

Without ``paths.dataset`` it trains on a small synthetic oscillator (``train.synthetic``). The
random draws are made on the CPU (``thermognn/train/device.py``), so the devices' losses should
agree to float32 round-off; a larger gap is a bug, not noise. Session 44, on an H200 machine
(the shell, 8 cases, 2 CPU threads): TIGNN epoch 4.3 s on the GPU against 16.7 s on the CPU,
corotated-prior window epoch 30.1 s against 103.1 s, losses within 4e-6 relative.
"""

from __future__ import annotations

import argparse
import csv
import shutil
from pathlib import Path

from thermognn.core.config import load_config
from thermognn.train import train
from thermognn.train.synthetic import write_oscillator_dataset


def _rows(out: Path) -> list[dict]:
    with open(out / "metrics.csv") as fh:
        return list(csv.DictReader(fh))


def _rel(a: str, b: str) -> str:
    if not a or not b:
        return ""
    a_, b_ = float(a), float(b)
    return f"{abs(b_ - a_) / max(abs(a_), 1e-300):.1e}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--devices", default="cpu,cuda", help="comma-separated train.device values")
    ap.add_argument("--out", default="/tmp/train_device")
    args, overrides = ap.parse_known_args()
    root = Path(args.out)
    devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    synthetic = not any(o.startswith("paths.dataset=") for o in overrides)
    results = {}
    for k, device in enumerate(devices):
        out = root / f"{k}_{device.replace(':', '_')}"
        shutil.rmtree(out, ignore_errors=True)
        if synthetic:
            write_oscillator_dataset(out / "dataset.h5", n_trajectories=6, steps=10)
        cfg = load_config([f"out={out}", "train.tensorboard=false", "train.resume=false", *overrides,
                           f"train.device={device}"])
        train(cfg)
        results[(k, device)] = _rows(out)
    first = devices[0]
    reference = results[(0, first)]
    print(f"\n{'device':<8} {'epoch':>5} {'seconds':>9} {'loss':>12} {'val_error':>12}  rel. to {first} (loss, val)")
    for (_, device), rows in results.items():
        for row, ref in zip(rows, reference):
            print(f"{device:<8} {row['epoch']:>5} {float(row['seconds']):9.2f} {float(row['loss']):12.6e} "
                  f"{float(row['val_error']) if row['val_error'] else float('nan'):12.6e}  "
                  f"{_rel(ref['loss'], row['loss'])}, {_rel(ref['val_error'], row['val_error'])}")


if __name__ == "__main__":
    main()
