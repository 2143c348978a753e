"""Geomagic Touch / Phantom Omni through the OpenHaptics HD API (libHD) with ctypes.

The device's own 1 kHz servo loop is an asynchronous scheduler callback
(``hdScheduleAsynchronous``) that, inside ``hdBeginFrame``/``hdEndFrame``, reads position,
velocity and buttons and applies the latest commanded force. The serve loop exchanges data
with it through GIL-atomic Python attributes. Hardware safety is on: ``HD_FORCE_OUTPUT``,
``HD_MAX_FORCE_CLAMPING``, ``HD_FORCE_RAMPING``; calibration is checked (``hdCheckCalibration``)
and updated when the device can do it itself.

Units: libHD uses millimetres (positions), mm/s, N, N/mm (stiffness); converted to SI here.
Axes: the Touch frame has y up and z towards the user; ``axes_to_model`` maps it to the
model frame (z up): x_m = x_d, y_m = -z_d, z_m = y_d.

Library: ``library`` option, else ``$THERMOGNN_LIBHD``, else ``libHD.so`` on the loader path.
"""

from __future__ import annotations

import ctypes
import time

import numpy as np

from thermognn.core.errors import DeviceError

from ._ctypes_util import bind_signatures, load_vendor_library
from .base import Device, DeviceReading, DeviceSpecs

# hdDefines.h (OpenHaptics 3.x)
HD_SUCCESS = 0x0000
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_VELOCITY = 0x2051
HD_DEVICE_MODEL_TYPE = 0x2501
HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551
HD_CALIBRATION_STYLE = 0x2555
HD_NOMINAL_MAX_STIFFNESS = 0x2602
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_NOMINAL_MAX_DAMPING = 0x2609
HD_SOFTWARE_FORCE_IMPULSE_LIMIT = 0x2607
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_MAX_FORCE_CLAMPING = 0x4001
HD_FORCE_RAMPING = 0x4002
HD_CALIBRATION_OK = 0x5000
HD_CALIBRATION_NEEDS_UPDATE = 0x5001
HD_CALIBRATION_NEEDS_MANUAL_INPUT = 0x5002
HD_CALIBRATION_ENCODER_RESET = 1 << 0
HD_CALIBRATION_AUTO = 1 << 1
HD_CALIBRATION_INKWELL = 1 << 2
HD_INVALID_HANDLE = 0xFFFFFFFF
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1
HD_DEFAULT_SCHEDULER_PRIORITY = (0xFFFF + 0) // 2

INSTALL = ("install OpenHaptics (libHD) and the Geomagic Touch Device Driver, connect and pair the device "
           "(Touch_Setup)")


class HDErrorInfo(ctypes.Structure):
    _fields_ = [("errorCode", ctypes.c_uint), ("internalErrorCode", ctypes.c_int), ("hHD", ctypes.c_uint)]


HDSchedulerCallback = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)


def bind_libhd(lib: ctypes.CDLL) -> ctypes.CDLL:
    """Declare the signatures of the libHD functions this plugin calls."""
    u, i, d, v = ctypes.c_uint, ctypes.c_int, ctypes.POINTER(ctypes.c_double), ctypes.c_void_p
    sig = {
        "hdInitDevice": (u, [ctypes.c_char_p]), "hdDisableDevice": (None, [u]), "hdMakeCurrentDevice": (None, [u]),
        "hdBeginFrame": (None, [u]), "hdEndFrame": (None, [u]),
        "hdGetDoublev": (None, [u, d]), "hdSetDoublev": (None, [u, d]),
        "hdGetIntegerv": (None, [u, ctypes.POINTER(i)]), "hdGetString": (ctypes.c_char_p, [u]),
        "hdEnable": (None, [u]), "hdDisable": (None, [u]), "hdIsEnabled": (ctypes.c_ubyte, [u]),
        "hdGetError": (HDErrorInfo, []), "hdGetErrorString": (ctypes.c_char_p, [u]),
        "hdCheckCalibration": (u, []), "hdUpdateCalibration": (None, [u]),
        "hdStartScheduler": (None, []), "hdStopScheduler": (None, []),
        "hdScheduleAsynchronous": (ctypes.c_ulong, [HDSchedulerCallback, v, ctypes.c_ushort]),
        "hdUnschedule": (None, [ctypes.c_ulong]),
    }
    return bind_signatures(lib, sig, "geomagic", INSTALL)


