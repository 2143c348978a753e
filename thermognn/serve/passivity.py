"""The served body kept passive: it never gives back more energy than the tool put in.

A law-prior model's exported ``energy_entropy`` is the body's own energy (docs/model.md, "The
law's energy in `evaluate`"): E = ½ vᵀ M v + Σ_e V_e (Ψ_vol + g∞ Ψ_iso) − f_body · u [J]. With the
loads' trapezoidal work W_s = Σ_k ½ (f_k−1 + f_k) · (u_k − u_k−1) [J], the energy the body has
absorbed, A_s = W_s − (E_s − E_0), dissipated or held in its Prony terms, is never negative for a
passive body. Every test rollout of the shipped learned laws keeps A >= 0 at every step (session
89). Under the sim device's press, though, Newmark's average acceleration (the FE's own rule,
energy-conserving only for a linear body) lets the liver's law ring ever louder after a release
once the tool has pressed three times (session 90: E from 1.3e-2 J to 0.56 J with the tool away,
every step converged).

:class:`PassivityController` is the time-domain passivity observer and controller of haptic
rendering (Hannaford & Ryu, 2002) on the body itself: after each step it books the step's work,
and where A has fallen below −``PASSIVITY_RTOL`` of the largest work so far (an elastic law's own
integrator drift left alone) it takes the excess out of the body's kinetic energy, scaling
the velocities (v ← s v, s² = (K − excess) / K, K = ½ vᵀ M v) so that A is zero again. Where the
body is passive (every step of the data) it never acts and the rollout is the model's, to the
bit. It uses only the exported file's ``energy_entropy`` (no torch model code, no dolfinx).
"""

from __future__ import annotations

import math

import numpy as np

#: the controller acts where A < −(PASSIVITY_RTOL × the largest |W| so far + PASSIVITY_ATOL): an
#: elastic law's own Newmark drift, which its data has too (the shell's snap-through: up to 4.4 %
#: of the work, session 89), is left alone; a runaway's is not (the liver's: A −3.8 W, session 90)
PASSIVITY_RTOL = 0.05
PASSIVITY_ATOL = 1.0e-12          # [J]


class PassivityController:
    """Keeps the carried state of an exported law-prior ``module`` passive along a served
    rollout (module docstring), from its first state z0 [N, D]: ``velocity`` and ``positions``
    are the state's v and q columns. ``step(z_prev, z, f_prev, f)`` books the step z_prev -> z
    under the nodal loads f_prev, f [N, 3] N (at its start and end) and returns z, its velocities
    scaled where the body would otherwise have given back more than it was given. ``acted`` counts
    those steps, ``removed`` [J] sums what they took out, ``absorbed`` [J] is A now."""

    def __init__(self, module, z0, velocity: slice, positions: slice) -> None:
        self.module, self.velocity, self.positions = module, velocity, positions
        self.e0 = self.energy(z0)
        self.work, self.peak = 0.0, 0.0                 # [J] the loads' work so far, its largest |W|
        self.acted, self.removed = 0, 0.0
        self.absorbed = 0.0

    def energy(self, z) -> float:
        """The body's energy E [J] of the carried state z (the exported ``energy_entropy``)."""
        return float(self.module.energy_entropy(z)[0])

    def step(self, z_prev, z, f_prev, f):
        """z after the step z_prev -> z under f_prev -> f (class docstring)."""
        dq = (z[:, self.positions] - z_prev[:, self.positions]).double().numpy()             # [N, 3] m
        self.work += float(np.sum(0.5 * (np.asarray(f_prev, dtype=float) + np.asarray(f, dtype=float)) * dq))
        self.peak = max(self.peak, abs(self.work))
        e = self.energy(z)
        excess = (e - self.e0) - self.work                                                 # −A [J]
        if excess <= PASSIVITY_RTOL * self.peak + PASSIVITY_ATOL:
            self.absorbed = -excess
            return z
        still = z.clone()
        still[:, self.velocity] = 0.0
        kinetic = e - self.energy(still)                                                    # ½ vᵀ M v [J]
        s = math.sqrt(max(kinetic - excess, 0.0) / kinetic) if kinetic > 0.0 else 0.0
        z = z.clone()
        z[:, self.velocity] *= s
        self.acted += 1
        self.removed += (1.0 - s * s) * kinetic
        self.absorbed = self.work - (e - (1.0 - s * s) * kinetic - self.e0)
        return z

    def stats(self) -> dict:
        """What ``serve``'s summary reports: steps it acted at, energy it took out [J], the loads'
        work [J] and what the body has absorbed [J]."""
        return {"passivity_steps": self.acted, "passivity_removed_J": self.removed,
                "passivity_work_J": self.work, "passivity_absorbed_J": self.absorbed}


__all__ = ["PASSIVITY_ATOL", "PASSIVITY_RTOL", "PassivityController"]
