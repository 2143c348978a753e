"""``serve(cfg)``: the main process. Starts the physics and haptic processes ("spawn"), shows the
live panel, handles Ctrl-C/SIGTERM, joins, writes the session log and returns the summary.

Imports neither torch nor dolfinx (torch lives in the physics process only).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
from omegaconf import DictConfig, OmegaConf

from thermognn.core.config import project_path, scene_served_hht
from thermognn.core.errors import ConfigError, DataError, DeviceError, ThermoGNNError
from thermognn.core.io import atomic_path
from thermognn.core.state import law_iterates

from . import protocol as P
from .coupling import COUPLINGS
from .loop import haptic_main, period_statistics
from .physics import physics_main

#: longest stretch of the session kept in the log [s] (ring buffer in shared memory)
MAX_LOG_S = 600.0


def _serve_params(cfg: DictConfig) -> dict:
    """Checked plain-Python settings from ``cfg.serve`` (ConfigError names the key)."""
    s = cfg.serve
    def num(key: str, positive: bool = True) -> float:
        value = OmegaConf.select(s, key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"serve.{key} = {value!r}, expected a number")
        if positive and value <= 0:
            raise ConfigError(f"serve.{key} = {value!r}, expected > 0")
        return float(value)

    def flag(key: str, default: bool) -> bool:
        value = OmegaConf.select(s, key, default=default)
        if not isinstance(value, bool):
            raise ConfigError(f"serve.{key} = {value!r}, expected true or false")
        return value
    params = {
        "device": str(s.device),
        "duration": num("duration", positive=False),
        "rate": num("rate"),
        "tool_radius": num("tool_radius"),
        "contact_stiffness": num("contact_stiffness"),
        "stale_ms": num("stale_ms"),
        "load_radius": num("load_radius", positive=False),
        "fade_ms": num("fade_ms"),
        "engage_threshold": num("engage_threshold", positive=False),
        "ramp_s": num("ramp_s", positive=False),
        "max_damping": num("max_damping", positive=False),
        "workspace_scale": num("workspace_scale"),
        "force_scale": num("force_scale"),
        "spin_us": num("spin_us", positive=False),
        "threads": int(num("physics_threads")),
        "body_stiffness_every": int(num("body_stiffness_every", positive=False)),
        "contact_coupling": str(OmegaConf.select(s, "contact_coupling", default="implicit")),
        "contact_rtol": num("contact_rtol"),
        "contact_trials": OmegaConf.select(s, "contact_trials"),
        "realtime": bool(s.realtime_physics),
        "body_passivity": flag("body_passivity", True),
        "body_reset": flag("body_reset", True),
        "realtime_priority": bool(s.realtime_priority),
        "startup_timeout": num("startup_timeout"),
    }
    if params["body_stiffness_every"] < 0 or params["body_stiffness_every"] != s.body_stiffness_every:
        raise ConfigError(f"serve.body_stiffness_every = {s.body_stiffness_every!r}, expected an integer >= 0")
    if params["contact_coupling"] not in COUPLINGS:
        raise ConfigError(f"serve.contact_coupling = {s.contact_coupling!r}, expected one of {', '.join(COUPLINGS)}")
    trials = params["contact_trials"]
    if isinstance(trials, bool) or not isinstance(trials, int) or trials < 1:
        raise ConfigError(f"serve.contact_trials = {trials!r}, expected an integer >= 1")
    params["max_force_step"] = None if s.max_force_step is None else num("max_force_step")
    options = OmegaConf.to_container(s.device_options, resolve=True) if s.device_options else {}
    if params["device"] == "sim":
        options.setdefault("path", str(s.path))
    if params["device"] == "replay" and s.replay_file is not None:
        options.setdefault("file", str(project_path(s.replay_file)))
    params["device_options"] = options
    return params


def _log_path(cfg: DictConfig) -> Path:
    if cfg.serve.log is not None:
        return Path(str(cfg.serve.log))
    return Path(str(cfg.out)) / "serve_log.csv"


def _ordered_log(log: np.ndarray, n: int) -> np.ndarray:
    """Rows of the ring buffer in time order ([min(n, rows), 9])."""
    rows = log.shape[0]
    if n <= rows:
        return log[:n].copy()
    k = n % rows
    return np.concatenate([log[k:], log[:k]])


def loop_statistics(rows: np.ndarray, rate: float) -> dict:
    """Timing and force figures of a session log (rows [T, 9]; the last row is the exit row)."""
    ticks = rows[:-1] if len(rows) > 1 else rows
    out: dict = {"ticks": int(len(ticks))}
    out.update(period_statistics(ticks[:, P.L_T], rate))
    force = rows[:, P.L_F]                                            # includes the exit row
    mag = np.linalg.norm(force, axis=1)
    out["max_force_N"] = float(mag.max()) if len(mag) else 0.0
    out["max_force_step_N"] = float(np.linalg.norm(np.diff(force, axis=0), axis=1).max()) if len(force) > 1 else 0.0
    out["contact_ticks"] = int((ticks[:, P.L_CONTACT] > 0).sum())
    out["contact_force_ticks"] = int((np.linalg.norm(ticks[:, P.L_F], axis=1) > 1e-9).sum())
    return out


def write_session_log(path: Path, rows: np.ndarray, summary: dict) -> None:
    """CSV (header t,x,y,z,fx,fy,fz,physics_step,contact) or HDF5 by suffix; atomic."""
    with atomic_path(path) as tmp:
        if path.suffix in (".h5", ".hdf5"):
            import h5py
            with h5py.File(tmp, "w") as h5:
                h5["time"] = rows[:, P.L_T]
                h5["position"] = rows[:, P.L_X]
                h5["force"] = rows[:, P.L_F]
                h5["physics_step"] = rows[:, P.L_STEP].astype(np.int64)
                h5["contact"] = rows[:, P.L_CONTACT].astype(np.int8)
                h5.attrs["summary"] = json.dumps(summary)
        else:
            np.savetxt(tmp, rows, delimiter=",", header=",".join(P.LOG_COLUMNS), comments="",
                       fmt=["%.6f"] + ["%.9g"] * 6 + ["%d", "%d"])


class _Panel:
    """Live rich panel (loop rate, period percentiles, physics rate, contact, force); quiet off a terminal."""

    def __init__(self, enabled: bool, device: str) -> None:
        from rich.console import Console
        self.console = Console()
        self.enabled = enabled and self.console.is_terminal
        self.device = device
        self.live = None
        self._last: tuple[float, float] | None = None   # (time, physics steps) of the previous update

    def __enter__(self) -> "_Panel":
        if self.enabled:
            from rich.live import Live
            self.live = Live(console=self.console, auto_refresh=False, transient=False)
            self.live.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.live is not None:
            self.live.__exit__(*exc)

    def update(self, control: np.ndarray, log: np.ndarray, rate: float) -> None:
        if self.live is None:
            return
        from rich.table import Table
        n = int(control[P.C_TICKS])
        k = min(n, 2000, log.shape[0])
        idx = (np.arange(n - k, n) % log.shape[0]) if k else np.zeros(0, dtype=int)
        t = log[idx, P.L_T]
        now, steps = time.perf_counter(), float(control[P.C_STEPS])
        t_prev, s_prev = self._last or (now, steps)
        phys = (steps - s_prev) / (now - t_prev) if now > t_prev else float("nan")
        self._last = (now, steps)
        table = Table(title=f"thermognn serve — {self.device}", show_header=False)
        if len(t) > 10:
            per = np.diff(t) * 1e3
            table.add_row("loop rate", f"{(len(t) - 1) / max(t[-1] - t[0], 1e-9):8.1f} Hz")
            table.add_row("period p50/p99/p99.9", "  ".join(f"{np.percentile(per, q):.3f}" for q in (50, 99, 99.9)) + " ms")
        table.add_row("physics rate", f"{phys:8.1f} Hz (step {int(steps)})")
        table.add_row("contact", "yes" if control[P.C_CONTACT] else "no")
        table.add_row("force", f"{control[P.C_FORCE]:.3f} N")
        table.add_row("elapsed", f"{(t[-1] if len(t) else 0.0):.1f} s")
        self.live.update(table, refresh=True)


@contextlib.contextmanager
def _signals(control: np.ndarray):
    """Ctrl-C / SIGTERM request a clean stop (main thread only; elsewhere the caller handles them)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    def handler(signum, _frame):
        P.request_stop(control, "sigint" if signum == signal.SIGINT else "sigterm")
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _status(control: np.ndarray, physics_pid: int | None, haptic_pid: int | None) -> dict:
    """Live status for ``serve(monitor=...)``."""
    return {"elapsed_s": time.perf_counter() - float(control[P.C_LOOP_T0]), "ticks": int(control[P.C_TICKS]),
            "physics_steps": int(control[P.C_STEPS]), "force_N": float(control[P.C_FORCE]),
            "contact": bool(control[P.C_CONTACT]), "physics_pid": physics_pid, "haptic_pid": haptic_pid}


