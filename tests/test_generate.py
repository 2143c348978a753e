"""The generate stage end to end on a tiny block (real dolfinx solves)."""


import numpy as np
import pytest

from thermognn.core.config import load_config
from thermognn.core.errors import ConfigError, ThermoGNNError
from thermognn.core.schema import NODE_CLAMPED, NODE_SURFACE, Dataset

TINY = ["scene.loads.n_trajectories=3", "scene.time.steps=4", "scene.loads.ramp_steps=2",
        "scene.mesh.cell_size=0.01"]


def _cfg(tmp_path, *extra):
    return load_config([f"out={tmp_path}", *TINY, *extra])




def test_generate_tiny_block_writes_valid_dataset(tmp_path):
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate

    path = generate(_cfg(tmp_path))
    assert path == tmp_path / "dataset.h5" and path.exists()
    assert not path.with_name("dataset.h5.partial").exists()
    d = Dataset(path)
    assert d.names == ["traj_0", "traj_1", "traj_2"] and d.ok_names == d.names
    assert d.layout.names == ["q", "v", "sigma"] and d.dt == pytest.approx(0.01)
    assert d.effects == ("elastic", "inertia") and d.scene == "block"
    n = d.mesh.nodes.shape[0]
    assert set(np.unique(d.mesh.node_type)) == {0, NODE_CLAMPED, NODE_SURFACE}
    assert np.allclose(d.mesh.nodes[d.mesh.node_type == NODE_CLAMPED, 2], 0.0)
    assert np.allclose(d.mesh.nodes[d.mesh.node_type == NODE_SURFACE, 2], 0.02)
    assert d.mesh.tets.shape[1] == 4 and d.mesh.tets.max() == n - 1
    for name in d.names:
        t = d.read(name)
        assert t.z.shape == (5, n, 12) and t.force.shape == (5, n, 3)
        assert np.all(np.isfinite(t.z))
        assert np.allclose(t.z[0, :, :3], d.mesh.nodes) and np.allclose(t.z[0, :, 3:], 0.0)
        clamped = d.mesh.node_type == NODE_CLAMPED
        assert np.allclose(t.z[:, clamped, :3], d.mesh.nodes[clamped]) and np.allclose(t.z[:, clamped, 3:6], 0)
        total = t.force.sum(axis=1)  # (S, 3): smooth ramp 0, 0.5, 1, 1, 1 of 1 N pressing down
        assert np.allclose(total[:, 2], [0.0, -0.5, -1.0, -1.0, -1.0]) and np.allclose(total[:, :2], 0)
        assert set(np.flatnonzero(np.abs(t.force[-1]).sum(1))) == set(t.load_nodes.tolist())
        assert np.all(d.mesh.node_type[t.load_nodes] == NODE_SURFACE)
        moved = t.z[-1, t.load_nodes, 2] - d.mesh.nodes[t.load_nodes, 2]
        assert np.all(moved < 0)  # pressed in
        assert np.abs(t.z[-1, :, 6:]).max() > 100.0  # stresses of order 1 N / (1 cm)^2
    assert len({tuple(d.read(name).load_point) for name in d.names}) == 3   # each case its own point
    assert d.split_groups == {f"traj_{k}": f"point_{k}" for k in range(3)}  # train splits by point
    # the solid linearised at rest (/linear), the physics baseline evaluate reports
    lin = d.linear_solid()
    free = np.repeat(d.mesh.node_type != NODE_CLAMPED, 3)
    assert np.array_equal(lin.free, free) and lin.stiffness.shape == (free.sum(), free.sum())
    assert lin.stress.shape == (6 * n, free.sum()) and lin.integrator == "newmark"
    assert lin.rayleigh == (0.0, 0.002) and (lin.beta, lin.gamma) == (0.25, 0.5)
    K, M = lin.stiffness.toarray(), lin.mass.toarray()
    assert np.allclose(K, K.T, atol=1e-9 * abs(K).max()) and np.allclose(M, M.T)
    assert np.linalg.eigvalsh(K).min() > 0 and np.linalg.eigvalsh(M).min() > 0   # clamped: positive definite
    # it re-simulates the data as generate's report says (the same stepper, from the stored operators)
    from thermognn.generate.modes import linear_rollout_error

    report = d.time_resolution
    again = linear_rollout_error(lin, d.mesh.nodes, [d.read(name) for name in d.ok_names], d.layout, d.dt)
    assert again["u"] == pytest.approx(report["linear_rollout_error"]["u"], rel=1e-9)
    assert 0 < again["u"] < 0.5 and 0 < again["v"] < 1.0


