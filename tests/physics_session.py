"""serve's physics process run in the test's own process on an exported model, the tool held
still (test_serve, test_pipeline)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from thermognn.serve import protocol as P
from thermognn.serve.contact import SurfaceContact
from thermognn.serve.shm import VersionedBuffer


class Recorder:
    """The exported module with a hand on the session (in this process): records every force
    model published before a step and requests a stop after ``steps`` physics steps, however many
    model calls a step makes (``implicit``: the session's serve.contact_coupling, whose trials call
    the model several times a step; the explicit one's finite-difference step calls it after one)."""

    def __init__(self, module, shared, steps: int, slow_calls: int = 0, slow_s: float = 0.0,
                 implicit: bool = True) -> None:
        self.module, self.z0, self.dt = module, module.z0, module.dt
        self.slow_calls, self.slow_s, self.calls = slow_calls, slow_s, 0   # a slow warm-up, if asked
        self.control = shared["control"]
        self.buf = VersionedBuffer(shared["model"], P.MODEL_PAYLOAD)
        self.payload = np.zeros(P.MODEL_PAYLOAD)
        self.published: list[np.ndarray] = []
        self.steps, self.implicit = steps, implicit

    def __getattr__(self, name: str):
        """The module's own attributes (``core``: a law prior's step counts, ``law_step_counts``)."""
        if name == "module":
            raise AttributeError(name)
        return getattr(self.module, name)

    def collect(self) -> None:
        """Record the force model published last, if it is new."""
        if self.buf.read(self.payload) and (not self.published
                                            or self.payload[P.M_VERSION] != self.published[-1][P.M_VERSION]):
            self.published.append(self.payload.copy())

    def __call__(self, z, f):
        self.collect()
        if (self.control[P.C_STEPS] >= self.steps - 1 if self.implicit    # this is the last step
                else len(self.published) >= self.steps):
            P.request_stop(self.control, "duration")
        self.calls += 1
        if self.calls <= self.slow_calls:
            time.sleep(self.slow_s)
        return self.module(z, f)


def run_physics_here(model: Path, steps: int, tool_x, slow=(0, 0.0), **params):
    """run_physics on the exported model in this process, the tool held at ``tool_x``, with the graph
    executor's optimisation off as serve's physics process runs it (``physics_main``; on, the
    profiling executor's one-off re-optimisation of a law prior's step takes about 40 s here):
    (summary, payloads)."""
    from thermognn.core.state import StateLayout
    from thermognn.serve.physics import load_exported, run_physics
    module, meta, buffers = load_exported(model)
    contact = SurfaceContact(buffers["reference_positions"], buffers["node_type"], buffers["surface_faces"],
                             0.003, 300.0, 0.006)
    shared = P.make_shared(16)
    try:
        tool = np.zeros(P.TOOL_PAYLOAD)
        tool[P.T_X] = tool_x
        VersionedBuffer(shared["tool"], P.TOOL_PAYLOAD).publish(tool)
        recorder = Recorder(module, shared, steps, *slow,
                            implicit=params.get("contact_coupling", "implicit") == "implicit")
        layout = StateLayout.from_json(meta["state_layout"])
        params = {"stale_ms": 50.0, "model": str(model), **params}
        if "v" in layout.names:                              # as physics_main passes them
            params["velocity"] = layout.slice("v")
        import torch
        with torch.jit.optimized_execution(False):           # as serve's physics process steps it
            summary = run_physics(params, recorder, layout.slice("q"), contact, shared)
        recorder.collect()
    finally:
        shared.close()
    return summary, np.array(recorder.published)
