"""Replay a recorded tool trajectory: the session log of an earlier ``serve`` (CSV, or HDF5 with
datasets ``time`` and ``position``) or any CSV with columns ``t, x, y, z`` (seconds, metres,
model frame; extra columns ignored).

Options: ``file`` (required), ``loop`` (start over at the end; default False: the device then
reports ``done`` and the loop stops with reason "device finished"), ``speed`` (time scale).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from thermognn.core.errors import DeviceError

from .base import Device, DeviceReading, DeviceSpecs


def read_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Times [T] s (starting at 0, increasing) and positions [T, 3] m from a CSV with t,x,y,z columns."""
    path = Path(path)
    if not path.is_file():
        raise DeviceError(f"replay device: trajectory file '{path}' not found (set serve.replay_file)")
    if path.suffix in (".h5", ".hdf5"):                     # HDF5 session log: time [T], position [T, 3]
        import h5py
        with h5py.File(path, "r") as h5:
            if "time" not in h5 or "position" not in h5:
                raise DeviceError(f"replay device: '{path}' lacks datasets 'time' and 'position'")
            t, x = np.asarray(h5["time"], dtype=float), np.asarray(h5["position"], dtype=float).reshape(-1, 3)
        return _clean(path, t, x)
    with path.open() as fh:
        header = [h.strip() for h in fh.readline().strip().split(",")]
    try:
        cols = [header.index(c) for c in ("t", "x", "y", "z")]
    except ValueError:
        raise DeviceError(f"replay device: '{path}' header {header} lacks columns t,x,y,z") from None
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return _clean(path, data[:, cols[0]], data[:, cols[1:]])


def _clean(path: Path, t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Strictly increasing times from 0 [T] s and positions [T, 3] m; DeviceError if too short."""
    if len(t) < 2:
        raise DeviceError(f"replay device: '{path}' has {len(t)} samples, expected at least 2")
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, x = t[keep], x[keep]
    return t - t[0], np.ascontiguousarray(x)


class ReplayDevice(Device):
    """Plays back positions by time (linear interpolation); forces are accepted and dropped."""

    scene_frame = True

    def __init__(self, file: str | None = None, loop: bool = False, speed: float = 1.0, **options) -> None:
        super().__init__(**options)
        if file is None:
            raise DeviceError("replay device: no trajectory file, set serve.device_options.file=<serve_log.csv>")
        self.times, self.positions = read_trajectory(file)
        self.loop = bool(loop)
        self.speed = float(speed)
        self.specs = DeviceSpecs("replay", 3.3, 0.88, 1000.0, (0.16, 0.12, 0.07))
        self.last_force = np.zeros(3)
        self._t0 = 0.0
        self._k = 0

    def _open(self) -> None:
        self._t0 = time.perf_counter()
        self._k = 0

    def _read(self) -> DeviceReading:
        now = time.perf_counter()
        t = (now - self._t0) * self.speed
        T = self.times[-1]
        if t >= T:
            if self.loop:
                t = t % T
                self._k = 0
            else:
                t, self.done = T, True
        k, ts = self._k, self.times
        if ts[k] > t:
            k = 0
        while k + 2 < len(ts) and ts[k + 1] <= t:  # advance the cursor (monotone in time)
            k += 1
        self._k = k
        dt = ts[k + 1] - ts[k]
        w = min(max((t - ts[k]) / dt, 0.0), 1.0)
        r = self.reading
        r.t = now
        p0, p1 = self.positions[k], self.positions[k + 1]
        for i in range(3):
            r.position[i] = p0[i] + w * (p1[i] - p0[i])
            r.velocity[i] = 0.0 if self.done else (p1[i] - p0[i]) / dt * self.speed
        return r

    def _set_force(self, force: np.ndarray) -> None:
        self.last_force[:] = force
