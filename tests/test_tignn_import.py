"""TIGNN beam importer: safe loading (no arbitrary unpickling) and a faithful conversion."""

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from thermognn.core.errors import DataError
from thermognn.core.schema import Dataset
from thermognn.train.tignn_import import import_tignn

BEAM = Path(__file__).resolve().parents[1].parent / "shared" / "datasets" / "tignn_beam"


class Exploit:
    def __reduce__(self):
        return (os.system, ("touch pwned",))


def test_malicious_pickle_is_refused(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    torch.save([Exploit()], src / "beam_1.pt")
    with pytest.raises(DataError, match="beam_1.pt: refused to unpickle"):
        import_tignn(src, tmp_path / "out.h5")
    assert not (tmp_path / "pwned").exists() and not Path("pwned").exists()
    assert not (tmp_path / "out.h5").exists()


def test_empty_folder(tmp_path):
    with pytest.raises(DataError, match="no beam_K.pt files"):
        import_tignn(tmp_path, tmp_path / "out.h5")


@pytest.mark.skipif(not BEAM.is_dir(), reason="../shared/datasets/tignn_beam not present")
def test_converts_real_beam_files(tmp_path):
    from torch_geometric.data import Data
    from torch_geometric.data.storage import GlobalStorage

    src = tmp_path / "src"
    src.mkdir()
    for k in (9, 1):  # a test and a validation trajectory, linked (never copied)
        (src / f"beam_{k}.pt").symlink_to(BEAM / f"beam_{k}.pt")
    out = import_tignn(src, tmp_path / "beam.h5")
    ds = Dataset(out)
    assert ds.names == ["beam_1", "beam_9"] and ds.layout.dim == 12 and ds.dt == pytest.approx(0.05)
    assert ds.split["test"][0] == "beam_9" and "beam_1" in ds.split["val"]
    assert (ds.mesh.node_type == 1).sum() == 36 and ds.mesh.edges().shape == (2, 3960)
    with torch.serialization.safe_globals([Data, GlobalStorage]):
        snaps = torch.load(BEAM / "beam_9.pt", weights_only=True)
    traj = ds.read("beam_9")
    assert traj.z.shape == (21, 756, 12)
    np.testing.assert_allclose(traj.z[0], snaps[0].x.double().numpy())
    np.testing.assert_allclose(traj.z[7], snaps[6].y.double().numpy())  # z[s+1] = y_s
    np.testing.assert_allclose(traj.force[7], snaps[6].f.double().numpy())  # force[s+1] = f_s
    assert np.all(traj.force[0] == 0) and traj.load_nodes.size == 6