def test_effects_decide_state_layout(tmp_path):
    """Quasi-static elastic scene: no velocity in z; viscous with store_internal: one xi per term."""
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate

    d = Dataset(generate(_cfg(tmp_path / "a", "scene.effects=[elastic]", "scene.loads.n_trajectories=1")))
    assert d.layout.names == ["q", "sigma"] and d.read("traj_0").z.shape[2] == 9
    assert d.time_convergence is None                   # quasi-static elastic: no time error to measure
    d = Dataset(generate(_cfg(tmp_path / "b", "scene.effects=[elastic,viscous]", "scene.store_internal=true",
                              "scene.material.prony=[{g: 0.3, tau: 0.05}]", "scene.loads.n_trajectories=1")))
    assert d.layout.names == ["q", "sigma", "xi1"]
    t = d.read("traj_0")
    assert d.status["traj_0"] == "ok" and np.abs(t.z[-1, :, 9:15]).max() > 0


def test_generate_resumes_and_skips_done_trajectories(tmp_path, monkeypatch):
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate, pipeline

    cfg = _cfg(tmp_path)
    real = pipeline.simulate
    calls = []

    def crash_after_first(solid, spec, layout, k, *a):
        if calls:
            raise KeyboardInterrupt
        calls.append(k)
        return real(solid, spec, layout, k, *a)

    monkeypatch.setattr(pipeline, "simulate", crash_after_first)
    with pytest.raises(KeyboardInterrupt):
        generate(cfg)
    assert (tmp_path / "dataset.h5.partial").exists() and not (tmp_path / "dataset.h5").exists()

    done = []
    monkeypatch.setattr(pipeline, "simulate", lambda solid, spec, layout, k, *a: done.append(k) or
                        real(solid, spec, layout, k, *a))
    generate(_cfg(tmp_path, "train.epochs=7"))      # keys outside the scene do not restart it
    assert done == [1, 2]
    d = Dataset(tmp_path / "dataset.h5")
    assert d.ok_names == ["traj_0", "traj_1", "traj_2"]


def test_generate_grows_a_finished_dataset(tmp_path, monkeypatch):
    """More load cases for the same scene and ``out``: only the new ones are solved, the old
    ones are kept as they were; another scene starts afresh."""
    pytest.importorskip("dolfinx")
    import h5py

    from thermognn.generate import generate, pipeline

    path = generate(_cfg(tmp_path, "scene.loads.n_trajectories=2"))
    before = Dataset(path).read("traj_1").z
    real = pipeline.simulate
    done = []
    monkeypatch.setattr(pipeline, "simulate", lambda solid, spec, layout, k, *a: done.append(k) or
                        real(solid, spec, layout, k, *a))
    assert generate(_cfg(tmp_path, "scene.loads.n_trajectories=3")) == path
    assert done == [2] and not path.with_name("dataset.h5.partial").exists()
    d = Dataset(path)
    assert d.ok_names == ["traj_0", "traj_1", "traj_2"] and np.array_equal(d.read("traj_1").z, before)
    assert d.linear_solid() is not None
    with h5py.File(path, "r") as f:
        assert "n_trajectories: 3" in f.attrs["config"]        # the file says what it holds
    done.clear()
    generate(_cfg(tmp_path, "scene.loads.n_trajectories=4", "scene.loads.magnitude=0.5"))
    assert done == [0, 1, 2, 3]


def test_generate_restarts_a_partial_file_with_other_load_points(tmp_path, monkeypatch):
    """A partial file from another load draw (an older version) is not mixed into the new one."""
    pytest.importorskip("dolfinx")
    import h5py

    from thermognn.generate import generate, pipeline

    cfg = _cfg(tmp_path)
    real = pipeline.simulate

    def crash_after_first(solid, spec, layout, k, *a):
        if k > 0:
            raise KeyboardInterrupt
        return real(solid, spec, layout, k, *a)

    monkeypatch.setattr(pipeline, "simulate", crash_after_first)
    with pytest.raises(KeyboardInterrupt):
        generate(cfg)
    with h5py.File(tmp_path / "dataset.h5.partial", "a") as f:
        f["trajectories/traj_0"].attrs["load_point"] += 1e-3
    done = []
    monkeypatch.setattr(pipeline, "simulate", lambda solid, spec, layout, k, *a: done.append(k) or
                        real(solid, spec, layout, k, *a))
    generate(cfg)
    assert done == [0, 1, 2]


