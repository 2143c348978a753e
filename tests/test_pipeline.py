"""The whole pipeline, every stage real, on a tiny block: dolfinx solve -> HDF5 -> PyG training
-> TorchScript -> haptic loop in its own process against the simulated device."""

import subprocess
import sys

import pytest

from thermognn.core.config import load_config
from thermognn.core.schema import Dataset

pytestmark = pytest.mark.slow

TINY = [
    "scene.loads.n_trajectories=6",
    "scene.time.steps=6",
    "train.epochs=3",
    "model.hidden=16",
    "model.message_passing=2",
    "serve.duration=2.0",
    "serve.device=sim",
]


def run_cli(*args):
    res = subprocess.run([sys.executable, "-m", "thermognn.cli", *args], capture_output=True, text=True,
                         timeout=900)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-4000:]
    return res.stdout


def test_pipeline_end_to_end(tmp_path):
    out = f"out={tmp_path}"
    run_cli("generate", out, *TINY)
    ds = Dataset(tmp_path / "dataset.h5")
    assert len(ds.ok_names) >= 5 and ds.layout.names[:2] == ["q", "v"]

    run_cli("train", out, *TINY)
    assert (tmp_path / "model.ckpt").exists()
    text = run_cli("evaluate", out, *TINY)
    assert "q" in text

    run_cli("export", out, *TINY)
    assert (tmp_path / "model.pt").exists()

    from thermognn.serve import serve

    summary = serve(load_config([out, *TINY]))
    assert summary["final_force_N"] == 0.0
    assert summary["max_force_N"] > 0.0
    assert summary["loop_rate_hz"] > 0.0  # the loop ran; its rate is a benchmark figure, not asserted
