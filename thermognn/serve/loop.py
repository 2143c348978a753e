"""The HAPTIC process: the 1 kHz loop. Imports numpy and the device plugins only, never torch.

Each tick (period 1/``rate``; sleep until ``spin_us`` before the deadline, then spin on
``time.perf_counter_ns``):

1. read the device; map its position to the model frame (virtual devices are already there);
2. publish the tool state to the physics process (seqlock buffer, no pickling);
3. if the physics process published a new local model (f0, x0, K), start blending to it from
   the previous one over one physics period; render f = f0 + K (x - x0) (never pulling);
4. safety chain (``thermognn.serve.safety``): NaN check, watchdog fade, ramp-in (judged on
   the commanded force), device force limits, passivity controller, force-rate limit;
5. command the force, write a log row into the shared ring buffer.

No allocation, model work or I/O in the loop (preallocated numpy arrays, in-place maths). On
any exit (duration, stop request, SIGTERM, device error, NaN) the device gets zero force.

``bare_loop`` runs the same pacing (``wait_until``) with no work: the machine's timing floor.
"""

from __future__ import annotations

import gc
import os
import signal
import sys
import time
from dataclasses import asdict

import numpy as np

from thermognn.core.errors import DeviceError

from . import protocol as P
from .safety import (EngageRamp, ForceClamp, PassivityController, RateLimiter, Watchdog, is_finite3,
                     limit_stiffness, norm3)
from .shm import SharedArrays, VersionedBuffer


class LocalModel:
    """One linearised contact model f(x) = f0 + K (x - x0) [N], never pulling (f . f0 >= 0)."""

    def __init__(self) -> None:
        self.f0 = np.zeros(3)
        self.x0 = np.zeros(3)
        self.K = np.zeros((3, 3))
        self._dx = np.zeros(3)

    def set(self, payload: np.ndarray, k_max: float) -> None:
        self.f0[:] = payload[P.M_F0]
        self.x0[:] = payload[P.M_X0]
        self.K.reshape(-1)[:] = payload[P.M_K]
        limit_stiffness(self.K, k_max)

    def copy_from(self, other: "LocalModel") -> None:
        self.f0[:] = other.f0
        self.x0[:] = other.x0
        self.K[:] = other.K

    def render(self, x: np.ndarray, out: np.ndarray) -> None:
        np.subtract(x, self.x0, out=self._dx)
        np.dot(self.K, self._dx, out=out)
        out += self.f0
        f0 = self.f0
        if out[0] * f0[0] + out[1] * f0[1] + out[2] * f0[2] <= 0.0:  # contact released: no pull
            out[:] = 0.0


class Blender:
    """Multirate blending: when a new local model arrives, move from the previous one to it
    linearly over one physics period (estimated in ticks), so the force never steps. A model
    arriving mid-blend starts from the blend as rendered at that moment (frozen as a linear model
    at the current position), not from the half-reached target."""

    def __init__(self, max_ticks: float = 50.0) -> None:
        self.previous = LocalModel()
        self.current = LocalModel()
        self.start_tick = 0
        self.period_ticks = 1.0      # EMA of ticks between physics updates
        self.blend_ticks = 1.0       # length of the current blend [ticks]
        self.max_ticks = float(max_ticks)
        self.last_update_tick = -1
        self._fp = np.zeros(3)
        self._fb = np.zeros(3)

    def weight(self, tick: int) -> float:
        """Blend weight of the current model at ``tick`` (1: fully the current one)."""
        return min(1.0, (tick - self.start_tick + 1) / max(self.blend_ticks, 1.0))

    def update(self, payload: np.ndarray, tick: int, k_max: float, x: np.ndarray) -> None:
        """Take the new local model ``payload`` at ``tick``, the tool being at ``x`` [3] m."""
        if self.last_update_tick < 0:
            self.current.set(payload, k_max)            # first model: nothing to blend from
            self.previous.copy_from(self.current)
        else:
            w = self.weight(tick)
            if w < 1.0:                                 # mid-blend: freeze the blend at x
                self.render(x, tick, self._fb)
                prev = self.previous
                prev.K *= 1.0 - w
                prev.K += w * self.current.K
                prev.f0[:] = self._fb
                prev.x0[:] = x
            else:
                self.previous.copy_from(self.current)
            self.current.set(payload, k_max)
            gap = tick - self.last_update_tick
            self.period_ticks += 0.2 * (gap - self.period_ticks)
            # after a late update (physics stalled) blend over the gap itself, up to max_ticks
            self.blend_ticks = max(self.period_ticks, min(float(gap), self.max_ticks))
        self.last_update_tick = tick
        self.start_tick = tick

    def render(self, x: np.ndarray, tick: int, out: np.ndarray) -> None:
        self.current.render(x, out)
        w = self.weight(tick)
        if w < 1.0:
            fp = self._fp
            self.previous.render(x, fp)
            for i in range(3):
                out[i] = (1.0 - w) * fp[i] + w * out[i]


