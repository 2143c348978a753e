"""What a served model's force is worth: exported models pressed by the same scripted tool in body
time, side by side, each against its own deformed surface (``benchmarks/serve_accuracy.py``).

``serve`` steps the physics flat out and samples the tool wherever the wall clock has it, so two
sessions never see the same loads. Here the tool follows the sim device's path
(``thermognn.devices.sim``) at body time instead: step k reads the tool at t_k = k Δt (Δt the
model's own step), finds its contact with the model's surface (``SurfaceContact``, the physics
process's, with serve's tool radius, penalty stiffness and load radius) and steps the model with
that contact's nodal loads, as ``run_physics`` does: by default the load the surface at the step's
end meets (``thermognn.serve.coupling``), else the one the surface before the step met. What comes
out per step is what the user would feel, f_k [3] N (the penalty force on the tool against the
surface before the step, the force model serve publishes), and the body's displacement
u_k = q_k − X [N, 3] m, with the body step's time.

Two such rollouts of the same path, a served model's and a reference's (the law stepped to
convergence, say), give the force error the served step's speed costs (:func:`compare`): each
model feels the tool against its own surface, so a body that yields too little pushes back too
hard, as it would under the user's hand. Torch is imported inside the functions (the package's
haptic side never imports it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thermognn.core.errors import DataError
from thermognn.core.state import StateLayout

from .health import BodyHealth
from .passivity import PassivityController
from .coupling import COUPLINGS, ContactCoupling
from .physics import CONTACT_ATOL, CONTACT_RTOL, CONTACT_TRIALS, ModelStep, body_contact, load_exported


@dataclass
class PressRollout:
    """One exported model stepped along a scripted tool path in body time."""

    times: np.ndarray         # [T] s: body time after each step (k Δt)
    tool: np.ndarray          # [T, 3] m: tool centre the step's contact was found at
    force: np.ndarray         # [T, 3] N: contact force on the user before each step (serve's published f0)
    displacement: np.ndarray  # [T, N, 3] m: the body's displacement q − X after each step
    step_ms: np.ndarray       # [T] ms: each model call
    finite: bool              # every state finite (False: the rollout stopped where it was not)
    law_counts: np.ndarray | None = None   # [4] a law prior's Newton iterations, law steps, those not
                                           # converged, cut ones (``physics.law_step_counts``); None: none
    passivity: dict | None = None          # a law prior's ``PassivityController.stats()``; None: none
    health: dict | None = None             # a meshed body's ``BodyHealth`` after each step, each [T]:
                                           # inverted_cells, crushed_cells, smallest_volume_ratio, largest_invariant,
                                           # cells_beyond_states; None: a model without cells
    resets: int = 0                        # steps that left crushed cells, the body reset to rest after
                                           # (``body_reset``, as serve does)
    trials: np.ndarray | None = None       # [T] model steps each body step took (implicit coupling's trials;
                                           # 1 each under the explicit one)
    unsettled: int = 0                     # implicit coupling: body steps whose load missed its tolerance

    @property
    def healthy(self) -> bool:
        """Finite throughout and never a crushed or inverted cell (``thermognn.serve.health``): a
        body's rollout, not only a finite one (session 94: a destroyed liver stayed finite for 600 steps)."""
        return self.finite and (self.health is None or not np.any(self.health["crushed_cells"] > 0))

    def first_step(self, key: str) -> int | None:
        """The first step (1-based) whose ``health[key]`` (a count of cells) is not zero; None: none
        was, or no health."""
        if self.health is None:
            return None
        hit = np.flatnonzero(np.asarray(self.health[key]) > 0)
        return int(hit[0]) + 1 if len(hit) else None


