"""The tool's contact load found at the end of the body's step (implicit penalty coupling; numpy only).

Found at the body's surface *before* a step and applied over it (explicit coupling), the penalty
load lags the surface by a step: on an undamped body it does positive work every cycle
(``benchmarks/contact_lag.py``). Under the sim device's press the shipped shell (20 g, undamped,
Δt = 5 ms) chattered between 0 and 2.4 N from step to step, left its law's states at step 143 and
was crushed (docs/accuracy.md, sessions 97-98). Here the load is the one the tool exerts on the
surface the step ends at. Along the contact's nodal pattern P [N, 3] (1/N: the loads a 1 N
contact force shares out, ``SurfaceContact.loads`` over |force|) its magnitude f [N] solves

    g(f) = f - |f_c(q_{n+1}(f))| = 0,      f_c(q) = k_c (r - s(q))⁺ n   (``SurfaceContact``)

with q_{n+1}(f) the body's positions after one step with the load f P. g(0) <= 0, and g grows
with f at a rate g' = 1 + k_c c_b >= 1 (c_b [m/N]: how far the surface yields over one step per
newton of load), so the root lies in [0, |f_c(q_{n+1}(0))|]. Each trial is one step of the model
itself: the first at the previous step's load (``guess``; the load varies little from step to
step) or, without one, at f = k_c (r - s_n) / g' (the root where the surface has no motion of its
own over the step, g' the previous call's slope; never the larger load found before the step,
which the body would overshoot), then secant updates kept inside the bracket found so far (else
bisection), until |g| <= rtol f + atol or ``max_steps`` steps; the step taken is the trial with
the smallest |g|. A tool that meets a surface still out of reach takes one step (no load), as does
a press on a body at rest; a body moving under the tool takes about two (the shell, the liver and
the bunny under the sim press: 1.5-1.7 a step over a press, the steps out of reach included).
The slope g' measured over two trials also gives the body's stiffness over the step,
k_b = 1 / c_b = k_c / (g' - 1) [N/m], and the series scale of the contact stiffness,
k_eff / k_c = 1 / g' (``contact.series_stiffness``), without the extra finite-difference step
the explicit coupling needs for it. The force the user feels is still the tool's penalty against
the surface as it is before each step (serve publishes it before the step, as it did).

The pattern is the contact's at the start of the step (or, with no contact there, at the end of
the unloaded step): the tool's point on the surface moves little in one step, and the step stays
one model call per trial. :class:`ContactCoupling` carries the slope, the previous load and the
counts from step to step, for serve's physics process and ``lockstep.press_rollout`` alike (and
applies the explicit coupling's load).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .contact import ContactResult, SurfaceContact

#: serve.contact_coupling values
COUPLINGS = ("implicit", "explicit")


@dataclass
class CoupledStep:
    """One body step with the tool's contact load found at its end (:func:`implicit_contact_step`)."""

    z: Any                   # the body's state after the step (what ``step`` returned for the chosen load)
    contact: ContactResult   # the tool's contact with the surface the step ends at
    loads: np.ndarray        # [N, 3] N: the nodal load the step took (its sum: minus its reaction on the tool)
    magnitude: float         # f [N]: the load's magnitude
    residual: float          # g(f) [N]: the load less the contact force it ends at (0: consistent)
    steps: int               # model steps taken (trials)
    chosen: int              # which of them (0-based) is the step taken
    slope: float             # g' = 1 + k_c c_b (>= 1) seen over the trials, else the one passed in
    measured: bool = False   # whether ``slope`` was seen over this step's trials (two with g' >= 1)

    def converged(self, rtol: float, atol: float) -> bool:
        """Whether |g| <= rtol f + atol."""
        return abs(self.residual) <= rtol * self.magnitude + atol