def wait_until(deadline_ns: int, spin_ns: int, _perf=time.perf_counter_ns, _sleep=time.sleep) -> int:
    """Pace one tick: sleep until ``spin_ns`` before ``deadline_ns`` (``time.perf_counter_ns``
    clock), then spin to it; returns the wake time [ns]. The haptic loop's only timing code."""
    remaining = deadline_ns - _perf()
    if remaining > spin_ns:
        _sleep((remaining - spin_ns) * 1e-9)
    while _perf() < deadline_ns:
        pass
    return _perf()


def period_statistics(t: np.ndarray, rate: float) -> dict:
    """Period figures of tick times ``t`` [s] against the nominal ``rate`` [Hz]: rate, period
    p50/p99/p99.9 [ms], worst gap [ms], period error |period - 1/rate| p99/p99.9 [us], gaps over
    2 ms (NaN figures, rate 0 and no gaps with fewer than 3 ticks). Shared by the session log
    statistics (``thermognn.serve.runner.loop_statistics``) and :func:`bare_loop`."""
    t = np.asarray(t, dtype=float)
    if len(t) <= 2:
        nan = float("nan")
        return dict(loop_rate_hz=0.0, period_p50_ms=nan, period_p99_ms=nan, period_p999_ms=nan,
                    worst_gap_ms=nan, period_err_p99_us=nan, period_err_p999_us=nan, gaps_over_2ms=0)
    period = np.diff(t) * 1e3                                     # [ms]
    err = np.abs(period - 1e3 / rate) * 1e3                       # [us]
    p50, p99, p999 = np.percentile(period, (50, 99, 99.9))
    e99, e999 = np.percentile(err, (99, 99.9))
    return dict(loop_rate_hz=float((len(t) - 1) / (t[-1] - t[0])), period_p50_ms=float(p50),
                period_p99_ms=float(p99), period_p999_ms=float(p999), worst_gap_ms=float(period.max()),
                period_err_p99_us=float(e99), period_err_p999_us=float(e999),
                gaps_over_2ms=int((period > 2.0).sum()))


def bare_loop(seconds: float, rate: float = 1000.0, spin_us: float = 400.0, realtime: bool = True,
              cpu: int | None = None) -> dict:
    """The haptic loop's pacing (:func:`wait_until`, same overrun rebase) with no work per tick,
    for ``seconds``: the timing floor of the machine. Pins, locks memory and asks for SCHED_FIFO
    like the haptic process (:func:`_pin_and_prioritise`; this changes the calling process, so
    run it in a process of its own), gc disabled in the loop, wake times in a preallocated array.
    Returns :func:`period_statistics` plus "ticks", "overruns", "seconds" and "scheduler"."""
    period_ns = int(round(1e9 / rate))
    spin_ns = int(spin_us * 1000)
    duration_ns = int(seconds * 1e9)
    wake = np.empty(int(seconds * rate) + 2, dtype=np.int64)      # more than enough ticks
    wake.fill(0)                                                  # touched now: no page faults later
    capacity = len(wake)
    scheduler = _pin_and_prioritise(cpu, realtime)
    wait = wait_until
    overruns = 0
    n = 0
    gc_was_enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        t_start = time.perf_counter_ns()
        t_next = t_start
        while n < capacity:
            t_wake = wait(t_next, spin_ns)
            wake[n] = t_wake
            n += 1
            if t_wake - t_start >= duration_ns:
                break
            if t_wake - t_next > period_ns:       # overran a whole period: rebase, as run_loop
                overruns += 1
                t_next = t_wake
            t_next += period_ns
    finally:
        if gc_was_enabled:
            gc.enable()
    out = {"ticks": n, "overruns": overruns, "seconds": float(seconds), "scheduler": scheduler}
    out.update(period_statistics((wake[:n] - wake[0]) * 1e-9 if n else wake[:0], rate))
    return out