def press_rollout(model: str | Path, steps: int, path: str = "press", period: float = 2.0,
                  depth: float | None = None, tool_radius: float = 0.003, contact_stiffness: float = 300.0,
                  load_radius: float = 0.006, threads: int = 1, body_passivity: bool = True,
                  body_reset: bool = True, coupling: str = "implicit", contact_rtol: float = CONTACT_RTOL,
                  contact_trials: int = CONTACT_TRIALS) -> PressRollout:
    """Step the exported ``model`` ``steps`` times with the tool of the sim device's ``path``
    (its ``period`` [s] and ``depth`` [m] below the surface, None: 20 % of the body's height) read
    at body time k Δt; the contact as ``serve``'s physics process finds it (``tool_radius`` [m],
    ``contact_stiffness`` [N/m], ``load_radius`` [m]), a law-prior body kept passive as serve keeps
    it (``body_passivity``: ``PassivityController``, its ``stats()`` in ``passivity``). A meshed
    body's health (``thermognn.serve.health.BodyHealth``) is recorded after every step (``health``)
    and, as serve does (``body_reset``), a step that leaves crushed or inverted cells sends the body
    back to rest (counted in ``resets``; its health is recorded before the reset). The contact load
    is found as serve finds it (``coupling``: "implicit", the load the surface at the step's end
    meets, within ``contact_rtol`` in at most ``contact_trials`` model steps,
    ``thermognn.serve.coupling``; "explicit", the one the surface before the step met); ``step_ms``
    is a body step's time, its trials together, and ``law_counts`` counts the steps taken, not the
    trials discarded. Steps stop at a state that is not finite."""
    import torch

    from thermognn.devices.sim import SimDevice

    if steps < 1:
        raise DataError(f"press_rollout: steps = {steps}, expected >= 1")
    if coupling not in COUPLINGS:
        raise DataError(f"press_rollout: coupling = {coupling!r}, expected one of {', '.join(COUPLINGS)}")
    torch.set_num_threads(int(threads))
    module, meta, buffers = load_exported(model)
    q_slice, contact = body_contact(model, meta, buffers, tool_radius, contact_stiffness, load_radius)
    X = buffers["reference_positions"].astype(float)                        # [N, 3] m
    device = SimDevice(path=path, period=period, depth=depth)
    device.attach_scene(X.min(axis=0), X.max(axis=0), tool_radius)         # as serve's haptic process does
    device.attach_surface(X[contact.surface_nodes], contact.surface_triangles())
    dt = float(buffers["dt"])
    z = module.z0.detach().clone()                                          # [N, D] carried state
    times, tool, force_list, disp, ms = [], [], [], [], []
    finite = True
    stepper = ModelStep(module)                                             # the model, its law counts per call
    law = np.zeros(4, dtype=np.int64) if stepper.law else None
    passive = (PassivityController(module, z, StateLayout.from_json(meta["state_layout"]).slice("v"), q_slice)
               if stepper.law and body_passivity else None)
    health = BodyHealth.of_module(module, X)
    record: dict[str, list] = {k: [] for k in ("inverted_cells", "crushed_cells", "smallest_volume_ratio",
                                               "largest_invariant", "cells_beyond_states")}
    resets, trials = 0, []
    f_prev = np.zeros_like(contact.loads)

    def positions(state) -> np.ndarray:
        return state[:, q_slice].numpy()

    coupler = ContactCoupling(stepper, positions, contact, coupling, contact_rtol, CONTACT_ATOL, contact_trials)

    with torch.jit.optimized_execution(False):                              # as run_physics steps it
        for k in range(steps):
            x = device.position_at(k * dt)
            stepper.reset()
            ts = time.perf_counter()
            force = coupler.begin(z, x).force                            # what the user feels (serve publishes it)
            coupled = coupler.step()                                     # implicit: the load the step's end meets
            z_prev, z, loads = z, coupled.z, coupled.loads
            ms.append((time.perf_counter() - ts) * 1e3)                    # the body's step alone
            trials.append(stepper.calls)
            if law is not None:
                law += stepper.counts[coupled.chosen]
            if passive is not None:
                z = passive.step(z_prev, z, f_prev, loads)
                f_prev = loads
            if not bool(torch.isfinite(z).all()):
                finite = False
                ms.pop()
                trials.pop()
                break
            times.append((k + 1) * dt)
            tool.append(x.copy())
            force_list.append(np.asarray(force, dtype=float).copy())
            disp.append(z[:, q_slice].numpy().astype(float) - X)
            if health is not None:
                h = health(z[:, q_slice].numpy())
                for key, values in record.items():
                    values.append(getattr(h, key))
                if h.destroyed and body_reset:                               # as serve's physics process
                    z = module.z0.detach().clone()                          # passive: E falls to E_0
                    resets += 1
    n = len(times)
    return PressRollout(np.asarray(times), np.asarray(tool).reshape(n, 3), np.asarray(force_list).reshape(n, 3),
                        np.asarray(disp).reshape(n, len(X), 3), np.asarray(ms), finite, law,
                        None if passive is None else passive.stats(),
                        None if health is None else {k: np.asarray(v) for k, v in record.items()}, resets,
                        np.asarray(trials, dtype=np.int64), coupler.unsettled)