def implicit_contact_step(step: Callable[[Any, np.ndarray], Any], positions: Callable[[Any], np.ndarray], z: Any,
                          x: np.ndarray, contact: SurfaceContact, slope: float = 2.0, rtol: float = 0.01,
                          atol: float = 1e-4, max_steps: int = 4, guess: float | None = None,
                          begun: tuple[ContactResult, np.ndarray] | None = None) -> CoupledStep:
    """Step the body ``z`` once with the tool centred at ``x`` [3] m pressing the surface the step ends at.

    ``step(z, loads)`` is one model step with nodal loads [N, 3] N; ``positions(z)`` the state's
    positions [N, 3] m; ``contact`` the tool's :class:`SurfaceContact`; ``slope`` the first
    secant's g' (>= 1; the previous call's ``CoupledStep.slope``); ``rtol``, ``atol`` [N] the
    tolerance on g; ``max_steps`` (>= 1) the most trials; ``guess`` [N] the first trial's load where
    the tool presses at the start (the previous call's ``magnitude``; None or 0: f_start / slope);
    ``begun`` the contact at the start and its nodal loads [N, 3] N where the caller has found them
    (``contact(x, positions(z))`` and a copy of ``contact.loads``; None: found here).
    See the module docstring.
    """
    if max_steps < 1:
        raise ValueError(f"max_steps = {max_steps}, expected >= 1")
    slope = max(float(slope), 1.0) if np.isfinite(slope) else 2.0
    if begun is None:
        begun = contact(x, positions(z)), contact.loads.copy()
    start, start_loads = begun
    zero = np.zeros_like(start_loads)
    trials: list[tuple[float, float, Any, ContactResult]] = []          # (f, g, z, contact at the end)

    def trial(f: float) -> bool:
        """One step with the load f [N]; False where it left positions that are not finite."""
        z1 = step(z, f * pattern if f > 0.0 else zero)
        q1 = positions(z1)
        if not np.isfinite(q1).all():                                   # the caller sees the state
            trials.append((f, np.inf, z1, start))
            return False
        res = contact(x, q1)
        trials.append((f, f - float(np.linalg.norm(res.force)), z1, res))
        return True

    if start.in_contact:
        f_start = float(np.linalg.norm(start.force))                     # k_c (r - s) at the start
        pattern = start_loads / f_start                                 # [N, 3] 1/N
        f0 = f_start / slope if not guess else float(guess)   # (f_start / g': the root for a surface at rest)
    else:                                                               # the unloaded step first
        f0, pattern = 0.0, zero
    if not trial(f0):
        f, _, z1, res = trials[-1]
        return CoupledStep(z1, res, f * pattern, f, np.inf, 1, 0, slope)
    if not start.in_contact:
        res = trials[0][3]
        if not res.in_contact:                                          # out of reach at the step's end too
            return CoupledStep(trials[0][2], res, zero, 0.0, 0.0, 1, 0, slope)
        pattern = contact.loads / float(np.linalg.norm(res.force))
    measured = False
    while True:
        best = min(range(len(trials)), key=lambda i: abs(trials[i][1]))
        f_b, g_b = trials[best][:2]
        if abs(g_b) <= rtol * f_b + atol or len(trials) >= max_steps:
            break
        f1, g1 = trials[-1][:2]
        if len(trials) >= 2:
            f2, g2 = trials[-2][:2]
            if f1 != f2 and (g1 - g2) / (f1 - f2) >= 1.0:
                slope, measured = (g1 - g2) / (f1 - f2), True
        f_next = max(f1 - g1 / slope, 0.0)
        below = [f for f, g, *_ in trials if g < 0.0]                   # g(0) <= 0: 0 bounds the root below
        above = [f for f, g, *_ in trials if g > 0.0]
        lo, hi = max(below, default=0.0), min(above, default=np.inf)
        if not lo < f_next < hi:
            f_next = 0.5 * (lo + hi) if np.isfinite(hi) else max(f_next, lo)
        if any(f == f_next for f, *_ in trials):
            break
        if not trial(f_next):
            best = len(trials) - 1
            break
    if len(trials) >= 2:                                                # the last two trials' slope
        (f1, g1), (f2, g2) = trials[-1][:2], trials[-2][:2]
        if f1 != f2 and np.isfinite(g1 - g2) and (g1 - g2) / (f1 - f2) >= 1.0:
            slope, measured = (g1 - g2) / (f1 - f2), True
    f, g, z1, res = trials[best]
    return CoupledStep(z1, res, f * pattern if f > 0.0 else zero, f, g, len(trials), best, slope, measured)