def test_load_cases_press_distinct_points():
    """Case k presses the k-th loadable node of one seeded order: n cases, n distinct points."""
    from thermognn.generate.scene import LoadSpec, load_case

    rng = np.random.default_rng(1)
    nodes = rng.random((30, 3))
    node_type = np.zeros(30, np.int8)
    node_type[:12] = NODE_SURFACE
    normals = np.tile([0.0, 0.0, 1.0], (30, 1))
    loads = LoadSpec(n_trajectories=12, magnitude=2.0, radius=0.0, ramp_steps=1, ramp_shape="linear", seed=3)
    cases = [load_case(k, nodes, node_type, normals, loads) for k in range(12)]
    centres = [int(c[1][0]) for c in cases]
    assert sorted(centres) == list(range(12))                       # every loadable node once
    assert all(np.allclose(c[0], nodes[c[1][0]]) for c in cases)
    assert all(np.allclose(c[2].sum(0), [0, 0, -2.0]) for c in cases)  # the whole force, inwards
    assert [int(load_case(k, nodes, node_type, normals, loads)[1][0]) for k in range(12)] == centres  # seeded
    loads.n_trajectories = 13
    with pytest.raises(ConfigError, match=r"scene.loads.n_trajectories = 13: at most 12"):
        load_case(0, nodes, node_type, normals, loads)
    # several magnitudes: the first round is the cases above, the next presses the same points harder
    loads.magnitude, loads.n_trajectories = (2.0, 3.0), 24
    again = [load_case(k, nodes, node_type, normals, loads) for k in range(24)]
    assert [int(c[1][0]) for c in again] == centres + centres
    assert all(np.allclose(a[2], b[2]) for a, b in zip(again, cases))
    assert all(np.allclose(c[2].sum(0), [0, 0, -3.0]) for c in again[12:])
    loads.n_trajectories = 25
    with pytest.raises(ConfigError, match=r"scene.loads.n_trajectories = 25: at most 24 \(12 loadable"):
        load_case(0, nodes, node_type, normals, loads)


def test_load_points_between_the_nodes():
    """scene.loads.between_nodes: after the node cases (unchanged), points drawn on the loadable
    triangles, each pressed at every magnitude; every case loads its own set of nodes, and each
    point is in the split group of its nearest node."""
    from thermognn.generate.scene import LoadSpec, between_node_points, load_case

    g = np.linspace(0.0, 0.04, 5)                                   # a 5 x 5 loadable grid at z = 0.02
    x, y = np.meshgrid(g, g, indexing="ij")
    top = np.column_stack([x.ravel(), y.ravel(), np.full(25, 0.02)])
    nodes = np.vstack([top, top - [0, 0, 0.02]])                    # and 25 nodes below it
    node_type = np.r_[np.full(25, NODE_SURFACE), np.zeros(25)].astype(np.int8)
    normals = np.tile([0.0, 0.0, 1.0], (50, 1))
    quads = [(5 * i + j, 5 * (i + 1) + j, 5 * (i + 1) + j + 1, 5 * i + j + 1) for i in range(4) for j in range(4)]
    faces = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    nodal = LoadSpec(n_trajectories=50, magnitude=(1.0, 1.3), radius=0.012, ramp_steps=1, ramp_shape="linear", seed=2)
    loads = LoadSpec(n_trajectories=66, magnitude=(1.0, 1.3), radius=0.012, ramp_steps=1, ramp_shape="linear", seed=2,
                     between_nodes=8)
    points = between_node_points(nodes, node_type, faces, loads)
    cases = [load_case(k, nodes, node_type, normals, loads, points) for k in range(66)]
    for k in range(50):                                             # the node cases as without the points
        before = load_case(k, nodes, node_type, normals, nodal)
        assert np.array_equal(cases[k].force, before.force) and np.array_equal(cases[k].point, before.point)
        assert cases[k].point_index == k % 25
    assert points.shape == (8, 3) and np.allclose(points[:, 2], 0.02) and points[:, :2].min() >= 0
    assert points[:, :2].max() <= 0.04 and np.min(np.linalg.norm(points[:, None] - top[None], axis=2)) > 0
    order = np.random.default_rng(2).permutation(25)
    for r, magnitude in enumerate((1.0, 1.3)):
        for j in range(8):
            case = cases[50 + 8 * r + j]
            assert np.array_equal(case.point, points[j]) and np.allclose(case.force.sum(0), [0, 0, -magnitude])
            nearest = int(np.argmin(np.linalg.norm(top - points[j], axis=1)))
            assert order[case.point_index] == nearest and nearest in case.load_nodes
            within = np.flatnonzero(np.linalg.norm(nodes - points[j], axis=1) <= 0.012)    # top nodes only
            assert np.array_equal(case.load_nodes, np.union1d(within, [nearest]))
    assert len({tuple(c.load_nodes) for c in cases[:25] + cases[50:58]}) == 33           # every case distinct
    assert np.array_equal(between_node_points(nodes, node_type, faces, loads), points)   # seeded
    with pytest.raises(ConfigError, match=r"n_trajectories = 67: at most 66 \(25 loadable nodes .* and 8 points"):
        load_case(0, nodes, node_type, normals, LoadSpec(**{**loads.__dict__, "n_trajectories": 67}), points)
    with pytest.raises(ConfigError, match=r"^scene.loads.between_nodes = 500: only \d+ load points"):
        between_node_points(nodes, node_type, faces, LoadSpec(**{**loads.__dict__, "between_nodes": 500}))


