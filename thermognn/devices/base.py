"""The one small interface every haptic device plugin implements.

SI units inside: positions [m], velocities [m/s], forces [N], stiffness [N/m], times [s].
Each plugin converts from its vendor's units and axes. A plugin is constructed with keyword
options (``serve.device_options`` plus a few the serve stage adds), then::

    dev.open(); specs = dev.specs
    r = dev.read()            # DeviceReading: timestamped position, velocity, buttons, flexion
    dev.set_force(f)          # f [3] N in the device frame (already clamped by serve's safety chain)
    dev.set_finger_levels(l)  # gloves: brake levels 0..1 per finger
    dev.health()              # None when fine, else a one-line fault
    dev.close()               # always commands zero force first

Devices with ``scene_frame = True`` (sim, replay) report positions already in the model's
frame; the others are mapped by the serve stage (workspace scale and offset).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from thermognn.core.errors import DeviceError


@dataclass(frozen=True)
class DeviceSpecs:
    """Hardware limits of a device (SI)."""

    name: str
    max_force: float                 # peak force [N]
    max_continuous_force: float      # force sustainable indefinitely [N]
    max_stiffness: float             # largest stable rendered stiffness [N/m]
    workspace: tuple[float, float, float]  # usable extent x y z [m]
    native_rate: float = 1000.0      # device servo rate [Hz]
    max_force_rate: float = 100.0    # force impulse limit [N/s] (change per tick = this / rate)
    max_damping: float = 5.0         # largest stable damping [N s/m]
    n_fingers: int = 0               # gloves: number of force-feedback fingers


@dataclass
class DeviceReading:
    """One timestamped sample of the device state (SI, device frame)."""

    t: float = 0.0                                                         # [s] monotonic
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))      # [3] m
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))      # [3] m/s
    buttons: int = 0                                                       # bit mask
    flexion: np.ndarray = field(default_factory=lambda: np.zeros(0))       # [fingers] 0..1


class Device:
    """Base class of the plugins. Subclasses override ``_open``, ``_close``, ``_read``, ``_set_force``."""

    #: positions already in the model frame (virtual devices)
    scene_frame: bool = False
    specs: DeviceSpecs = DeviceSpecs("device", 3.3, 0.88, 1000.0, (0.16, 0.12, 0.07))

    def __init__(self, **options) -> None:
        self.options = dict(options)
        self.is_open = False
        self.reading = DeviceReading()   # reused by read(): no allocation per tick
        self.done = False                # replay end etc.: the loop stops with reason "device finished"

    # -- lifecycle ---------------------------------------------------------------------------
    def open(self) -> DeviceSpecs:
        if not self.is_open:
            self._open()
            self.is_open = True
        return self.specs

    def close(self) -> None:
        """Command zero force (always), then release the device."""
        if not self.is_open:
            return
        try:
            self._set_force(np.zeros(3))
            if self.specs.n_fingers:
                self._set_finger_levels(np.zeros(self.specs.n_fingers), force=True)
        finally:
            self.is_open = False
            self._close()

    def __enter__(self) -> "Device":
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- scene ---------------------------------------------------------------------------
    def attach_scene(self, lo: np.ndarray, hi: np.ndarray, tool_radius: float) -> None:
        """Bounding box [m] of the model's reference geometry (virtual devices place their path)."""

    def attach_surface(self, points: np.ndarray, faces: np.ndarray | None = None) -> None:
        """Reference positions [M, 3] m of the body's surface nodes and its triangles [F, 3] (indices
        into ``points``; None: nodes only), after ``attach_scene`` (virtual devices aim their path
        at the surface itself, not at its bounding box)."""

    # -- I/O -----------------------------------------------------------------------------
    def read(self) -> DeviceReading:
        if not self.is_open:
            raise DeviceError(f"{self.specs.name}: read() before open()")
        return self._read()

    def set_force(self, force: np.ndarray) -> None:
        """Command ``force`` [3] N (device frame)."""
        if not self.is_open:
            raise DeviceError(f"{self.specs.name}: set_force() before open()")
        self._set_force(force)

    def set_finger_levels(self, levels: np.ndarray) -> None:
        """Gloves: brake levels 0..1 per finger (others ignore it)."""
        if self.specs.n_fingers:
            self._set_finger_levels(np.clip(np.asarray(levels, dtype=float), 0.0, 1.0))

    def health(self) -> str | None:
        """None when fine, else a one-line description of the fault."""
        return None

    # -- to override ---------------------------------------------------------------------------
    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read(self) -> DeviceReading:
        self.reading.t = time.perf_counter()
        return self.reading

    def _set_force(self, force: np.ndarray) -> None:
        pass

    def _set_finger_levels(self, levels: np.ndarray, force: bool = False) -> None:
        pass


def finite_difference_velocity(x_new: np.ndarray, x_old: np.ndarray, dt: float, out: np.ndarray) -> np.ndarray:
    """(x_new - x_old) / dt into ``out`` [3] m/s (0 when dt <= 0)."""
    if dt > 0:
        np.subtract(x_new, x_old, out=out)
        out /= dt
    else:
        out[:] = 0.0
    return out