def _recv(conn, timeout: float, proc) -> dict | None:
    """The next message from a child, None if it died or timed out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if conn.poll(0.05):
            try:
                return conn.recv()
            except (EOFError, OSError):
                return None
        if not proc.is_alive() and not conn.poll(0):
            return None
    return None


def serve(cfg: DictConfig, monitor: Callable[[dict], None] | None = None) -> dict:
    """Run the haptic session described by ``cfg.serve`` on the model ``cfg.paths.exported``.

    ``monitor`` (optional) is called from the main process about every 0.1 s while the loop runs
    with a status dict (elapsed_s, ticks, physics_steps, force_N, contact, physics_pid,
    haptic_pid); tests use it to inject faults at a known moment.

    Returns the summary dict (loop_rate_hz, period_p50/p99/p999_ms, worst_gap_ms,
    physics_rate_hz, max_force_N, max_force_step_N, contact_ticks, final_force_N, exit_reason,
    physics_step_ms (median body step, its coupling trials together), body_fd_evaluations,
    contact_K_scale_mean (published K over contact stiffness), body_fd_disabled ("" or why the
    body-stiffness FD was off at the end), body_fd_off_checks (step-time checks that held it off), contact_coupling (serve.contact_coupling),
    contact_steps (body steps the implicit coupling loaded), contact_trials_per_step (its model calls
    a body step), contact_unsettled_steps and contact_unsettled_max_N (loaded steps whose load missed
    serve.contact_rtol within serve.contact_trials, and the largest such miss |g| [N]),
    physics_warning ("" or the step-time warning), and for a law-prior model law_steps,
    law_unconverged_steps, law_cut_steps, law_iterations and law_warning ("" or the first
    unconverged step's line), and with ``body_passivity`` passivity_steps, passivity_removed_J,
    passivity_work_J, passivity_absorbed_J (``thermognn.serve.passivity``), and for a body that
    carries its mesh body_largest_invariant, body_smallest_volume_ratio, body_steps_beyond_states,
    body_destroyed_steps, body_resets and body_warning (``thermognn.serve.health``),
    served_rule_note ("" or the lines of ``served_rule_note`` and ``served_step_note``),
    body_time_ratio (the body's seconds a wall second: physics_rate_hz times its Δt) and
    realtime_warning ("" or ``realtime_warning``'s line, also on stderr), ...).
    """
    from thermognn import devices

    params = _serve_params(cfg)
    devices.load(params["device"])                         # unknown plugin: fail before starting anything
    model_path = project_path(str(cfg.paths.exported))
    if not model_path.is_file():
        raise DataError(f"paths.exported: model file '{model_path}' not found (run `thermognn export` first)")
    log_path = _log_path(cfg)
    rate = params["rate"]
    # session log ring buffer: the whole session, at most its last MAX_LOG_S seconds
    log_rows = int(min(params["duration"] if params["duration"] > 0 else MAX_LOG_S, MAX_LOG_S) * rate + 2 * rate + 16)
    shared = P.make_shared(log_rows)
    control = shared["control"]
    params.update(shm=shared.spec(), model=str(model_path))
    ncpu = os.cpu_count() or 1
    if bool(cfg.serve.pin_cpus) and ncpu > 1:
        params["cpu"] = ncpu - 1
    ctx = mp.get_context("spawn")
    physics_conn, physics_child = ctx.Pipe()
    haptic_conn, haptic_child = ctx.Pipe()
    physics = ctx.Process(target=physics_main, args=(params, physics_child), name="thermognn-physics", daemon=True)
    haptic = None
    detail = ""
    physics_summary: dict = {}
    haptic_summary: dict = {}
    t_wall = time.perf_counter()
    control[P.C_FINAL_FORCE] = float("nan")                # the haptic process sets 0 once it has zeroed the device
    completed = False
    rule_note = ""                                         # served_rule_note, once the model's geometry is in
    try:
        with _signals(control):
            physics.start()
            geometry = _recv(physics_conn, params["startup_timeout"], physics)
            if geometry is None:
                raise DataError(f"paths.exported: physics process failed to load '{model_path}' "
                                f"(exit code {physics.exitcode})")
            if not geometry.get("ok"):
                raise DataError(geometry["error"])
            if control[P.C_STOP]:
                raise KeyboardInterrupt
            notes = [n for n in (served_rule_note(geometry, model_path), served_step_note(geometry, model_path)) if n]
            for line in notes:
                print(f"thermognn serve: note: {line}", file=sys.stderr, flush=True)
            rule_note = "; ".join(notes)
            lo, hi = np.array(geometry["lo"]), np.array(geometry["hi"])
            top = 0.5 * (lo + hi)
            top[2] = hi[2] + params["tool_radius"] + 0.5 * (hi[2] - lo[2])
            params.update(lo=lo.tolist(), hi=hi.tolist(), anchor=top.tolist(), surface=geometry.get("surface", []),
                          surface_faces=geometry.get("surface_faces", []))
            haptic = ctx.Process(target=haptic_main, args=(params, haptic_child), name="thermognn-haptic", daemon=True)
            haptic.start()
            opened = _recv(haptic_conn, 60.0, haptic)
            if opened is None or not opened.get("ok"):
                msg = (opened or {}).get("error") or f"haptic process exited with code {haptic.exitcode}"
                raise DeviceError(f"serve.device: {params['device']}: {msg}")
            with _Panel(bool(cfg.serve.panel), params["device"]) as panel:
                last_panel = 0.0
                while haptic.is_alive():
                    if not physics.is_alive() and control[P.C_STOP] == 0:
                        P.request_stop(control, "physics_crash")
                        detail = f"physics process exited with code {physics.exitcode}"
                    if monitor is not None and control[P.C_HAPTIC_STATE] == 1:
                        monitor(_status(control, physics.pid, haptic.pid))
                    if time.perf_counter() - last_panel >= 0.2:
                        panel.update(control, shared["log"], rate)
                        last_panel = time.perf_counter()
                    haptic.join(timeout=0.1)
                panel.update(control, shared["log"], rate)
            if haptic_conn.poll(1.0):
                haptic_summary = haptic_conn.recv()
            if haptic.exitcode not in (0, None) and control[P.C_STOP] == 0:
                P.request_stop(control, "haptic_crash")
                detail = f"haptic process exited with code {haptic.exitcode}"
        completed = True
    except KeyboardInterrupt:
        P.request_stop(control, "sigint")
        completed = True
    finally:
        P.request_stop(control, "stopped")
        for proc in (haptic, physics):
            if proc is not None and proc.pid is not None:
                proc.join(timeout=10.0)
                if proc.is_alive():
                    proc.terminate()
                    proc.join(timeout=5.0)
        if physics_conn.poll(0):
            with contextlib.suppress(EOFError, OSError):
                msg = physics_conn.recv()
                physics_summary = msg if "steps" in msg else physics_summary
        ran = haptic is not None and int(control[P.C_TICKS]) > 0
        stop_reason = P.REASONS[int(control[P.C_STOP])]
        if not (ran and completed):
            shared.close()              # startup failed or an exception propagates
    if not ran:
        if haptic_summary.get("error"):
            raise DeviceError(f"serve.device: {params['device']}: {haptic_summary['error']}")
        if stop_reason in ("sigint", "sigterm"):
            raise ThermoGNNError(f"serve: interrupted ({stop_reason}) before the haptic loop started")
        raise ThermoGNNError(f"serve: the haptic loop did not run (stop reason: {stop_reason})")

    reason = P.REASONS[int(control[P.C_STOP])]
    detail = detail or haptic_summary.get("error") or physics_summary.get("error") or ""
    if reason == "physics_nan" and "nan_at_step" in physics_summary:
        detail = detail or f"model state not finite at step {physics_summary['nan_at_step']}"
    rows = _ordered_log(shared["log"], int(control[P.C_TICKS]))
    steps = float(control[P.C_STEPS])
    phys_span = float(control[P.C_PHYSICS_T] - control[P.C_PHYSICS_T0])
    summary = {"device": params["device"], "exit_reason": reason, "exit_detail": detail}
    summary.update(loop_statistics(rows, rate))
    summary.update(
        physics_rate_hz=steps / phys_span if phys_span > 0 else 0.0,
        physics_steps=int(steps),
        final_force_N=float(control[P.C_FINAL_FORCE]),
        overruns=int(haptic_summary.get("overruns", 0)),
        tick_work_mean_us=float(haptic_summary.get("tick_work_mean_us", float("nan"))),
        tick_work_max_us=float(haptic_summary.get("tick_work_max_us", float("nan"))),
        blend_period_ticks=float(haptic_summary.get("blend_period_ticks", float("nan"))),
        passivity_dissipated_J=float(haptic_summary.get("passivity_dissipated_J", 0.0)),
        max_damping_Ns_per_m=float(haptic_summary.get("max_damping_Ns_per_m", 0.0)),
        physics_step_ms=float(physics_summary.get("step_ms", float("nan"))),
        physics_fd_ms=float(physics_summary.get("fd_ms", float("nan"))),
        body_fd_evaluations=int(physics_summary.get("fd_evaluations", 0)),
        body_stiffness_mean_N_per_m=float(physics_summary.get("body_stiffness_mean_N_per_m", float("nan"))),
        contact_K_scale_mean=float(physics_summary.get("k_scale_mean", float("nan"))),
        physics_warning=str(physics_summary.get("warning", "")),
        body_fd_disabled=str(physics_summary.get("fd_disabled", "")),
        body_fd_off_checks=int(physics_summary.get("fd_off_checks", 0)),
        contact_coupling=str(physics_summary.get("contact_coupling", params["contact_coupling"])),
        contact_steps=int(physics_summary.get("contact_steps", 0)),
        contact_trials_per_step=float(physics_summary.get("contact_trials_per_step", float("nan"))),
        contact_unsettled_steps=int(physics_summary.get("contact_unsettled_steps", 0)),
        contact_unsettled_max_N=float(physics_summary.get("contact_unsettled_max_N", 0.0)),
        **{k: physics_summary[k] for k in ("law_steps", "law_unconverged_steps", "law_cut_steps",
                                           "law_iterations", "law_warning", "passivity_steps",
                                           "passivity_removed_J", "passivity_work_J", "passivity_absorbed_J")
           if k in physics_summary},
        n_nodes=int(geometry["n_nodes"]),
        model_step=str(geometry.get("step", "")),
        data_time_error=str(geometry.get("data_time_error", "")),
        served_rule_note=rule_note,
        haptic_scheduler=str(haptic_summary.get("scheduler", "")),
        haptic_torch_loaded=bool(haptic_summary.get("torch_loaded", False)),
        wall_s=time.perf_counter() - t_wall,
        log=str(log_path),
    )
    dt = float(geometry.get("dt", 0.0))                    # [s] the body's step
    summary["body_time_ratio"] = summary["physics_rate_hz"] * dt
    summary["realtime_warning"] = realtime_warning(summary["body_time_ratio"], dt, summary["contact_ticks"],
                                                   summary["contact_force_ticks"], params["stale_ms"], int(steps))
    if summary["realtime_warning"]:
        print(f"thermognn serve: warning: {summary['realtime_warning']}", file=sys.stderr, flush=True)
    shared.close()
    write_session_log(log_path, rows, summary)
    _print_summary(summary)
    return summary


#: ``realtime_warning``: below this share of real time a session's body is said to lag the hand
REALTIME_WARN = 0.5


def realtime_warning(ratio: float, dt: float, contact_ticks: int, force_ticks: int, stale_ms: float,
                     steps: int) -> str:
    """One line where the body's time ran at less than ``REALTIME_WARN`` of real time over a
    session (``ratio``: body seconds a wall second, ``body_time_ratio``; ``dt`` [s] its step;
    ``steps`` its body steps, two at least), else "". The physics process steps the body as fast
    as it can against the tool where the hand is now, so a body at 1/r of real time sees the tool
    move r times faster in its own time than the hand moved: its inertia and viscosity resist
    r times the speed they would (session 99: the liver's law under `serve` on a 2-core CPU took
    2.2 body steps of Δt = 20 ms a second, 23x slower than real time; stepped in lockstep,
    ``thermognn.serve.lockstep.press_rollout``, the sim press 20x faster, as such a body sees it,
    peaked at 6.6 N against 2.3 N at its own pace), and a step slower
    than ``stale_ms`` leaves the haptic loop a stale force model that its watchdog fades
    (``contact_ticks`` and ``force_ticks``: the ticks in contact and those with a force)."""
    if steps < 2 or dt <= 0.0 or not ratio < REALTIME_WARN:
        return ""
    slower = 1.0 / ratio if ratio > 0 else float("inf")
    felt = (f"; the force reached the device on {force_ticks} of {contact_ticks} ticks in contact (the watchdog "
            f"fades a force model older than serve.stale_ms = {stale_ms:g} ms)" if contact_ticks else "")
    return (f"the body's time ran at {ratio:.2g} of real time ({steps} steps of Δt = {dt * 1e3:g} ms, "
            f"{slower:.3g}x slower): the tool moved {slower:.3g}x faster in the body's time than the hand did, "
            f"so its inertia and any viscosity resisted a faster motion than the hand's{felt}; a faster body step "
            f"(its median is physics_step_ms) is what serves this body in real time")


def served_rule_note(geometry: dict, model_path) -> str:
    """One line where a law model is served at its data's undamped Newmark rule though its scene
    declares the rule it is served with (``scene.time.served_hht`` in ``conf/scene/<scene>.yaml``,
    which ``thermognn export`` applies since session 96: the liver's HHT 0.02, which held its law
    under 60 s of the sim press where the undamped rule collapsed it within 30 s); "" otherwise
    (no law, a damped or energy rule already, a scene that declares none or is not found)."""
    step, name = geometry.get("step_settings") or {}, str(geometry.get("scene") or "")
    if not step.get("law") or step.get("law_hht") or step.get("law_rule") == "energy" or not name:
        return ""
    try:
        hht = scene_served_hht(name)
    except ConfigError:                                    # a note, never a failure
        return ""
    if not hht:
        return ""
    return (f"{model_path} steps the {name} scene's law at its data's undamped Newmark rule, where the scene "
            f"serves it with HHT's α = -{float(hht):g} (scene.time.served_hht: the undamped liver collapsed "
            f"within 30 s of pressing, the damped one held 60 s); export it again (thermognn export) unless "
            f"rollout.prior_hht=0 was meant")


def served_step_note(geometry: dict, model_path) -> str:
    """One line where a law iterated to a tolerance is served with a fresh tangent at every Newton
    update or without a line search, as files exported before session 97 are (``thermognn export``
    now keeps the tangent and searches the updates: under the sim press the bunny's body stepped 5x
    faster, and cut no step after the tool's release where the fresh, unsearched one took up to
    16 s a step), or with unmixed chord updates, as files exported before session 102 are (the
    liver's body 1.43x faster by its mean step mixed); "" otherwise (no law, a fixed Newton budget,
    or a file exported so already)."""
    step = geometry.get("step_settings") or {}
    if not law_iterates(step):
        return ""
    missing = [what for what, off in (("its tangent kept", step.get("law_tangent") != "kept"),
                                      ("its updates line-searched", not step.get("law_search")),
                                      ("its chord updates Anderson-mixed", not step.get("law_anderson"))) if off]
    if not missing:
        return ""
    return (f"{model_path} steps its law to a tolerance without {' or '.join(missing)}: export it again "
            f"(thermognn export), which serves it so (the bunny's body 5x faster under the sim press, no step "
            f"cut after a release; since session 102 the liver's 1.4x faster by its mean step), unless "
            f"rollout.prior_tangent=fresh, rollout.prior_line_search=0 or rollout.prior_anderson=0 was meant")


def _print_summary(summary: dict) -> None:
    from rich.console import Console
    from rich.table import Table
    table = Table(title="serve summary", show_header=False)
    for key, value in summary.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    Console().print(table)