class ContactCoupling:
    """The tool's contact load on a served body, step after step, as serve's physics process
    (``physics.run_physics``) and ``lockstep.press_rollout`` both apply it.

    Each body step is :meth:`begin` (the tool at x [3] m against the surface as it is: the force
    serve publishes before the step) then :meth:`step`. ``coupling`` "implicit" finds the load at
    the step's end (:func:`implicit_contact_step`, within ``rtol`` f + ``atol`` [N] in at most
    ``max_steps`` calls of ``step``), the slope g' and the load carried from step to step;
    "explicit" applies the load found at the start, one call. ``step(z, loads)`` is one model step
    with nodal loads [N, 3] N, ``positions(z)`` the state's positions [N, 3] m. Counted over the
    implicit steps: ``calls`` (model calls), ``loaded`` (steps with a load), ``unsettled`` and
    ``unsettled_max`` [N] (loaded steps whose load missed the tolerance, the largest |g|)."""

    def __init__(self, step: Callable[[Any, np.ndarray], Any], positions: Callable[[Any], np.ndarray],
                 contact: SurfaceContact, coupling: str = "implicit", rtol: float = 0.01, atol: float = 1e-4,
                 max_steps: int = 4) -> None:
        if coupling not in COUPLINGS:
            raise ValueError(f"coupling = {coupling!r}, expected one of {', '.join(COUPLINGS)}")
        self.model_step, self.positions, self.contact = step, positions, contact
        self.implicit = coupling == "implicit"
        self.rtol, self.atol, self.max_steps = float(rtol), float(atol), int(max_steps)
        self.slope, self.guess = 2.0, None           # carried between implicit steps
        self.calls = self.loaded = self.unsettled = 0
        self.unsettled_max = 0.0
        self._begun: tuple[Any, np.ndarray, ContactResult, np.ndarray] | None = None

    def begin(self, z: Any, x: np.ndarray) -> ContactResult:
        """The tool centred at ``x`` [3] m against the surface of the body ``z`` as it is: the
        start of the next :meth:`step` (its loads kept for it)."""
        res = self.contact(x, self.positions(z))
        self._begun = (z, np.array(x, dtype=float), res, self.contact.loads.copy())
        return res

    def step(self) -> CoupledStep:
        """One body step from the state :meth:`begin` saw."""
        if self._begun is None:
            raise RuntimeError("ContactCoupling.step: begin(z, x) first")
        z, x, start, loads = self._begun
        self._begun = None
        if not self.implicit:                        # the load the surface before the step met
            f = float(np.linalg.norm(start.force))
            return CoupledStep(self.model_step(z, loads), start, loads, f, float("nan"), 1, 0, self.slope)
        coupled = implicit_contact_step(self.model_step, self.positions, z, x, self.contact, self.slope, self.rtol,
                                        self.atol, self.max_steps, self.guess, (start, loads))
        self.slope, self.guess = coupled.slope, coupled.magnitude
        self.calls += coupled.steps
        if coupled.magnitude > 0.0:
            self.loaded += 1
            if not coupled.converged(self.rtol, self.atol):
                self.unsettled += 1
                self.unsettled_max = max(self.unsettled_max, abs(coupled.residual))
        return coupled

    def body_stiffness(self, coupled: CoupledStep) -> float | None:
        """The body's stiffness k_b = k_c / (g' - 1) [N/m] over an implicit step whose trials
        measured the slope (inf: g' = 1, rigid), else None."""
        if not (self.implicit and coupled.measured):
            return None
        return self.contact.k / (coupled.slope - 1.0) if coupled.slope > 1.0 else float("inf")