def _pin_and_prioritise(cpu: int | None, realtime: bool) -> str:
    """Best effort: pin to ``cpu``, lock memory and ask for SCHED_FIFO; returns the policy obtained."""
    if cpu is not None and cpu >= 0:
        try:
            os.sched_setaffinity(0, {int(cpu)})
        except (AttributeError, OSError, ValueError):
            pass
    if realtime:
        _lock_memory()
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
            return "fifo"
        except (AttributeError, OSError, PermissionError):
            pass
    return "other"


def _lock_memory() -> bool:
    """Best effort mlockall(MCL_CURRENT | MCL_FUTURE): no page faults in the loop."""
    try:
        import ctypes
        import ctypes.util
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        return libc.mlockall(1 | 2) == 0
    except (OSError, AttributeError):
        return False


def haptic_main(params: dict, conn) -> None:
    """Entry point of the haptic process (multiprocessing target). ``conn``: pipe to the main process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)           # Ctrl-C is handled by the main process
    term = [False]
    signal.signal(signal.SIGTERM, lambda *_: term.__setitem__(0, True))
    shared = SharedArrays.attach(params["shm"])
    control = shared["control"]
    summary: dict = {"error": None}
    device = None
    zeroed = False
    try:
        from thermognn import devices
        cls = devices.load(params["device"])
        device = cls(**params.get("device_options", {}))
        device.attach_scene(np.asarray(params["lo"]), np.asarray(params["hi"]), params["tool_radius"])
        if params.get("surface"):
            faces = params.get("surface_faces")
            device.attach_surface(np.asarray(params["surface"], dtype=float),
                                  np.asarray(faces, dtype=np.int64) if faces else None)
        specs = device.open()
        conn.send({"ok": True, "specs": asdict(specs)})
        summary["torch_loaded"] = "torch" in sys.modules      # must stay False (checked by the tests)
        summary["scheduler"] = _pin_and_prioritise(params.get("cpu"), bool(params.get("realtime_priority", True)))
        summary.update(run_loop(params, device, shared, term))
    except DeviceError as exc:
        P.request_stop(control, "device_error")
        summary["error"] = str(exc)
    except Exception as exc:  # noqa: BLE001 - reported to the main process, force zeroed below
        P.request_stop(control, "haptic_crash")
        summary["error"] = f"{type(exc).__name__}: {exc}"
    finally:
        if device is not None and device.is_open:
            try:
                device.set_force(np.zeros(3))
                zeroed = True
            except Exception as exc:  # noqa: BLE001
                summary["error"] = summary["error"] or f"zero force failed: {exc}"
            try:
                device.close()      # closes with zero force again
            except Exception as exc:  # noqa: BLE001
                summary["error"] = summary["error"] or f"device close failed: {exc}"
        control[P.C_FINAL_FORCE] = 0.0 if (zeroed or device is None) else float("nan")
        control[P.C_FORCE] = 0.0
        control[P.C_HAPTIC_STATE] = 2
        P.send_summary(conn, summary)
        gc.enable()
        shared.close()


def run_loop(params: dict, device, shared: SharedArrays, term: list) -> dict:
    """The 1 kHz loop proper; returns loop statistics. See the module docstring."""
    control, log = shared["control"], shared["log"]
    model_buf = VersionedBuffer(shared["model"], P.MODEL_PAYLOAD)
    tool_buf = VersionedBuffer(shared["tool"], P.TOOL_PAYLOAD)
    specs = device.specs
    rate = float(params["rate"])
    dt = 1.0 / rate
    period_ns = int(round(1e9 / rate))
    spin_ns = int(params.get("spin_us", 400.0) * 1000)
    duration = float(params["duration"])
    log_rows = log.shape[0]

    # frames: model = anchor + scale * R @ device ; device force = force_scale * R^T @ model force
    scene = bool(device.scene_frame)
    R = np.asarray(getattr(device, "axes_to_model", np.eye(3)), dtype=float)
    RT = np.ascontiguousarray(R.T)
    scale = 1.0 if scene else float(params.get("workspace_scale", 1.0))
    force_scale = float(params.get("force_scale", 1.0))
    anchor = np.zeros(3) if scene else np.asarray(params["anchor"], dtype=float)
    k_max = specs.max_stiffness / max(scale * force_scale, 1e-12)   # model-frame stiffness limit [N/m]

    # safety chain
    clamp = ForceClamp(specs.max_force, specs.max_continuous_force, dt, params.get("continuous_tau", 1.0))
    engage = EngageRamp(dt, params.get("engage_threshold", 0.1), params.get("ramp_s", 0.5))
    max_step = params.get("max_force_step") or specs.max_force_rate * dt
    rate_limit = RateLimiter(max_step)
    passivity = PassivityController(dt, min(params.get("max_damping", 5.0), specs.max_damping))
    watchdog = Watchdog(params["stale_ms"] / 1000.0, params.get("fade_ms", 100.0) / 1000.0, dt)

    # preallocated state
    x = np.zeros(3)            # tool centre, model frame [m]
    v = np.zeros(3)            # tool velocity, model frame [m/s]
    f_model = np.zeros(3)      # rendered force, model frame [N]
    f_dev = np.zeros(3)        # commanded force, device frame [N]
    f_log = np.zeros(3)
    tool = np.zeros(P.TOOL_PAYLOAD)
    payload = np.zeros(P.MODEL_PAYLOAD)
    blender = Blender(max_ticks=max(1.0, params["stale_ms"] / 1000.0 * rate))
    last_version = 0.0
    physics_time = 0.0
    physics_step = 0.0
    contact = 0.0
    reason = ""
    stopping = ""              # reason of a requested stop, while the force fades out
    stop_gain = 1.0
    stop_step = dt / max(params.get("fade_ms", 100.0) / 1000.0, dt)
    overruns = 0
    max_alpha = 0.0
    busy_sum = 0
    busy_max = 0

    parent = os.getppid()
    gc.collect()
    gc.disable()                                  # no collector pauses inside the loop
    perf_ns = time.perf_counter_ns
    wait = wait_until
    t_start = perf_ns()
    t_next = t_start
    control[P.C_LOOP_T0] = t_start / 1e9
    control[P.C_HAPTIC_STATE] = 1
    tick = 0
    while True:
        # -- timing: sleep, then spin to the deadline ------------------------------------------
        t_wake = wait(t_next, spin_ns)
        if t_wake - t_next > period_ns:       # overran a whole period: rebase, no catch-up burst
            overruns += 1
            t_next = t_wake
        t_next += period_ns
        now = t_wake * 1e-9

        # -- stop conditions: fade the force out over fade_ms, then leave --------------------
        if not stopping:
            if control[P.C_STOP] != 0:
                stopping = P.REASONS[int(control[P.C_STOP])]
            elif term[0]:
                stopping = "sigterm"
            elif duration > 0 and (t_wake - t_start) * 1e-9 >= duration:
                stopping = "duration"
            elif device.done:
                stopping = "device_finished"
            if stopping:
                P.request_stop(control, stopping)   # tells the physics process and the main process
        else:
            stop_gain -= stop_step
            if stop_gain <= 0.0:
                reason = stopping
                break
        if tick % 100 == 0:
            fault = device.health()
            if fault:
                raise DeviceError(f"{specs.name}: {fault}")
            if not stopping and os.getppid() != parent:     # main process killed: stop on our own
                stopping = "main_gone"
                P.request_stop(control, stopping)

        # -- device -> model frame -------------------------------------------------------------
        r = device.read()
        if scene:
            x[:] = r.position
            v[:] = r.velocity
        else:
            np.dot(R, r.position, out=x)
            x *= scale
            x += anchor
            np.dot(R, r.velocity, out=v)
            v *= scale
        tool[P.T_TIME] = now
        tool[P.T_X] = x
        tool[P.T_V] = v
        tool_buf.publish(tool)

        # -- multirate local model ---------------------------------------------------------------
        if model_buf.read(payload) and payload[P.M_VERSION] != last_version:
            last_version = payload[P.M_VERSION]
            physics_time = payload[P.M_TIME]
            physics_step = payload[P.M_STEP]
            contact = payload[P.M_CONTACT]
            blender.update(payload, tick, k_max, x)
        blender.render(x, tick, f_model)
        if not is_finite3(f_model):
            P.request_stop(control, "haptic_nan")
            reason = "haptic_nan"
            break

        # -- safety chain (device frame) ---------------------------------------------------------
        g = watchdog.gain(now, physics_time)
        if watchdog.faded:
            engage.reset()
        if scene:
            f_dev[:] = f_model
        else:
            np.dot(RT, f_model, out=f_dev)
        f_dev *= force_scale
        e = engage.gain(norm3(f_dev))              # on the commanded force, before the fades
        f_dev *= g * stop_gain * e
        clamp.apply(f_dev)
        if scene:                                   # device-frame velocity for the observer
            passivity.apply(f_dev, v)
        else:
            passivity.apply(f_dev, r.velocity)
        clamp.apply_peak(f_dev)
        rate_limit.apply(f_dev)
        passivity.commit(f_dev, v if scene else r.velocity)
        if passivity.alpha > max_alpha:
            max_alpha = passivity.alpha
        device.set_force(f_dev)

        # -- log (ring buffer) --------------------------------------------------------------------
        if scene:
            f_log[:] = f_dev
        else:
            np.dot(R, f_dev, out=f_log)
            f_log *= 1.0 / force_scale
        row = log[tick % log_rows]
        row[P.L_T] = (t_wake - t_start) * 1e-9
        row[P.L_X] = x
        row[P.L_F] = f_log
        row[P.L_STEP] = physics_step
        row[P.L_CONTACT] = contact
        tick += 1
        control[P.C_TICKS] = tick
        control[P.C_FORCE] = norm3(f_dev)
        control[P.C_CONTACT] = contact
        control[P.C_ENERGY] = passivity.energy
        busy = perf_ns() - t_wake                   # work per tick [ns] (headroom check)
        busy_sum += busy
        if busy > busy_max:
            busy_max = busy

    # -- exit: zero force, final log row --------------------------------------------------------
    f_dev[:] = 0.0
    device.set_force(f_dev)
    t_end = perf_ns()
    row = log[tick % log_rows]
    row[P.L_T] = (t_end - t_start) * 1e-9
    row[P.L_X] = x
    row[P.L_F] = 0.0
    row[P.L_STEP] = physics_step
    row[P.L_CONTACT] = 0.0
    control[P.C_TICKS] = tick + 1
    control[P.C_FORCE] = 0.0
    P.request_stop(control, reason or "stopped")
    gc.enable()
    return {"reason": reason, "ticks": tick, "overruns": overruns, "passivity_energy_J": passivity.energy,
            "passivity_dissipated_J": passivity.dissipated, "max_damping_Ns_per_m": max_alpha,
            "blend_period_ticks": blender.period_ticks, "elapsed_s": (t_end - t_start) * 1e-9,
            "tick_work_mean_us": busy_sum / max(tick, 1) / 1e3, "tick_work_max_us": busy_max / 1e3}
