"""Shared test helpers."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

#: rank 0 of a torchrun training dies right after the mid-epoch write of model.last.ckpt at batch
#: STOP of the second epoch (STOP = 0: never); ``{module}`` is where the loop finds save_checkpoint
_INTERRUPTED_TRAINING = """import sys
import {module} as saver
from thermognn.core.config import load_config
from thermognn.train import train

out, stop, overrides = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
real = saver.save_checkpoint


def interrupt(state, path):
    real(state, path)
    if stop and "mid_epoch" in state and (len(state["history"]), state["mid_epoch"]["batch"]) == (1, stop):
        raise SystemExit("interrupted")


saver.save_checkpoint = interrupt
train(load_config([f"out={{out}}", "train.checkpoint_minutes=1e-9", *overrides]))
"""


@pytest.fixture
def torchrun_train(tmp_path):
    """``run(out, stop, overrides, processes=2, module=...)``: ``thermognn train`` under torchrun
    (one thread each, mid-epoch checkpoints after every batch), rank 0 interrupted as
    ``_INTERRUPTED_TRAINING`` says; returns the finished process."""
    torchrun = Path(sys.executable).with_name("torchrun")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def run(out, stop: int, overrides, processes: int = 2, module: str = "thermognn.train.loop"):
        script = tmp_path / f"train_{module.replace('.', '_')}.py"
        script.write_text(_INTERRUPTED_TRAINING.format(module=module))
        return subprocess.run([str(torchrun), "--standalone", f"--nproc_per_node={processes}", str(script), str(out),
                               str(stop), *overrides], capture_output=True, text=True, timeout=600, env=env)
    return run