def force_envelope(force: np.ndarray, steps: int) -> np.ndarray:
    """The force's envelope [T, 3] N: a centred average of ``force`` [T, 3] N over ``steps`` steps
    (odd, ≥ 3) with half weight at both ends, the mean of the two (steps − 1)-step averages about
    each step, so that a buzz alternating at every step averages out exactly; at either end of the
    path it is averaged over the steps there are."""
    if steps < 3 or steps % 2 == 0:
        raise DataError(f"force_envelope: steps = {steps}, expected an odd number >= 3")
    window = np.ones(steps)
    window[[0, -1]] = 0.5                                                   # [steps]: 1/2, 1, ..., 1, 1/2
    T, h = len(force), steps // 2
    if T == 0:
        return force.astype(float)

    def centred(x: np.ndarray) -> np.ndarray:                               # [T] the window about each step
        return np.convolve(x, window)[h:h + T]

    weight = centred(np.ones(T))                                            # [T] the window's weight there
    return np.stack([centred(force[:, i]) / weight for i in range(force.shape[1])], axis=1).reshape(T, -1)


def compare(rollout: PressRollout, reference: PressRollout, envelope_steps: int = 5) -> dict:
    """Errors of ``rollout`` against ``reference`` over the steps both took (whole-rollout ratios,
    as ``evaluate``'s): ``force`` ‖f − f_ref‖ / ‖f_ref‖ over all steps, ``peak_force`` the largest
    |f − f_ref| [N] with the reference's largest |f_ref| [N] beside it, ``displacement``
    ‖u − u_ref‖ / ‖u_ref‖ over all steps and nodes; ``steps`` compared, whether ``rollout``
    stopped early (``finite``), and its body's health (``PressRollout.healthy``: never a crushed or
    inverted cell; ``resets``; ``first_beyond_states``, the first step a cell left its law's
    training states, None: none did or no law box). ``force_magnitude`` is ``force``'s ratio for
    |f| alone: how hard, not which way (the contact's normal turns from facet to facet of a coarse
    surface).

    The force also split in two (:func:`force_envelope`, a centred average over ``envelope_steps``
    steps: 5 at 20 ms spans 80 ms): ``force_envelope``, the envelopes' ratio as ``force``, what the
    hand feels as the press's shape; and ``force_jitter`` (``reference_jitter``), each rollout's own
    step-to-step part ‖f − env(f)‖ / ‖env(f)‖, felt as a buzz at the step rate. A body ringing under
    the tool (an undamped scene's stiff modes) jitters at every time step, in a phase no finer step
    pins down, so ``force`` between two time steps can stay large where the envelopes agree."""
    n = min(len(rollout.times), len(reference.times))
    df = rollout.force[:n] - reference.force[:n]                            # [n, 3] N
    du = rollout.displacement[:n] - reference.displacement[:n]              # [n, N, 3] m
    f_ref = float(np.linalg.norm(reference.force[:n]))
    u_ref = float(np.linalg.norm(reference.displacement[:n]))

    def ratio(a: float, b: float) -> float:
        return a / b if b > 0 else float("nan")

    env, env_ref = (force_envelope(r.force[:n], envelope_steps) for r in (rollout, reference))    # [n, 3] N
    return {"steps": n, "finite": bool(rollout.finite and n == len(reference.times)),
            "healthy": rollout.healthy, "resets": rollout.resets,
            "first_beyond_states": rollout.first_step("cells_beyond_states"),
            "force": ratio(float(np.linalg.norm(df)), f_ref),
            "peak_force_error_N": float(np.linalg.norm(df, axis=1).max()) if n else float("nan"),
            "peak_force_N": float(np.linalg.norm(reference.force[:n], axis=1).max()) if n else float("nan"),
            "displacement": ratio(float(np.linalg.norm(du)), u_ref),
            "force_magnitude": ratio(float(np.linalg.norm(np.linalg.norm(rollout.force[:n], axis=1)
                                                          - np.linalg.norm(reference.force[:n], axis=1))), f_ref),
            "force_envelope": ratio(float(np.linalg.norm(env - env_ref)), float(np.linalg.norm(env_ref))),
            "force_jitter": ratio(float(np.linalg.norm(rollout.force[:n] - env)), float(np.linalg.norm(env))),
            "reference_jitter": ratio(float(np.linalg.norm(reference.force[:n] - env_ref)),
                                      float(np.linalg.norm(env_ref)))}