def test_generate_presses_between_the_nodes(tmp_path):
    """A real generate with two points between the nodes after the node cases: their trajectories
    press there, in the split group of the nearest loadable node."""
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate
    from thermognn.generate.scene import node_types, scene_from_config

    spec = scene_from_config(_cfg(tmp_path).scene)
    P = int((node_types(spec.points, spec.tets, spec.mesh_cfg) == NODE_SURFACE).sum())
    d = Dataset(generate(_cfg(tmp_path, f"scene.loads.n_trajectories={P + 2}", "scene.loads.between_nodes=2",
                              "scene.time.steps=2")))
    assert d.ok_names == [f"traj_{k}" for k in range(P + 2)]
    top = d.mesh.nodes[d.mesh.node_type == NODE_SURFACE]
    group_of = {tuple(d.load_points[f"traj_{k}"]): d.split_groups[f"traj_{k}"] for k in range(P)}
    for name in (f"traj_{P}", f"traj_{P + 1}"):
        point = d.load_points[name]
        assert point[2] == pytest.approx(0.02) and np.min(np.linalg.norm(top - point, axis=1)) > 1e-6
        nearest = top[np.argmin(np.linalg.norm(top - point, axis=1))]
        assert d.split_groups[name] == group_of[tuple(nearest)]
        assert np.allclose(d.read(name).force[-1].sum(0), [0, 0, -1.0])


def test_generate_substeps_solve_finer_in_time_and_measure_the_datas_time_error(tmp_path):
    """``scene.time.substeps`` k: each stored step solved as k FE steps of dt/k, the loads linear
    between the stored ones. On the tiny block under a linear ramp (whose loads are linear between
    the stored steps anyway) the data at dt with 2 sub-steps are the FE at dt/2 with twice the
    steps, every other state. ``scene.time.convergence_check``: the report's error of data at dt
    is theirs against that finer solve, and sub-steps shrink it (on the block at dt 2 ms, halved
    in u and σ, v to a quarter: its stiff modes, damped by βK, the trapezoid does not damp)."""
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate

    one = ["scene.loads.n_trajectories=1", "scene.loads.ramp_shape=linear", "scene.time.dt=0.002",
           "scene.time.steps=8", "scene.loads.ramp_steps=4"]
    coarse = Dataset(generate(_cfg(tmp_path / "c", *one)))
    sub = Dataset(generate(_cfg(tmp_path / "s", *one, "scene.time.substeps=2")))
    half = Dataset(generate(_cfg(tmp_path / "h", *one, "scene.time.dt=0.001", "scene.time.steps=16",
                                 "scene.loads.ramp_steps=8", "scene.time.convergence_check=0")))
    zc, zs, zh = (d.read("traj_0").z for d in (coarse, sub, half))
    assert (coarse.substeps, sub.substeps, half.substeps) == (1, 2, 1) and zs.shape == zc.shape
    assert np.allclose(zs, zh[::2], rtol=0, atol=1e-9 * np.abs(zh).max(axis=(0, 1)))
    assert np.array_equal(sub.read("traj_0").force, coarse.read("traj_0").force)
    assert half.time_convergence is None
    X = coarse.mesh.nodes
    report = coarse.time_convergence
    assert (report["substeps"], report["fine_substeps"], [c["name"] for c in report["cases"]]) == (1, 2, ["traj_0"])
    fine = zh[::2]
    for g, sl, base in (("u", slice(0, 3), X), ("v", slice(3, 6), 0.0), ("sigma", slice(6, 12), 0.0)):
        want = np.linalg.norm(zc[..., sl] - fine[..., sl]) / np.linalg.norm(fine[..., sl] - base)
        assert report[g] == pytest.approx(want, rel=1e-6) and 0 < want < 1
        assert sub.time_convergence[g] < 0.6 * report[g]          # (measured: 0.50, 0.26, 0.49)
    assert sub.time_convergence["fine_substeps"] == 4
    from thermognn.generate.pipeline import TIME_HINT, describe_convergence

    for d, k in ((coarse, 1), (sub, 2)):
        lines = describe_convergence(d.time_convergence, "block")
        assert lines[0].startswith(f"time convergence (block): the data (dt 0.002 s, {k} FE step{'s' if k > 1 else ''} "
                                   f"a step) are u ") and f"from the FE at {2 * k} sub-steps a step (traj_0: FE" in lines[0]
        above = max(d.time_convergence["u"], d.time_convergence["v"]) > TIME_HINT
        assert (len(lines) == 2 and f"scene.time.substeps={2 * k}" in lines[1]) == above


