"""The PHYSICS process: loads the exported TorchScript model and steps the body flat out.

Every step: read the tool state (seqlock buffer), compute the contact with the current surface
(``thermognn.serve.contact``, numpy), publish the local force model (f0 at x0, K = df/dx) for
the haptic loop, then advance the state ``z = model(z, f)`` with the nodal contact load f [N, 3]
the tool exerts on the surface the step ends at (secant trials of the model,
``thermognn.serve.coupling``; with ``serve.contact_coupling=explicit`` the load at the surface
before the step). Not under no_grad: the model uses autograd. NaN/Inf in z stops the session
("physics_nan"). K is the contact spring in series with the body's own stiffness, measured on
the trials (explicit: by finite differences on the model; see ``run_physics``). torch is
imported here only, inside the process.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np

from thermognn.core.errors import DataError
from thermognn.core.state import StateLayout, describe_step, describe_time_error

from . import protocol as P
from .contact import SurfaceContact, normal_compliance, series_stiffness
from .coupling import ContactCoupling
from .health import BodyHealth, beyond_states_warning, destroyed_warning
from .passivity import PassivityController
from .shm import SharedArrays, VersionedBuffer

FORMAT = "thermognn-model/1"
FD_EPS = 0.1                 # relative load perturbation of the body-stiffness finite difference
TIMING_WINDOW = 4096         # step times kept for the medians (the latest ones)
WARMUP_STEPS = (3, 10)       # steps (1-based) whose median step time the first glitch check uses
RECHECK_STEPS = 50           # then the check again every this many steps, on the latest ones' median
STALE_MARGIN = 0.8           # warn when a publish gap exceeds this fraction of serve.stale_ms
CONTACT_RTOL = 0.01          # serve.contact_rtol's default: the coupled load's relative tolerance
CONTACT_ATOL = 1e-4          # [N] and its absolute one
CONTACT_TRIALS = 4           # serve.contact_trials's default: the most model steps a coupled step tries
BUFFERS = ("reference_positions", "z0", "edge_index", "node_type", "surface_faces", "dt")


def load_exported(path: str | Path):
    """(module, meta dict, buffers dict of numpy arrays) of an exported model; DataError if it breaks the contract."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise DataError(f"paths.exported: model file '{path}' not found (run `thermognn export` first)")
    extra = {"thermognn.json": ""}
    try:
        module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
    except Exception as exc:  # noqa: BLE001 - torch raises RuntimeError of many kinds
        raise DataError(f"paths.exported: '{path}' is not a TorchScript model ({str(exc).splitlines()[0]})") from None
    try:
        meta = json.loads(extra["thermognn.json"] or "{}")
    except json.JSONDecodeError:
        raise DataError(f"paths.exported: '{path}' has unreadable thermognn.json metadata") from None
    if meta.get("format") != FORMAT:
        raise DataError(f"paths.exported: '{path}' metadata format = {meta.get('format')!r}, expected '{FORMAT}'")
    named = dict(module.named_buffers())
    missing = [b for b in BUFFERS if b not in named]
    if missing:
        raise DataError(f"paths.exported: '{path}' lacks buffers {missing}")
    buffers = {k: named[k].detach().cpu().numpy() for k in BUFFERS}
    return module, meta, buffers


def body_contact(path: str | Path, meta: dict, buffers: dict, tool_radius: float, contact_stiffness: float,
                 load_radius: float) -> tuple[slice, SurfaceContact]:
    """The exported model's (at ``path``) q columns of its state and the tool's contact with its
    surface (``tool_radius`` [m], ``contact_stiffness`` [N/m], ``load_radius`` [m]); DataError
    without a state layout."""
    try:
        q_slice = StateLayout.from_json(meta["state_layout"]).slice("q")
    except (KeyError, TypeError, ValueError):
        raise DataError(f"paths.exported: '{path}' metadata lacks a state_layout with 'q'") from None
    return q_slice, SurfaceContact(buffers["reference_positions"], buffers["node_type"], buffers["surface_faces"],
                                   tool_radius, contact_stiffness, load_radius)


