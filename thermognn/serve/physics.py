"""The PHYSICS process: loads the exported TorchScript model and steps the body flat out.

Every step: read the tool state (seqlock buffer), compute the contact with the current surface
(``thermognn.serve.contact``, numpy), publish the local force model (f0 at x0, K = df/dx) for
the haptic loop, then advance the state ``z = model(z, f)`` with the nodal contact load f
[N, 3] (not under no_grad: the model uses autograd). NaN/Inf in z stops the session
("physics_nan"). torch is imported here only, inside the process.
"""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import numpy as np

from thermognn.core.errors import DataError
from thermognn.core.state import StateLayout

from . import protocol as P
from .contact import SurfaceContact
from .shm import SharedArrays, VersionedBuffer

FORMAT = "thermognn-model/1"
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


def model_geometry(buffers: dict, meta: dict) -> dict:
    """What the main and haptic processes need to know about the body (plain Python)."""
    X = buffers["reference_positions"].astype(float)
    return {"ok": True, "n_nodes": int(X.shape[0]), "lo": X.min(axis=0).tolist(), "hi": X.max(axis=0).tolist(),
            "dt": float(buffers["dt"]), "n_faces": int(len(buffers["surface_faces"])),
            "scene": meta.get("scene"), "state_layout": meta.get("state_layout")}


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
        try:
            q_slice = StateLayout.from_json(meta["state_layout"]).slice("q")
        except (KeyError, TypeError, ValueError):
            raise DataError(f"paths.exported: '{params['model']}' metadata lacks a state_layout with 'q'") from None
        contact = SurfaceContact(buffers["reference_positions"], buffers["node_type"], buffers["surface_faces"],
                                 params["tool_radius"], params["contact_stiffness"], params["load_radius"])
    except Exception as exc:  # noqa: BLE001 - reported to the main process as one line
        msg = str(exc) if isinstance(exc, DataError) else f"{type(exc).__name__}: {exc}"
        conn.send({"ok": False, "error": msg})
        control[P.C_PHYSICS_STATE] = 2
        shared.close()
        return
    conn.send(model_geometry(buffers, meta))
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


def run_physics(params: dict, module, q_slice: slice, contact: SurfaceContact, shared: SharedArrays) -> dict:
    """Step the model until a stop is requested; returns step statistics."""
    import torch

    control = shared["control"]
    model_buf = VersionedBuffer(shared["model"], P.MODEL_PAYLOAD)
    tool_buf = VersionedBuffer(shared["tool"], P.TOOL_PAYLOAD)
    z = module.z0.detach().clone()                       # [N, D]
    dtype = z.dtype
    dt = float(module.dt)
    realtime = bool(params.get("realtime", False))
    tool = np.zeros(P.TOOL_PAYLOAD)
    far = contact.hi + 10.0                              # no tool yet: far above the body
    tool[P.T_X] = far
    payload = np.zeros(P.MODEL_PAYLOAD)
    step = 0
    t0 = time.perf_counter()
    control[P.C_PHYSICS_T0] = t0
    control[P.C_PHYSICS_STATE] = 1
    step_time = 0.0
    parent = os.getppid()
    while control[P.C_STOP] == 0:
        if step % 100 == 0 and os.getppid() != parent:     # main process killed: stop on our own
            P.request_stop(control, "main_gone")
            break
        tool_buf.read(tool)
        x = tool[P.T_X]
        q = z[:, q_slice].detach().numpy()               # [N, 3] current positions
        res = contact(x, q)
        payload[P.M_VERSION] = step + 1
        payload[P.M_STEP] = step
        payload[P.M_TIME] = time.perf_counter()
        payload[P.M_F0] = res.force
        payload[P.M_X0] = x
        payload[P.M_K] = res.stiffness.reshape(-1)
        payload[P.M_CONTACT] = 1.0 if res.in_contact else 0.0
        payload[P.M_DEPTH] = res.depth
        model_buf.publish(payload)

        f = torch.from_numpy(contact.loads).to(dtype)    # [N, 3] nodal load on the body
        ts = time.perf_counter()
        z = module(z, f).detach()
        step_time += time.perf_counter() - ts
        if not bool(torch.isfinite(z).all()):
            P.request_stop(control, "physics_nan")
            return {"steps": step, "nan_at_step": step + 1, "elapsed_s": time.perf_counter() - t0,
                    "model_time_s": step_time}
        step += 1
        control[P.C_STEPS] = step
        control[P.C_PHYSICS_T] = time.perf_counter()
        if realtime:                                     # pace to the model's dt (else: flat out)
            wait = t0 + step * dt - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
    return {"steps": step, "elapsed_s": time.perf_counter() - t0, "model_time_s": step_time}
