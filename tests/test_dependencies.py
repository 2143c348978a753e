"""Stage dependencies stay apart: a user with a trained model and a device needs neither FEniCSx
nor the training code, and the FE side never loads torch. The one place these rules are checked."""

import subprocess
import sys

import pytest

FENICS = ["dolfinx", "gmsh", "ufl", "basix"]
LOAD_PLUGINS = "import thermognn.devices as d\nfor n in ('sim', 'replay', 'geomagic', 'senseglove'): d.load(n)\n"
CASES = [
    # (modules imported, extra statements run after them, modules that must stay unloaded)
    (["thermognn.cli", "thermognn.core.config", "thermognn.core.schema"], "", ["torch", "dolfinx"]),
    (["thermognn.generate", "thermognn.generate.pipeline"], "", ["torch"]),
    (["thermognn.train", "thermognn.export", "thermognn.train.loop", "thermognn.train.evaluation",
      "thermognn.export.exporter"], "", FENICS),
    (["thermognn.serve", "thermognn.serve.loop", "thermognn.serve.runner"], "",
     ["torch", "dolfinx", "thermognn.train", "thermognn.generate"]),
    (["thermognn.devices"], LOAD_PLUGINS, ["torch", "dolfinx"]),  # plugins resolved through entry points
]


@pytest.mark.parametrize("imported, statements, forbidden", CASES, ids=lambda x: ",".join(x) if isinstance(x, list) else "")
def test_stage_imports(imported, statements, forbidden):
    code = (f"import sys\nfor m in {imported!r}: __import__(m)\n{statements}"
            f"bad = [m for m in {forbidden!r} if m in sys.modules]\nprint(','.join(bad))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "", f"importing {imported} loaded {res.stdout.strip()}"
