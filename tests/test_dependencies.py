"""Stage dependencies stay apart: a user with a trained model and a device needs neither FEniCSx
nor the training code, and the FE side never loads torch."""

import subprocess
import sys

import pytest

CASES = [
    # (modules imported, modules that must stay unloaded)
    (["thermognn.cli", "thermognn.core.config", "thermognn.core.schema"], ["torch", "dolfinx"]),
    (["thermognn.generate"], ["torch"]),
    (["thermognn.train", "thermognn.export"], ["dolfinx"]),
    (["thermognn.serve"], ["dolfinx", "thermognn.train", "thermognn.generate"]),
    (["thermognn.devices", "thermognn.devices.sim", "thermognn.devices.replay", "thermognn.devices.geomagic",
      "thermognn.devices.senseglove"], ["torch", "dolfinx"]),
]


@pytest.mark.parametrize("imported, forbidden", CASES, ids=lambda x: ",".join(x))
def test_stage_imports(imported, forbidden):
    code = (f"import sys\nfor m in {imported!r}: __import__(m)\n"
            f"bad = [m for m in {forbidden!r} if m in sys.modules]\nprint(','.join(bad))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "", f"importing {imported} loaded {res.stdout.strip()}"
