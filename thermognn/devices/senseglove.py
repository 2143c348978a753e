"""SenseGlove Nova through a C-callable subset of SGCore (ctypes).

The Nova has no motors: it renders contact with finger brakes (force-feedback levels 0..1 on
thumb, index, middle and ring) and an optional vibration motor. The serve loop's contact force
|f| [N] becomes the brake level of the rendering finger (``finger``, default index),
level = min(|f| / ``full_force``, 1). Levels are sent at most ``max_send_rate`` (60) times a
second and only when they change (quantised to SGCore's 0..100 percent).

Position: the wrist position the library reports (from the glove's tracker, millimetres) plus a
fixed ``fingertip_offset`` [m]; velocity by finite difference. Flexions 0..1 per finger.

C functions used (SGCore C wrapper subset)::

    int  SGCore_Init(void);                       1 ok
    int  SGCore_DeviceCount(void);
    int  SGCore_IsNova(int glove);
    int  SGCore_GetFlexions(int glove, float* out, int n);          0..1, thumb..pinky
    int  SGCore_GetWristPosition(int glove, float* out3);          [mm]
    int  SGCore_SendHaptics(int glove, const int* ffb, int n_ffb, int vibro);   0..100
    int  SGCore_StopHaptics(int glove);
    void SGCore_Dispose(void);

Library: ``library`` option, else ``$THERMOGNN_SGCORE``, else ``libSGCoreC.so``.
"""

from __future__ import annotations

import ctypes
import time

import numpy as np

from thermognn.core.errors import DeviceError

from ._ctypes_util import bind_signatures, load_vendor_library
from .base import Device, DeviceReading, DeviceSpecs, finite_difference_velocity

N_FFB = 4          # thumb, index, middle, ring
N_FINGERS = 5
INSTALL = "install SenseGlove's SGCore C library and run SenseCom with the Nova paired"


def bind_sgcore(lib: ctypes.CDLL) -> ctypes.CDLL:
    i, fp, ip = ctypes.c_int, ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_int)
    sig = {
        "SGCore_Init": (i, []), "SGCore_DeviceCount": (i, []), "SGCore_IsNova": (i, [i]),
        "SGCore_GetFlexions": (i, [i, fp, i]), "SGCore_GetWristPosition": (i, [i, fp]),
        "SGCore_SendHaptics": (i, [i, ip, i, i]), "SGCore_StopHaptics": (i, [i]), "SGCore_Dispose": (None, []),
    }
    return bind_signatures(lib, sig, "senseglove", INSTALL)


class SenseGloveNova(Device):
    """SenseGlove Nova force-feedback glove (finger brakes + vibration)."""

    def __init__(self, library: str | None = None, glove: int = 0, finger: int = 1, full_force: float = 2.0,
                 max_send_rate: float = 60.0, vibration: bool = False,
                 fingertip_offset: tuple[float, float, float] = (0.0, 0.0, 0.0), **options) -> None:
        super().__init__(**options)
        if not 0 <= int(finger) < N_FFB:
            raise DeviceError(f"senseglove: finger = {finger}, expected 0..{N_FFB - 1} (thumb, index, middle, ring)")
        self.library = library
        self.glove = int(glove)
        self.finger = int(finger)
        self.full_force = float(full_force)          # [N] force that fully locks the brake
        self.min_interval = 1.0 / float(max_send_rate)
        self.vibration = bool(vibration)
        self.offset = np.asarray(fingertip_offset, dtype=float)
        self.specs = DeviceSpecs("senseglove", 5.0, 5.0, 1000.0, (1.0, 1.0, 1.0), 60.0, 1000.0, 5.0, N_FFB)
        self.lib: ctypes.CDLL | None = None
        self._flex = (ctypes.c_float * N_FINGERS)()
        self._wrist = (ctypes.c_float * 3)()
        self._ffb = (ctypes.c_int * N_FFB)()
        self._levels = np.zeros(N_FFB)
        self.sent = np.full(N_FFB, -1, dtype=np.int64)   # last levels sent [%] (-1: nothing yet)
        self.sent_vibro = -1
        self.last_send = -1e9
        self.sends = 0
        self._x_prev = np.zeros(3)
        self._t_prev = 0.0
        self.reading.flexion = np.zeros(N_FINGERS)

    def _open(self) -> None:
        self.lib = bind_sgcore(load_vendor_library("THERMOGNN_SGCORE", ("SGCoreC", "libSGCoreC.so"), self.library,
                                                   "senseglove", INSTALL))
        lib = self.lib
        if lib.SGCore_Init() != 1:
            self.lib = None
            raise DeviceError(f"senseglove: SGCore_Init failed; {INSTALL}")
        n = lib.SGCore_DeviceCount()
        if n <= self.glove:
            lib.SGCore_Dispose()
            self.lib = None
            raise DeviceError(f"senseglove: glove {self.glove} not found ({n} connected); {INSTALL}")
        if not lib.SGCore_IsNova(self.glove):
            lib.SGCore_Dispose()
            self.lib = None
            raise DeviceError(f"senseglove: glove {self.glove} is not a Nova")
        self._read()
        self.reading.velocity[:] = 0.0

    def _close(self) -> None:
        if self.lib is not None:
            self.lib.SGCore_StopHaptics(self.glove)
            self.lib.SGCore_Dispose()
            self.lib = None

    def _read(self) -> DeviceReading:
        lib, r = self.lib, self.reading
        now = time.perf_counter()
        if lib.SGCore_GetWristPosition(self.glove, self._wrist) != 1 or \
                lib.SGCore_GetFlexions(self.glove, self._flex, N_FINGERS) != 1:
            raise DeviceError(f"senseglove: glove {self.glove} stopped answering (disconnected?)")
        self._x_prev[:] = r.position
        for k in range(3):
            r.position[k] = self._wrist[k] * 1e-3 + self.offset[k]      # mm -> m
        for k in range(N_FINGERS):
            r.flexion[k] = self._flex[k]
        finite_difference_velocity(r.position, self._x_prev, now - self._t_prev if self._t_prev else 0.0, r.velocity)
        r.t = self._t_prev = now
        return r

    def _set_force(self, force: np.ndarray) -> None:
        """Contact force [N] -> brake level of the rendering finger."""
        n = float(np.sqrt(force[0] * force[0] + force[1] * force[1] + force[2] * force[2]))
        self._levels[:] = 0.0
        self._levels[self.finger] = min(n / self.full_force, 1.0)
        self._set_finger_levels(self._levels)

    def _set_finger_levels(self, levels: np.ndarray, force: bool = False) -> None:
        """Send brake levels 0..1 [4] if they changed and 1/max_send_rate has passed (``force``: now)."""
        if self.lib is None:
            return
        pct = np.clip(np.rint(np.asarray(levels, dtype=float)[:N_FFB] * 100.0), 0, 100).astype(np.int64)
        vibro = int(pct.max()) if self.vibration else 0
        now = time.perf_counter()
        if not force and (np.array_equal(pct, self.sent) and vibro == self.sent_vibro):
            return
        if not force and now - self.last_send < self.min_interval:
            return                          # kept pending: sent on a later call once allowed
        for k in range(N_FFB):
            self._ffb[k] = int(pct[k])
        if self.lib.SGCore_SendHaptics(self.glove, self._ffb, N_FFB, vibro) != 1:
            raise DeviceError(f"senseglove: SGCore_SendHaptics failed for glove {self.glove}")
        self.sent[:] = pct
        self.sent_vibro = vibro
        self.last_send = now
        self.sends += 1
