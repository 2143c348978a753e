"""Device plugins: discovery, the sim and replay plugins, and the real ctypes bindings of the
hardware plugins run against small fake vendor libraries compiled from tests/csrc/."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from thermognn import devices
from thermognn.core.errors import DeviceError, ThermoGNNError
from thermognn.devices.base import Device

CSRC = Path(__file__).parent / "csrc"


def compile_fake(src: str, out_dir: Path) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc not available")
    lib = out_dir / (Path(src).stem + ".so")
    subprocess.run(["gcc", "-shared", "-fPIC", "-O1", "-o", str(lib), str(CSRC / src), "-lpthread", "-lm"],
                   check=True, capture_output=True)
    return lib


@pytest.fixture
def fake_libhd(tmp_path, monkeypatch):
    lib = compile_fake("fake_libhd.c", tmp_path)
    monkeypatch.setenv("THERMOGNN_LIBHD", str(lib))
    return lib


@pytest.fixture
def fake_sgcore(tmp_path, monkeypatch):
    lib = compile_fake("fake_sgcore.c", tmp_path)
    monkeypatch.setenv("THERMOGNN_SGCORE", str(lib))
    return lib


# -- discovery -------------------------------------------------------------------------------
def test_available_lists_entry_points():
    names = set(devices.available())
    assert {"sim", "replay", "geomagic", "senseglove"} <= names
    for name in ("sim", "replay", "geomagic", "senseglove"):
        assert issubclass(devices.load(name), Device)


def test_unknown_device_lists_available():
    with pytest.raises(DeviceError) as err:
        devices.load("phantom9000")
    msg = str(err.value)
    assert "\n" not in msg and "phantom9000" in msg and "sim" in msg and "geomagic" in msg
    assert isinstance(err.value, ThermoGNNError)




# -- sim ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", ["press", "palpate", "drag"])
def test_sim_paths_start_above_and_press_into_the_body(path):
    lo, hi, r = np.array([-0.02, -0.02, 0.0]), np.array([0.02, 0.02, 0.02]), 0.003
    dev = devices.load("sim")(path=path, period=2.0)
    dev.attach_scene(lo, hi, r)
    start, deepest = dev.position_at(0.0), dev.position_at(1.0)
    assert start[2] > hi[2] + r                      # out of contact at the start
    assert deepest[2] < hi[2] + r                    # the sphere penetrates the top face
    assert np.all(deepest[:2] > lo[:2]) and np.all(deepest[:2] < hi[:2])
    with dev:
        a = dev.read().position.copy()
        time.sleep(0.01)
        b = dev.read()
        assert b.t > 0 and np.all(np.isfinite(b.velocity))
        assert np.linalg.norm(b.position - a) < 0.01
        dev.set_force(np.array([0.0, 0.0, 1.0]))
    assert not dev.is_open and np.all(dev.last_force == 0)   # close() commands zero force


@pytest.mark.parametrize("path", ["press", "palpate", "drag"])
def test_sim_paths_press_the_surface_under_the_tool_not_the_bounding_box(path):
    """A body whose top is a ridge along y = 0 falling off to the sides (z = 0.04 − |y|, so the
    box's top face is 4 cm above most of it): given the surface (``attach_surface``, as serve
    does), every path starts ``clearance`` above the surface under the tool and reaches ``depth``
    into it, wherever the tool is."""
    g = np.linspace(-0.03, 0.03, 31)
    x, y = np.meshgrid(g, g, indexing="ij")
    surface = np.stack([x.ravel(), y.ravel(), 0.04 - np.abs(y.ravel())], 1)         # [M, 3] m
    lo, hi, r = np.array([-0.03, -0.03, 0.0]), np.array([0.03, 0.03, 0.04]), 0.003
    dev = devices.load("sim")(path=path, period=2.0)
    dev.attach_scene(lo, hi, r)
    dev.attach_surface(surface)
    for t in np.linspace(0.0, 18.0, 181):
        p = dev.position_at(float(t))
        under = 0.04 - abs(p[1])                                   # the surface's height under the tool
        assert abs(dev.surface_top(p[0], p[1]) - under) < 0.0025    # the grid and the reach: a few mm
        s = (under + r + dev.clearance - p[2]) / (dev.clearance + dev.depth)
        assert -1e-9 < s < 1.0 + 0.1                                # between clearance above and depth into it
    deepest = dev.position_at(1.0)
    assert deepest[2] - r < dev.surface_top(deepest[0], deepest[1]) - 0.9 * dev.depth


def _box_faces(nx: int, ny: int, z: float, offset: int) -> tuple[np.ndarray, np.ndarray]:
    """A face z = const of a 4 cm x 4 cm box: nx x ny nodes, two triangles per square (indices from
    ``offset``)."""
    x, y = np.meshgrid(np.linspace(0.0, 0.04, nx), np.linspace(0.0, 0.04, ny), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], 1)
    idx = np.arange(x.size).reshape(nx, ny) + offset
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return pts, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


@pytest.mark.parametrize("path", ["press", "palpate", "drag"])
def test_sim_paths_start_above_a_closed_body_with_a_coarse_top(path):
    """A closed box whose top face's nodes lie 8 mm apart and whose bottom face's 2 mm apart (as a
    gmsh block's can): near most of the top in plan, every surface node within reach is the
    bottom face's. Given the surface's triangles too (as serve gives them), every path starts
    above the top face and presses into it from there; given its nodes alone, the tool would
    start inside the body."""
    top, top_faces = _box_faces(6, 6, 0.02, 0)
    bottom, bottom_faces = _box_faces(21, 21, 0.0, len(top))
    bottom[:, :2] += 0.001                                   # (off the top's columns in plan)
    surface, faces = np.concatenate([top, bottom]), np.concatenate([top_faces, bottom_faces])   # [M, 3], [F, 3]
    r = 0.003
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.04, 0.04, 0.02])
    dev = devices.load("sim")(path=path, period=2.0)
    dev.attach_scene(lo, hi, r)
    dev.attach_surface(surface, faces)
    for t in np.linspace(0.0, 18.0, 181):
        p = dev.position_at(float(t))
        assert dev.surface_top(p[0], p[1]) == pytest.approx(0.02, abs=1e-12), (t, p)
        assert 0.02 + r - dev.depth - 1e-9 <= p[2] <= 0.02 + r + dev.clearance + 1e-9, (t, p)
    nodes_only = devices.load("sim")(path=path, period=2.0)
    nodes_only.attach_scene(lo, hi, r)
    nodes_only.attach_surface(surface)
    assert nodes_only.surface_top(0.02, 0.02) == 0.0                        # the bottom face's nodes


def test_sim_rejects_unknown_path():
    with pytest.raises(DeviceError, match="serve.path"):
        devices.load("sim")(path="zigzag")


# -- replay -----------------------------------------------------------------------------------
def test_replay_plays_back_a_session_log(tmp_path):
    log = tmp_path / "serve_log.csv"
    t = np.linspace(0.0, 0.05, 51)
    rows = np.column_stack([t, t, 2 * t, np.full_like(t, 0.01), np.zeros((51, 3)), np.arange(51), np.zeros(51)])
    np.savetxt(log, rows, delimiter=",", header="t,x,y,z,fx,fy,fz,physics_step,contact", comments="")
    dev = devices.load("replay")(file=str(log))
    with dev:
        time.sleep(0.02)
        r = dev.read()
        assert 0.0 < r.position[0] <= 0.05 and r.position[1] == pytest.approx(2 * r.position[0])
        assert r.velocity[0] == pytest.approx(1.0)
        time.sleep(0.05)
        r = dev.read()
        assert dev.done and r.position[0] == pytest.approx(0.05)


def test_replay_needs_a_file(tmp_path):
    with pytest.raises(DeviceError, match="replay"):
        devices.load("replay")()
    with pytest.raises(DeviceError, match="not found"):
        devices.load("replay")(file=str(tmp_path / "nope.csv"))


# -- geomagic (fake libHD) ------------------------------------------------------------------------
def test_geomagic_binds_libhd(fake_libhd):
    dev = devices.load("geomagic")()
    specs = dev.open()
    fake = ctypes.CDLL(str(fake_libhd))              # same handle as the plugin's: shared state
    fake.fake_hd_last_force.argtypes = [ctypes.POINTER(ctypes.c_double)]
    fake.fake_hd_max_force.restype = ctypes.c_double
    try:
        assert specs.max_force == pytest.approx(3.3) and specs.max_continuous_force == pytest.approx(0.88)
        assert specs.max_stiffness == pytest.approx(1260.0)           # N/mm -> N/m
        assert specs.workspace == pytest.approx((0.16, 0.12, 0.07))   # mm -> m
        for cap in (0x4000, 0x4001, 0x4002):                          # force output, clamping, ramping
            assert fake.fake_hd_enabled(cap) == 1
        assert fake.fake_hd_count(b"hdCheckCalibration") >= 1
        assert fake.fake_hd_count(b"hdScheduleAsynchronous") == 1 and fake.fake_hd_running() == 1
        time.sleep(0.03)
        r = dev.read()
        assert 0 < np.linalg.norm(r.position) < 0.05                 # mm -> m (20 mm circle)
        assert r.velocity == pytest.approx([0.001, -0.002, 0.003])
        assert r.buttons == 1
        dev.set_force(np.array([0.5, -0.25, 0.125]))
        time.sleep(0.02)
        out = (ctypes.c_double * 3)()
        fake.fake_hd_last_force(out)
        assert list(out) == pytest.approx([0.5, -0.25, 0.125])       # applied in the servo callback
        assert dev.servo_ticks > 5 and fake.fake_hd_frames() > 5
        assert dev.health() is None
    finally:
        dev.close()
    out = (ctypes.c_double * 3)()
    fake.fake_hd_last_force(out)
    assert list(out) == [0.0, 0.0, 0.0]                                # zero force on close
    assert fake.fake_hd_running() == 0 and fake.fake_hd_count(b"hdUnschedule") == 1
    assert fake.fake_hd_count(b"hdDisableDevice") == 1 and fake.fake_hd_enabled(0x4000) == 0


def test_geomagic_axes_to_model():
    R = devices.load("geomagic").axes_to_model
    assert R @ np.array([0.0, 1.0, 0.0]) == pytest.approx([0.0, 0.0, 1.0])   # Touch y up -> model z up
    assert R @ R.T == pytest.approx(np.eye(3))


def test_geomagic_calibration_update_and_manual(fake_libhd, monkeypatch):
    monkeypatch.setenv("FAKE_HD_CALIBRATION", "update")
    dev = devices.load("geomagic")()
    dev.open()
    dev.close()
    fake = ctypes.CDLL(str(fake_libhd))
    assert fake.fake_hd_count(b"hdUpdateCalibration") == 1
    monkeypatch.setenv("FAKE_HD_CALIBRATION", "manual")
    with pytest.raises(DeviceError, match="calibrat"):
        devices.load("geomagic")().open()
    assert fake.fake_hd_running() == 0


def test_geomagic_no_device(fake_libhd, monkeypatch):
    monkeypatch.setenv("FAKE_HD_FAIL_INIT", "1")
    with pytest.raises(DeviceError) as err:
        devices.load("geomagic")().open()
    assert "hdInitDevice" in str(err.value) and "no device" in str(err.value) and "\n" not in str(err.value)


def test_geomagic_missing_library(tmp_path, monkeypatch):
    monkeypatch.setenv("THERMOGNN_LIBHD", str(tmp_path / "libHD.so"))
    with pytest.raises(DeviceError) as err:
        devices.load("geomagic")().open()
    assert "OpenHaptics" in str(err.value) and "THERMOGNN_LIBHD" in str(err.value)


# -- senseglove (fake SGCore) -------------------------------------------------------------------
def test_senseglove_levels_rate_limited_and_on_change(fake_sgcore):
    dev = devices.load("senseglove")(full_force=2.0, max_send_rate=60.0)
    specs = dev.open()
    fake = ctypes.CDLL(str(fake_sgcore))
    assert specs.n_fingers == 4
    r = dev.read()
    assert r.position == pytest.approx([0.01, 0.02, 0.03])            # mm -> m
    assert r.flexion == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.5])
    dev.set_force(np.array([0.0, 0.0, 1.0]))                           # 1 N of 2 N -> index 50 %
    assert fake.fake_sg_sends() == 1 and fake.fake_sg_last_level(1) == 50 and fake.fake_sg_last_level(0) == 0
    for _ in range(50):                                                # unchanged: nothing sent
        dev.set_force(np.array([0.0, 0.0, 1.0]))
    assert fake.fake_sg_sends() == 1
    dev.set_force(np.array([0.0, 0.0, 1.5]))                           # changed but within 1/60 s
    assert fake.fake_sg_sends() == 1
    time.sleep(1.0 / 60.0 + 0.005)
    dev.set_force(np.array([0.0, 0.0, 1.5]))                           # pending change goes out
    assert fake.fake_sg_sends() == 2 and fake.fake_sg_last_level(1) == 75
    dev.set_force(np.array([0.0, 0.0, 9.0]))
    time.sleep(1.0 / 60.0 + 0.005)
    dev.set_force(np.array([0.0, 0.0, 9.0]))
    assert fake.fake_sg_last_level(1) == 100                           # clipped to 1
    t0 = time.perf_counter()                                           # hammering: <= 60 Hz
    k0 = fake.fake_sg_sends()
    i = 0
    while time.perf_counter() - t0 < 0.2:
        dev.set_force(np.array([0.0, 0.0, 0.5 + 0.5 * (i % 2)]))
        i += 1
    assert fake.fake_sg_sends() - k0 <= int(0.2 * 60) + 1
    dev.close()
    assert fake.fake_sg_stops() == 1 and fake.fake_sg_disposed() == 1 and fake.fake_sg_last_level(1) == 0


def test_senseglove_no_glove(fake_sgcore, monkeypatch):
    monkeypatch.setenv("FAKE_SG_DEVICES", "0")
    with pytest.raises(DeviceError, match="not found"):
        devices.load("senseglove")().open()


def test_senseglove_missing_library(tmp_path, monkeypatch):
    monkeypatch.setenv("THERMOGNN_SGCORE", str(tmp_path / "libSGCoreC.so"))
    with pytest.raises(DeviceError) as err:
        devices.load("senseglove")().open()
    assert "SGCore" in str(err.value) and "THERMOGNN_SGCORE" in str(err.value)


def test_geomagic_health_reports_a_stalled_servo_loop(fake_libhd):
    dev = devices.load("geomagic")()
    dev.open()
    try:
        time.sleep(0.06)
        assert dev.health() is None
        time.sleep(0.06)
        assert dev.health() is None
        ctypes.CDLL(str(fake_libhd)).hdStopScheduler()          # the HD scheduler dies
        time.sleep(0.06)
        dev.health()
        time.sleep(0.06)
        assert "servo loop stopped" in (dev.health() or "")
    finally:
        dev.close()


def test_replay_reads_an_hdf5_session_log(tmp_path):
    h5py = pytest.importorskip("h5py")
    with h5py.File(tmp_path / "log.h5", "w") as h5:
        h5["time"] = np.array([0.0, 0.01, 0.02])
        h5["position"] = np.array([[0.0, 0, 0.03], [0.001, 0, 0.03], [0.002, 0, 0.03]])
    from thermognn.devices.replay import read_trajectory
    t, x = read_trajectory(tmp_path / "log.h5")
    assert t[-1] == pytest.approx(0.02) and x.shape == (3, 3)
