"""Shared core: state layout from effects, HDF5 schema round trip, atomic and resumable writes."""

import json

import h5py
import numpy as np
import pytest

from thermognn.core.errors import ConfigError, DataError
from thermognn.core.io import atomic_path
from thermognn.core.schema import SCHEMA_VERSION, Dataset, DatasetWriter, Mesh, Trajectory
from thermognn.core.state import StateLayout, is_reversible, state_layout


def unit_cube_mesh() -> Mesh:
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], float)
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    return Mesh(nodes, tets, np.array([1, 0, 0, 2, 2], np.int8))


def make_traj(name: str, mesh: Mesh, layout: StateLayout, steps: int = 4) -> Trajectory:
    rng = np.random.default_rng(abs(hash(name)) % 2**32)
    n = mesh.nodes.shape[0]
    return Trajectory(name, np.arange(steps) * 0.01, rng.normal(size=(steps, n, layout.dim)),
                      rng.normal(size=(steps, n, 3)), np.array([3, 4]), np.array([0.5, 0.5, 1.0]))


def test_state_layout_follows_effects():
    assert state_layout(["elastic"]).names == ["q", "sigma"]
    assert state_layout(["elastic", "inertia"]).names == ["q", "v", "sigma"]
    lay = state_layout(["elastic", "viscous", "inertia"], n_prony=2, store_internal=True)
    assert lay.names == ["q", "v", "sigma", "xi1", "xi2"] and lay.dim == 24
    assert lay.slice("sigma") == slice(6, 12)
    assert StateLayout.from_json(lay.to_json()) == lay
    assert is_reversible(["elastic", "inertia"]) and not is_reversible(["elastic", "viscous"])
    with pytest.raises(ConfigError, match="unknown effect 'plastic'"):
        state_layout(["elastic", "plastic"])


def test_mesh_edges_and_boundary():
    mesh = unit_cube_mesh()
    edges = mesh.edges()
    assert edges.shape == (2, 2 * 9)  # 6 + 6 edges, 3 shared
    assert set(map(tuple, edges.T)) == set(map(tuple, edges[::-1].T))  # both directions
    assert mesh.boundary_faces().shape == (6, 3)  # 8 faces, the shared one is interior


def test_hdf5_round_trip(tmp_path):
    mesh, layout = unit_cube_mesh(), state_layout(["elastic", "inertia"])
    path = tmp_path / "d.h5"
    trajs = [make_traj(f"traj_{k}", mesh, layout) for k in (2, 10, 1)]
    with DatasetWriter(path, mesh, layout, 0.01, "scene:\n  name: t\n", "{}", "t", ["elastic", "inertia"]) as w:
        for t in trajs:
            w.write(t)
    with h5py.File(path) as f:
        assert f.attrs["schema_version"] == SCHEMA_VERSION
        for key in ("config", "versions", "state_layout", "dt", "effects", "scene"):
            assert key in f.attrs
    ds = Dataset(path)
    assert ds.names == ["traj_1", "traj_2", "traj_10"]  # natural order
    assert ds.layout == layout and ds.dt == 0.01 and ds.effects == ("elastic", "inertia")
    np.testing.assert_array_equal(ds.mesh.tets, mesh.tets)
    back = ds.read("traj_10")
    np.testing.assert_array_equal(back.z, trajs[1].z)
    np.testing.assert_array_equal(back.force, trajs[1].force)
    assert back.status == "ok"


def test_writer_refuses_nan_and_resumes(tmp_path):
    mesh, layout = unit_cube_mesh(), state_layout(["elastic"])
    path = tmp_path / "d.h5"
    bad = make_traj("a", mesh, layout)
    bad.z[1, 0, 0] = np.nan
    w = DatasetWriter(path, mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"])
    with pytest.raises(ValueError, match="non-finite"):
        w.write(bad)
    w.write(make_traj("b", mesh, layout))
    w.close(finalize=False)  # interrupted: nothing at `path`, the partial file holds 'b'
    assert not path.exists()
    with DatasetWriter(path, mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"]) as w2:
        assert w2.has("b") and not w2.has("a")
    assert Dataset(path).names == ["b"]
    # a partial file from a different config is discarded, not mixed in
    w3 = DatasetWriter(tmp_path / "e.h5", mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"])
    w3.write(make_traj("b", mesh, layout))
    w3.close(finalize=False)
    with DatasetWriter(tmp_path / "e.h5", mesh, layout, 0.1, "c: 2\n", "{}", "t", ["elastic"]) as w4:
        assert not w4.has("b")


def test_dataset_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match="missing.h5: dataset not found"):
        Dataset(tmp_path / "missing.h5")
    corrupt = tmp_path / "corrupt.h5"
    corrupt.write_bytes(b"this is not hdf5")
    with pytest.raises(DataError, match="corrupt.h5: not a readable HDF5 file"):
        Dataset(corrupt)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f.attrs["hello"] = 1
    with pytest.raises(DataError, match="foreign.h5: missing root attribute 'schema_version'"):
        Dataset(foreign)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert not target.exists() and list(tmp_path.iterdir()) == []
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole"


def test_split_attribute_round_trip(tmp_path):
    mesh, layout = unit_cube_mesh(), state_layout(["elastic"])
    with DatasetWriter(tmp_path / "s.h5", mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"]) as w:
        w.write(make_traj("a", mesh, layout))
        w.set_split({"train": ["a"], "val": [], "test": []})
    assert Dataset(tmp_path / "s.h5").split == {"train": ["a"], "val": [], "test": []}
    assert json.loads(json.dumps(Dataset(tmp_path / "s.h5").split))


def test_split_group_round_trip(tmp_path):
    """A trajectory's split group is stored when set and read back; files without one have none."""
    mesh, layout = unit_cube_mesh(), state_layout(["elastic"])
    grouped = make_traj("a", mesh, layout)
    grouped.split_group = "point_3"
    with DatasetWriter(tmp_path / "g.h5", mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"]) as w:
        w.write(grouped)
        w.write(make_traj("b", mesh, layout))
    ds = Dataset(tmp_path / "g.h5")
    assert ds.split_groups == {"a": "point_3"}
    assert ds.read("a").split_group == "point_3" and ds.read("b").split_group == ""


def test_fe_cost_round_trip(tmp_path):
    """``generate``'s record of what each FE solve cost is stored and read back; ``fe_cost`` sums
    it per step over the trajectories named, and is None where one of them has no record."""
    mesh, layout = unit_cube_mesh(), state_layout(["elastic"])
    timed = make_traj("a", mesh, layout)
    timed.fe_seconds, timed.fe_iterations, timed.fe_cuts = 0.5, 12, 1
    steps = len(timed.time) - 1
    with DatasetWriter(tmp_path / "c.h5", mesh, layout, 0.1, "c: 1\n", "{}", "t", ["elastic"]) as w:
        w.write(timed)
        w.write(make_traj("b", mesh, layout))
    ds = Dataset(tmp_path / "c.h5")
    back = ds.read("a")
    assert (back.fe_seconds, back.fe_iterations, back.fe_cuts) == (0.5, 12, 1)
    assert np.isnan(ds.read("b").fe_seconds)
    assert ds.fe_cost(["a"]) == {"ms_per_step": pytest.approx(500.0 / steps),
                                 "iterations_per_step": pytest.approx(12 / steps), "cuts": 1, "steps": steps}
    assert ds.fe_cost(["a", "b"]) is None