@pytest.mark.parametrize("value", [[], "hard", [1.0, float("nan")], [[1.0]]])
def test_bad_load_magnitude_names_the_key(value):
    from thermognn.generate.scene import _magnitudes

    with pytest.raises(ConfigError, match=r"^scene.loads.magnitude = .*: expected a force \[N\] or a list"):
        _magnitudes(value)
    assert _magnitudes(2) == 2.0 and _magnitudes([1, 1.3]) == (1.0, 1.3)


def test_generate_failed_trajectory_is_recorded_without_nan(tmp_path):
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate

    path = generate(_cfg(tmp_path, "scene.loads.magnitude=1e4", "scene.loads.n_trajectories=1"))
    d = Dataset(path)
    assert d.status == {"traj_0": "failed"}
    t = d.read("traj_0")
    assert "floor" in t.reason and np.all(np.isfinite(t.z)) and len(t.time) < 5
    assert t.z.shape[0] == t.force.shape[0] == len(t.time)


@pytest.mark.parametrize("override, needle", [
    ("scene.material.law=mooney", "scene.material.law"),
    ("scene.mesh.geometry=meshes/nope.geo", "nope.geo"),
    ("scene.time.integrator=leapfrog", "scene.time.integrator"),
    ("scene.effects=[elastic,plastic]", "plastic"),
    ("scene.time.dt=-1", "scene.time.dt"),
    ("scene.mesh.clamp=left", "scene.mesh.clamp"),
    ("scene.loads.ramp_shape=step", "scene.loads.ramp_shape"),
    ("scene.loads.n_trajectories=1000", "scene.loads.n_trajectories"),
    ("scene.loads.magnitude=[]", "scene.loads.magnitude"),
    ("scene.loads.between_nodes=-1", "scene.loads.between_nodes"),
    ("scene.loads.between_nodes=1.5", "scene.loads.between_nodes"),
    ("scene.time.substeps=0", "scene.time.substeps"),
    ("scene.time.substeps=1.5", "scene.time.substeps"),
    ("scene.time.convergence_check=-1", "scene.time.convergence_check"),
])
def test_bad_scene_config_gives_one_line_error(tmp_path, override, needle):
    pytest.importorskip("dolfinx")
    from thermognn.generate import generate

    with pytest.raises(ThermoGNNError) as e:
        generate(_cfg(tmp_path, override))
    msg = str(e.value)
    assert "\n" not in msg and needle in msg
    assert not (tmp_path / "dataset.h5").exists()


def test_unknown_scene_key_is_config_error(tmp_path):
    with pytest.raises(ConfigError):
        _cfg(tmp_path, "scene.no_such_key=1")


@pytest.mark.parametrize("scene, extra", [
    ("shell", []),
    ("liver", ["scene.store_internal=true"]),
    ("bunny", []),
])
def test_other_scenes_generate(tmp_path, scene, extra):
    """Shell (own geometry), liver (Ogden + 2 Prony terms, meshio .msh) and bunny (neo-Hookean +
    Prony, .vtu): one short trajectory each; the shared meshes are optional (skipped if absent)."""
    pytest.importorskip("dolfinx")
    from thermognn.core.config import PROJECT_ROOT
    from thermognn.generate import generate

    if scene in ("liver", "bunny") and not (PROJECT_ROOT.parent / "shared" / "meshes").is_dir():
        pytest.skip("../shared/meshes not available")
    cfg = load_config([f"out={tmp_path}", f"scene={scene}", "scene.loads.n_trajectories=1",
                       "scene.time.steps=2", *extra])
    d = Dataset(generate(cfg))
    t = d.read("traj_0")
    assert d.status["traj_0"] == "ok" and np.all(np.isfinite(t.z)) and t.z.shape[0] == 3
    if scene == "liver":
        assert d.layout.names == ["q", "v", "sigma", "xi1", "xi2"]
        assert np.abs(t.z[-1, :, d.layout.slice("xi2")]).max() > 0
    assert np.all(d.mesh.node_type[t.load_nodes] == NODE_SURFACE)