def model_geometry(buffers: dict, meta: dict, contact: SurfaceContact) -> dict:
    """What the main and haptic processes need to know about the body (plain Python); the surface
    is the contact's: its nodes' reference positions and its triangles as indices into them."""
    X = buffers["reference_positions"].astype(float)
    surface = X[np.asarray(contact.surface_nodes, dtype=np.int64)]          # [M, 3] m
    return {"ok": True, "n_nodes": int(X.shape[0]), "lo": X.min(axis=0).tolist(), "hi": X.max(axis=0).tolist(),
            "surface": surface.tolist(), "surface_faces": contact.surface_triangles().tolist(),
            "dt": float(buffers["dt"]), "n_faces": int(len(buffers["surface_faces"])),
            "scene": meta.get("scene"), "state_layout": meta.get("state_layout"), "step": describe_step(meta.get("step")),
            "step_settings": meta.get("step") if isinstance(meta.get("step"), dict) else None,
            "data_time_error": describe_time_error(meta.get("data_time_error"))}


def physics_main(params: dict, conn) -> None:
    """Entry point of the physics process (multiprocessing target)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    shared = SharedArrays.attach(params["shm"])
    control = shared["control"]
    summary: dict = {"error": None, "steps": 0}
    try:
        import torch
        torch.set_num_threads(int(params.get("threads", 1)))
        module, meta, buffers = load_exported(params["model"])
        q_slice, contact = body_contact(params["model"], meta, buffers, params["tool_radius"],
                                        params["contact_stiffness"], params["load_radius"])
    except Exception as exc:  # noqa: BLE001 - reported to the main process as one line
        msg = str(exc) if isinstance(exc, DataError) else f"{type(exc).__name__}: {exc}"
        conn.send({"ok": False, "error": msg})
        control[P.C_PHYSICS_STATE] = 2
        shared.close()
        return
    conn.send(model_geometry(buffers, meta, contact))
    layout = StateLayout.from_json(meta["state_layout"])
    if "v" in layout.names:                              # the state's v columns (``body_passivity``)
        params = {**params, "velocity": layout.slice("v")}
    try:
        # the profiling executor's re-optimisation made scripted steps ~1.7x slower than eager here
        with torch.jit.optimized_execution(False):
            summary.update(run_physics(params, module, q_slice, contact, shared))
    except Exception as exc:  # noqa: BLE001
        P.request_stop(control, "physics_crash")
        summary["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    finally:
        control[P.C_PHYSICS_STATE] = 2
        P.send_summary(conn, summary)
        shared.close()


def law_step_counts(module) -> np.ndarray | None:
    """An exported law-prior model's step counts since it was loaded (its prior's
    ``newton_taken``): [4] int, the Newton iterations, the law's steps (two a model step with a
    network, one per sweep and the final one; one for a law alone), those that had not converged
    where their most iterations (``rollout.prior_newton_max``) ran out (with
    ``rollout.prior_step_cuts``: a cut step's sub-step at the floor), and the cut steps; None for
    any other model. A step that has not converged is taken as it stands, and its force may be
    wrong: under the sim's default liver press such a step ran the body away (docs/accuracy.md,
    session 78)."""
    prior = getattr(getattr(module, "core", None), "prior", None)
    counts = getattr(prior, "newton_taken", None)
    return None if counts is None else np.asarray(counts.detach().numpy(), dtype=np.int64).copy()


class ModelStep:
    """The exported model as :func:`thermognn.serve.coupling.implicit_contact_step`'s ``step``:
    ``z' = module(z, loads)`` with nodal loads [N, 3] N as numpy, and a law prior's step counts
    (``law_step_counts``) of each call since the latest :meth:`reset` in ``counts`` (empty for any
    other model), so that the trials the coupling discards can be told from the step it takes;
    ``calls`` counts the calls since then."""

    def __init__(self, module) -> None:
        self.module = module
        self.law = law_step_counts(module) is not None
        self.counts: list[np.ndarray] = []
        self.calls = 0

    def reset(self) -> None:
        self.counts, self.calls = [], 0

    def __call__(self, z, loads: np.ndarray):
        import torch

        before = law_step_counts(self.module) if self.law else None
        out = self.module(z, torch.from_numpy(np.ascontiguousarray(loads)).to(z.dtype)).detach()
        self.calls += 1
        if before is not None:
            self.counts.append(law_step_counts(self.module) - before)
        return out

    def discarded(self, chosen: int) -> np.ndarray | None:
        """The law counts of every call since :meth:`reset` but the ``chosen`` one (None: not a law)."""
        if not self.law:
            return None
        total = np.sum(self.counts, axis=0) if self.counts else np.zeros(4, dtype=np.int64)
        return total - (self.counts[chosen] if self.counts else 0)


def _law_warning(unconverged: int, steps: int, step: int) -> str:
    """One line for the first law step that has not converged (``law_step_counts``)."""
    return (f"the body's law step did not converge at model step {step} ({unconverged} of {steps} law steps so "
            f"far): such a step is taken as it stands and its force may be wrong; export with more "
            f"rollout.prior_newton_max or with rollout.prior_step_cuts=4 (docs/accuracy.md, session 78)")


def run_physics(params: dict, module, q_slice: slice, contact: SurfaceContact, shared: SharedArrays) -> dict:
    """Step the model until a stop is requested; returns step statistics.

    Contact load (``contact_coupling``): "implicit" (default) finds it at the step's end,
    ``coupling.implicit_contact_step`` within ``contact_rtol`` in at most ``contact_trials`` model
    calls, the slope g' carried from step to step; the trials it discards are left out of the law
    counts below and a step's time counts them all. "explicit" applies the load at the surface
    before the step. Either way the force model is published before the step: the tool's penalty
    against the surface as it is (published after a slow step, x0 would be the tool of long ago and
    f0 + K (x - x0) would be extrapolated far: the liver in real time felt at most 0.1 N). The
    summary's ``contact_coupling``,
    ``contact_steps`` (loaded steps), ``contact_trials_per_step``, ``contact_unsettled_steps`` and
    ``contact_unsettled_max_N`` (loaded steps whose load missed the tolerance; the largest |g|).

    Published stiffness: the contact spring k_c = ``contact_stiffness`` [N/m] in series with the
    body, K = -k_eff n n^T, k_eff = k_c k_b / (k_c + k_b) (``contact.series_stiffness``). The
    body's local stiffness k_b [N/m] over one physics step comes, under the implicit coupling, from
    the trials' slope, k_b = k_c / (g' - 1), on every loaded step that took two or more; under the
    explicit one from finite differences on the model: every ``body_stiffness_every`` contact
    steps (0: off, K = contact stiffness only; the first contact step always), one extra step from
    the same z with the nodal loads scaled by (1 + FD_EPS); k_b = FD_EPS |f| / du with du the
    load-weighted inward normal displacement difference of the loaded nodes
    (``contact.normal_compliance``, du <= 0 or not finite: rigid). The perturbed step is
    discarded; its k_b applies from the next publish on and is kept until the next evaluation or
    the loss of contact.

    Glitch check, first after steps 3..10 (the first ones include warm-up; no FD step before
    it), then every RECHECK_STEPS steps on the median of the latest RECHECK_STEPS step times: an
    FD step delays the next published force model by one more model step, so FD stays off while
    two model steps would exceed 0.8 * ``stale_ms`` (the watchdog would fade the force): the
    stiffness is never bought with a glitch. ``fd_disabled`` in the summary says why while it is
    off ("" once a later check finds the steps fast enough again, e.g. after a slow warm-up),
    ``fd_off_checks`` counts the checks that held it off. If one step alone exceeds the margin
    at the first check, a one-line warning goes to stderr (prefix 'thermognn serve: warning:')
    and into the summary.

    A law-prior body is kept passive (``body_passivity``, :class:`PassivityController`, on the
    state's v columns ``params["velocity"]``): where it would give back more energy than the tool
    put in, the excess leaves its kinetic energy;
    ``passivity_steps`` and ``passivity_removed_J`` in the summary say how often and how much.

    A law-prior model's steps are counted (``law_step_counts``, FD steps and discarded trials left out):
    ``law_steps``, ``law_unconverged_steps``, ``law_cut_steps`` and ``law_iterations`` in the
    summary; the first law step that has not converged puts a one-line warning on stderr and in
    ``law_warning``.

    A body that carries its mesh (a law prior) has its health checked after every step
    (``thermognn.serve.health.BodyHealth``, ~2 ms on the liver's 1493 cells): the first step that
    takes a cell beyond its learned law's training states puts a one-line warning on stderr and in
    ``body_warning``; a step that leaves crushed or inverted cells (J = det F at most 1 %: a
    destroyed body, though finite) sends the body back to rest where ``body_reset`` (on by default;
    the first such step warns), else is served as it is with the warning. The summary's
    ``body_largest_invariant`` (the largest scaled invariant of any cell, 1 at the edge of the law's
    states; nan for the scene's own law), ``body_steps_beyond_states``, ``body_destroyed_steps``,
    ``body_resets`` and ``body_smallest_volume_ratio`` say how it went.
    """
    import torch

    control = shared["control"]
    model_buf = VersionedBuffer(shared["model"], P.MODEL_PAYLOAD)
    tool_buf = VersionedBuffer(shared["tool"], P.TOOL_PAYLOAD)
    z = module.z0.detach().clone()                       # [N, D]
    dtype = z.dtype
    dt = float(module.dt)
    realtime = bool(params.get("realtime", False))
    every = int(params.get("body_stiffness_every", 0))
    k_c = float(contact.k)
    tool = np.zeros(P.TOOL_PAYLOAD)
    far = contact.hi + 10.0                              # no tool yet: far above the body
    tool[P.T_X] = far
    payload = np.zeros(P.MODEL_PAYLOAD)
    step = 0
    t0 = time.perf_counter()
    control[P.C_PHYSICS_T0] = t0
    control[P.C_PHYSICS_STATE] = 1
    step_time = 0.0
    times = np.zeros(TIMING_WINDOW)                      # latest body step times [s] (a step's trials together)
    fd_times = np.zeros(TIMING_WINDOW)                   # latest FD step times [s]
    n_fd = 0                                             # FD evaluations
    k_body: float | None = None                          # latest body stiffness [N/m] (None: not measured)
    since_fd = 0                                         # contact steps since the latest FD evaluation
    k_body_sum, n_k_body, n_rigid = 0.0, 0, 0
    scale_sum, n_scale = 0.0, 0
    warning = ""
    fd_disabled = ""                                     # why FD is off ("" while allowed)
    fd_off_checks = 0                                    # glitch checks that held FD off
    parent = os.getppid()
    law_base = law_step_counts(module)                   # None: not a law prior
    law_now = law_base
    law_fd = None if law_base is None else np.zeros_like(law_base)   # what FD steps and discarded trials added
    law_warning = ""
    passive = None                                       # the body kept passive (law priors: passivity.py)
    if law_base is not None and params.get("body_passivity", True):
        passive = PassivityController(module, z, params["velocity"], q_slice)
    f_prev = np.zeros_like(contact.loads)
    stepper = ModelStep(module)

    def positions(state) -> np.ndarray:
        return state[:, q_slice].numpy()

    coupling = ContactCoupling(stepper, positions, contact, params.get("contact_coupling", "implicit"),
                               float(params.get("contact_rtol", CONTACT_RTOL)), CONTACT_ATOL,
                               int(params.get("contact_trials", CONTACT_TRIALS)))
    implicit = coupling.implicit

    health = BodyHealth.of_module(module, module.reference_positions.detach().cpu().numpy())   # None: no cells
    reset = bool(params.get("body_reset", True))
    body = {"largest": 0.0, "smallest_j": 1.0, "beyond": 0, "destroyed": 0, "resets": 0, "warning": ""}

    def body_stats() -> dict:
        if health is None:
            return {}
        return {"body_largest_invariant": body["largest"] if health.scales is not None else float("nan"),
                "body_smallest_volume_ratio": body["smallest_j"],
                "body_steps_beyond_states": body["beyond"], "body_destroyed_steps": body["destroyed"],
                "body_resets": body["resets"], "body_warning": body["warning"]}

    def body_warn(line: str) -> None:
        body["warning"] = f"{body['warning']}; {line}" if body["warning"] else line
        print(f"thermognn serve: warning: {line}", file=sys.stderr, flush=True)

    def law_stats() -> dict:
        if law_base is None:
            return {}
        n = law_now - law_base - law_fd
        return {"law_iterations": int(n[0]), "law_steps": int(n[1]), "law_unconverged_steps": int(n[2]),
                "law_cut_steps": int(n[3]), "law_warning": law_warning}

    def stats() -> dict:
        n_t, n_f = min(step, TIMING_WINDOW), min(n_fd, TIMING_WINDOW)
        return {"step_ms": float(np.median(times[:n_t]) * 1e3) if n_t else float("nan"),
                "fd_ms": float(np.median(fd_times[:n_f]) * 1e3) if n_f else float("nan"),
                "fd_evaluations": n_fd, "fd_rigid": n_rigid,
                "body_stiffness_mean_N_per_m": k_body_sum / n_k_body if n_k_body else float("nan"),
                "k_scale_mean": scale_sum / n_scale if n_scale else float("nan"), "warning": warning,
                "fd_disabled": fd_disabled, "fd_off_checks": fd_off_checks,
                "contact_coupling": "implicit" if implicit else "explicit",
                "contact_trials_per_step": coupling.calls / step if implicit and step else float("nan"),
                "contact_unsettled_steps": coupling.unsettled, "contact_unsettled_max_N": coupling.unsettled_max,
                "contact_steps": coupling.loaded, **law_stats(), **body_stats(),
                **({} if passive is None else passive.stats())}

    while control[P.C_STOP] == 0:
        if step % 100 == 0 and os.getppid() != parent:     # main process killed: stop on our own
            P.request_stop(control, "main_gone")
            break
        tool_buf.read(tool)
        x = tool[P.T_X]
        z_prev = z
        res = coupling.begin(z_prev, x)                  # the tool against the surface now
        f_mag = float(np.linalg.norm(res.force))
        pressing = res.in_contact and f_mag > 0.0
        if not pressing:
            k_body, since_fd = None, 0                   # contact lost: measure afresh next time
        scale = 1.0 if k_body is None else series_stiffness(k_c, k_body) / k_c   # k_b / (k_c + k_b)
        if pressing:
            scale_sum += scale
            n_scale += 1
        payload[P.M_VERSION] = step + 1
        payload[P.M_STEP] = step
        payload[P.M_TIME] = time.perf_counter()
        payload[P.M_F0] = res.force
        payload[P.M_X0] = x
        payload[P.M_K] = (scale * res.stiffness).reshape(-1)
        payload[P.M_CONTACT] = 1.0 if res.in_contact else 0.0
        payload[P.M_DEPTH] = res.depth
        model_buf.publish(payload)

        stepper.reset()
        ts = time.perf_counter()
        coupled = coupling.step()                        # implicit: the load the surface at the step's end meets
        elapsed = time.perf_counter() - ts
        z, loads = coupled.z, coupled.loads
        measured = coupling.body_stiffness(coupled)
        if measured is not None and coupled.magnitude > 0.0 and pressing:   # from the next publish on
            k_body = measured
            if np.isfinite(k_body):
                k_body_sum += k_body
                n_k_body += 1
            else:
                n_rigid += 1
        if law_base is not None:                         # the discarded trials' counts are not the body's
            law_fd += stepper.discarded(coupled.chosen)
        step_time += elapsed
        times[step % TIMING_WINDOW] = elapsed
        if not bool(torch.isfinite(z).all()):
            P.request_stop(control, "physics_nan")
            return {"steps": step, "nan_at_step": step + 1, "elapsed_s": time.perf_counter() - t0,
                    "model_time_s": step_time, **stats()}
        if passive is not None:                           # never more energy out than the tool put in
            z = passive.step(z_prev, z, f_prev, loads)
            f_prev = loads
        step += 1
        if health is not None:                            # cells still cells, within the law's states
            h = health(z[:, q_slice].numpy())
            if np.isfinite(h.largest_invariant):
                body["largest"] = max(body["largest"], h.largest_invariant)
            body["smallest_j"] = min(body["smallest_j"], h.smallest_volume_ratio)
            if h.cells_beyond_states:
                if not body["beyond"]:
                    body_warn(beyond_states_warning(h, step, health.guard_margin, health.hht))
                body["beyond"] += 1
            if h.destroyed:
                if not body["destroyed"]:
                    body_warn(destroyed_warning(h, step, reset))
                body["destroyed"] += 1
                if reset:                                 # passive: the body's energy falls to E_0
                    z = module.z0.detach().clone()
                    body["resets"] += 1
        control[P.C_STEPS] = step
        control[P.C_PHYSICS_T] = time.perf_counter()
        if law_base is not None:
            law_now = law_step_counts(module)
            counted = law_now - law_base - law_fd                 # the body's own steps so far
            if counted[2] and not law_warning:
                law_warning = _law_warning(int(counted[2]), int(counted[1]), step)
                print(f"thermognn serve: warning: {law_warning}", file=sys.stderr, flush=True)

        if pressing and every > 0 and step > WARMUP_STEPS[1] and not fd_disabled and not implicit:
            since_fd += 1
            if k_body is None or since_fd >= every:      # body stiffness by finite differences
                ts = time.perf_counter()
                z_pert = module(z_prev, torch.from_numpy(loads).to(dtype) * (1.0 + FD_EPS)).detach()
                fd_times[n_fd % TIMING_WINDOW] = time.perf_counter() - ts
                if law_base is not None:                 # the discarded step's counts are not the body's
                    after = law_step_counts(module)
                    law_fd += after - law_now
                    law_now = after
                n_fd += 1
                since_fd = 0
                du = normal_compliance(z[:, q_slice].numpy(), z_pert[:, q_slice].numpy(), loads, res.normal)
                if np.isfinite(du) and du > 0.0:
                    k_body = FD_EPS * f_mag / du
                    k_body_sum += k_body
                    n_k_body += 1
                else:
                    k_body = float("inf")                # no measurable yield: rigid
                    n_rigid += 1

        if step >= WARMUP_STEPS[1] and (step - WARMUP_STEPS[1]) % RECHECK_STEPS == 0:   # step-time check
            first = step == WARMUP_STEPS[1]              # median of steps 3..10, later of the latest 50
            window = WARMUP_STEPS[1] - WARMUP_STEPS[0] + 1 if first else RECHECK_STEPS
            step_ms = float(np.median(times[[(step - 1 - i) % TIMING_WINDOW for i in range(window)]])) * 1e3
            if first:
                warning = _step_time_warning(params, step_ms)
                if warning:
                    print(f"thermognn serve: warning: {warning}", file=sys.stderr, flush=True)
            limit_ms = STALE_MARGIN * float(params["stale_ms"])
            fd_disabled = ""
            if every > 0 and not implicit and 2.0 * step_ms > limit_ms:
                fd_off_checks += 1
                fd_disabled = (f"a model step takes {step_ms:.1f} ms: with a finite-difference step the gap "
                               f"between force models would pass {limit_ms:.0f} ms (0.8 serve.stale_ms)")
        if realtime:                                     # pace to the model's dt (else: flat out)
            wait = t0 + step * dt - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
    return {"steps": step, "elapsed_s": time.perf_counter() - t0, "model_time_s": step_time, **stats()}


def _step_time_warning(params: dict, step_ms: float) -> str:
    """One line when a model step [ms] (the gap between published force models) comes near
    serve.stale_ms, where the watchdog fades the force; "" otherwise."""
    stale_ms = float(params["stale_ms"])
    if not step_ms > STALE_MARGIN * stale_ms:
        return ""
    return (f"model '{params.get('model', '?')}' steps in {step_ms:.1f} ms with {int(params.get('threads', 1))} "
            f"thread(s), near serve.stale_ms = {stale_ms:g} ms where the watchdog fades the force: it may fade "
            f"repeatedly; remedies: a smaller model (e.g. model.hidden=32, then re-train and export), more "
            f"serve.physics_threads, or a larger serve.stale_ms")