class GeomagicTouch(Device):
    """Geomagic Touch (Phantom Omni) via OpenHaptics' HD API."""

    #: model = R @ device (Touch: y up, z to the user -> model z up)
    axes_to_model = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

    def __init__(self, library: str | None = None, device_name: str | None = None, **options) -> None:
        super().__init__(**options)
        self.library = library
        self.device_name = device_name
        self.specs = DeviceSpecs("geomagic", 3.3, 0.88, 1260.0, (0.16, 0.12, 0.07), 1000.0, 100.0, 2.0)
        self.lib: ctypes.CDLL | None = None
        self.handle = HD_INVALID_HANDLE
        self._sched = None
        self._callback = HDSchedulerCallback(self._servo)      # kept alive as long as self
        self._pos = (ctypes.c_double * 3)()                     # [mm], written by the servo thread
        self._vel = (ctypes.c_double * 3)()                     # [mm/s]
        self._buttons = ctypes.c_int(0)
        self._force_out = (ctypes.c_double * 3)()               # [N] buffer handed to hdSetDoublev
        self._force_cmd = (0.0, 0.0, 0.0)                       # latest command (tuple: GIL-atomic swap)
        self._stopping = False
        self.servo_ticks = 0
        self.fault: str | None = None
        self._health_t = 0.0
        self._health_ticks = 0

    # -- helpers -------------------------------------------------------------------------------
    def _error(self) -> str | None:
        info = self.lib.hdGetError()
        if info.errorCode == HD_SUCCESS:
            return None
        text = self.lib.hdGetErrorString(info.errorCode)
        return f"{text.decode() if text else 'HD error'} (0x{info.errorCode:04x}, internal {info.internalErrorCode})"

    def _get_doubles(self, pname: int, n: int) -> np.ndarray:
        buf = (ctypes.c_double * n)()
        self.lib.hdGetDoublev(pname, buf)
        return np.frombuffer(buf, dtype=np.float64).copy()

    # -- lifecycle -----------------------------------------------------------------------------
    def _open(self) -> None:
        self.lib = bind_libhd(load_vendor_library("THERMOGNN_LIBHD", ("HD", "libHD.so"), self.library,
                                                  "geomagic", INSTALL))
        lib = self.lib
        name = self.device_name.encode() if self.device_name else None      # HD_DEFAULT_DEVICE
        self.handle = lib.hdInitDevice(name)
        err = self._error()
        if err or self.handle == HD_INVALID_HANDLE:
            raise DeviceError(f"geomagic: hdInitDevice failed: {err or 'invalid handle'}; is the Touch connected "
                              f"and paired? ({INSTALL})")
        lib.hdMakeCurrentDevice(self.handle)
        try:
            self._read_specs()
            self._check_calibration()
            for cap in (HD_FORCE_OUTPUT, HD_MAX_FORCE_CLAMPING, HD_FORCE_RAMPING):
                lib.hdEnable(cap)
            self._sched = lib.hdScheduleAsynchronous(self._callback, None, HD_DEFAULT_SCHEDULER_PRIORITY)
            lib.hdStartScheduler()
            err = self._error()
            if err:
                raise DeviceError(f"geomagic: could not start the servo loop: {err}")
        except BaseException:
            self._shutdown()
            raise

    def _read_specs(self) -> None:
        """Device limits from libHD (N, N/mm, N s/mm, mm), in SI."""
        max_force = float(self._get_doubles(HD_NOMINAL_MAX_FORCE, 1)[0])
        cont = float(self._get_doubles(HD_NOMINAL_MAX_CONTINUOUS_FORCE, 1)[0])
        stiff = float(self._get_doubles(HD_NOMINAL_MAX_STIFFNESS, 1)[0]) * 1e3      # N/mm -> N/m
        damp = float(self._get_doubles(HD_NOMINAL_MAX_DAMPING, 1)[0]) * 1e3        # N s/mm -> N s/m
        ws = self._get_doubles(HD_USABLE_WORKSPACE_DIMENSIONS, 6) * 1e-3            # mm -> m (min xyz, max xyz)
        d = self.specs
        self.specs = DeviceSpecs(
            "geomagic",
            max_force if max_force > 0 else d.max_force,
            cont if cont > 0 else d.max_continuous_force,
            stiff if stiff > 0 else d.max_stiffness,
            tuple(float(e) for e in (ws[3:] - ws[:3])) if np.all(ws[3:] > ws[:3]) else d.workspace,
            1000.0, d.max_force_rate, damp if damp > 0 else d.max_damping)

    def _check_calibration(self) -> None:
        lib = self.lib
        state = lib.hdCheckCalibration()
        if state == HD_CALIBRATION_OK:
            return
        style = ctypes.c_int(0)
        lib.hdGetIntegerv(HD_CALIBRATION_STYLE, ctypes.byref(style))
        if state == HD_CALIBRATION_NEEDS_UPDATE:
            for s in (HD_CALIBRATION_ENCODER_RESET, HD_CALIBRATION_AUTO, HD_CALIBRATION_INKWELL):
                if style.value & s:
                    lib.hdUpdateCalibration(s)
                    break
            if lib.hdCheckCalibration() == HD_CALIBRATION_OK:
                return
        hint = "put the stylus in the inkwell" if style.value & HD_CALIBRATION_INKWELL else "run Touch_Diagnostic"
        raise DeviceError(f"geomagic: device not calibrated (hdCheckCalibration = 0x{state:04x}); {hint} and retry")

    def _servo(self, _user_data) -> int:
        """Servo callback (HD scheduler thread, 1 kHz): read state, apply the latest force."""
        try:
            return self._servo_frame()
        except BaseException as exc:  # noqa: BLE001 - never let an exception cross into C
            self.fault = f"servo callback failed: {type(exc).__name__}: {exc}"
            return HD_CALLBACK_DONE

    def _servo_frame(self) -> int:
        lib = self.lib
        if lib is None:
            return HD_CALLBACK_DONE
        lib.hdBeginFrame(self.handle)
        lib.hdGetDoublev(HD_CURRENT_POSITION, self._pos)
        lib.hdGetDoublev(HD_CURRENT_VELOCITY, self._vel)
        lib.hdGetIntegerv(HD_CURRENT_BUTTONS, ctypes.byref(self._buttons))
        fx, fy, fz = (0.0, 0.0, 0.0) if self._stopping else self._force_cmd
        self._force_out[0], self._force_out[1], self._force_out[2] = fx, fy, fz
        lib.hdSetDoublev(HD_CURRENT_FORCE, self._force_out)
        lib.hdEndFrame(self.handle)
        err = self._error()
        if err:
            self.fault = err
            return HD_CALLBACK_DONE
        self.servo_ticks += 1
        return HD_CALLBACK_CONTINUE

    def _close(self) -> None:
        self._shutdown()

    def _shutdown(self) -> None:
        lib = self.lib
        if lib is None:
            return
        self._force_cmd = (0.0, 0.0, 0.0)
        self._stopping = True
        t_end = time.perf_counter() + 0.01
        ticks = self.servo_ticks
        while self._sched is not None and self.servo_ticks < ticks + 2 and time.perf_counter() < t_end:
            time.sleep(0.001)                      # let the servo loop apply zero force
        lib.hdStopScheduler()
        if self._sched is not None:
            lib.hdUnschedule(self._sched)
            self._sched = None
        if self.handle != HD_INVALID_HANDLE:
            lib.hdDisable(HD_FORCE_OUTPUT)
            lib.hdDisableDevice(self.handle)
            self.handle = HD_INVALID_HANDLE
        self.lib = None

    # -- I/O -------------------------------------------------------------------------------------
    def _read(self) -> DeviceReading:
        r = self.reading
        r.t = time.perf_counter()
        p, v = self._pos, self._vel
        for k in range(3):
            r.position[k] = p[k] * 1e-3          # mm -> m
            r.velocity[k] = v[k] * 1e-3          # mm/s -> m/s
        r.buttons = self._buttons.value
        return r

    def _set_force(self, force: np.ndarray) -> None:
        self._force_cmd = (float(force[0]), float(force[1]), float(force[2]))

    def health(self) -> str | None:
        """The servo loop's error, or a stalled servo loop (no frame since the previous call >= 50 ms ago)."""
        if self.fault:
            return self.fault
        now = time.perf_counter()
        if now - self._health_t >= 0.05:
            if self.servo_ticks == self._health_ticks and self._health_t > 0:
                return "servo loop stopped (no frames from the HD scheduler)"
            self._health_t, self._health_ticks = now, self.servo_ticks
        return None
