"""Safety chain of the haptic loop: pure classes on 3-vectors [N], testable without processes.

Order in the loop (``thermognn.serve.loop``), every tick::

    f = model force (multirate local model)          -> NaN/Inf: zero force, exit "haptic_nan"
    f *= engage.gain(|f|) * watchdog.gain(now, last)  no force until small at engage, then ramp;
                                                      stale physics -> fade to zero (and re-engage)
    clamp.apply(f)                                    peak / continuous (RMS) device limits
    passivity.apply(f, v)                             Hannaford-Ryu observer + adaptive damping
    clamp.apply_peak(f); rate.apply(f)                no tick changes the force by more than the
    passivity.commit(f, v)                            device impulse limit; observer books the
                                                      force actually commanded

All methods work in place on float64 arrays of shape [3] (no allocation per tick).
"""

from __future__ import annotations

import math

import numpy as np


def norm3(f: np.ndarray) -> float:
    """Euclidean norm of a 3-vector, without allocating."""
    return math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])


def clamp_norm(f: np.ndarray, limit: float) -> float:
    """Scale ``f`` [3] in place so that |f| <= ``limit``; return the factor applied (<= 1)."""
    n = norm3(f)
    if n > limit:
        s = limit / n if n > 0 else 0.0
        f *= s
        return s
    return 1.0


def limit_stiffness(K: np.ndarray, k_max: float) -> float:
    """Scale the 3x3 stiffness ``K`` [N/m] in place so its Frobenius norm (>= spectral norm) <= k_max."""
    n = float(np.sqrt(np.sum(K * K)))
    if n > k_max:
        K *= k_max / n
        return k_max / n
    return 1.0


class ForceClamp:
    """Device force limits: peak ``max_force`` [N] always; ``max_continuous`` [N] as the RMS force
    over the time constant ``tau`` [s] approaches it (motor heating)."""

    def __init__(self, max_force: float, max_continuous: float, dt: float, tau: float = 1.0) -> None:
        self.max_force = float(max_force)
        self.max_continuous = float(min(max_continuous, max_force))
        self.alpha = min(1.0, dt / tau)   # EMA weight per tick
        self.mean_square = 0.0            # [N^2]

    @property
    def rms(self) -> float:
        return math.sqrt(self.mean_square)

    @property
    def limit(self) -> float:
        """Current force limit [N]: the peak limit while the RMS force is below 90 % of the
        continuous limit, falling linearly to the continuous limit as the RMS reaches it (no
        chatter between the two)."""
        r = self.rms / self.max_continuous if self.max_continuous > 0 else 1.0
        if r <= 0.9:
            return self.max_force
        if r >= 1.0:
            return self.max_continuous
        return self.max_force + (self.max_continuous - self.max_force) * (r - 0.9) / 0.1

    def apply(self, f: np.ndarray) -> None:
        clamp_norm(f, self.limit)
        self.mean_square += self.alpha * (f[0] * f[0] + f[1] * f[1] + f[2] * f[2] - self.mean_square)

    def apply_peak(self, f: np.ndarray) -> None:
        clamp_norm(f, self.max_force)


class EngageRamp:
    """Ramp-in at engage: gain 0 until the commanded force is below ``threshold`` [N], then a
    linear ramp to 1 over ``ramp_s`` [s]. ``reset()`` disengages (e.g. after a watchdog fade)."""

    def __init__(self, dt: float, threshold: float = 0.1, ramp_s: float = 0.5) -> None:
        self.step = dt / ramp_s if ramp_s > 0 else 1.0
        self.threshold = float(threshold)
        self.engaged = False
        self.value = 0.0

    def reset(self) -> None:
        self.engaged = False
        self.value = 0.0

    def gain(self, f_cmd: float) -> float:
        """Gain for this tick given the commanded force magnitude ``f_cmd`` [N]."""
        if not self.engaged:
            if f_cmd <= self.threshold:
                self.engaged = True
            else:
                return 0.0
        if self.value < 1.0:
            self.value = min(1.0, self.value + self.step)
        return self.value


class RateLimiter:
    """No tick changes the commanded force by more than ``max_step`` [N] (device impulse limit)."""

    def __init__(self, max_step: float) -> None:
        self.max_step = float(max_step)
        self.previous = np.zeros(3)
        self._d = np.zeros(3)

    def apply(self, f: np.ndarray) -> None:
        d = self._d
        np.subtract(f, self.previous, out=d)
        clamp_norm(d, self.max_step)
        np.add(self.previous, d, out=f)
        self.previous[:] = f

    def reset(self, f: np.ndarray | None = None) -> None:
        self.previous[:] = 0.0 if f is None else f


class PassivityController:
    """Time-domain passivity observer/controller (Hannaford & Ryu 2002) for the virtual environment.

    ``energy`` [J] is the energy the environment has absorbed: E += -f.v dt with f the force on the
    user and v the tool velocity. When a tick would make it negative (the environment would have
    generated energy) the controller adds the damping force -alpha v, alpha = -E/(|v|^2 dt)
    [N s/m], capped at ``max_damping``, which dissipates exactly the excess.
    """

    def __init__(self, dt: float, max_damping: float = 5.0, v_min: float = 1e-4) -> None:
        self.dt = float(dt)
        self.max_damping = float(max_damping)
        self.v_min2 = v_min * v_min        # [m^2/s^2] below: no damping (noise)
        self.energy = 0.0                  # [J]
        self.alpha = 0.0                   # last damping [N s/m]
        self.dissipated = 0.0              # [J] total dissipated by the controller

    def apply(self, f: np.ndarray, v: np.ndarray) -> None:
        """Add damping to ``f`` [3] N in place when the observer would go active."""
        v2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        e_next = self.energy - (f[0] * v[0] + f[1] * v[1] + f[2] * v[2]) * self.dt
        self.alpha = 0.0
        if e_next < 0.0 and v2 > self.v_min2:
            self.alpha = min(-e_next / (v2 * self.dt), self.max_damping)
            for i in range(3):
                f[i] -= self.alpha * v[i]

    def commit(self, f: np.ndarray, v: np.ndarray) -> None:
        """Book the force actually commanded this tick."""
        de = -(f[0] * v[0] + f[1] * v[1] + f[2] * v[2]) * self.dt
        self.energy += de
        if self.alpha > 0.0:
            self.dissipated += self.alpha * (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) * self.dt

    def reset(self) -> None:
        self.energy = 0.0
        self.alpha = 0.0


class Watchdog:
    """Physics freshness: gain 1 while the last physics update is younger than ``stale_s`` [s];
    once stale the gain falls linearly to 0 over ``fade_s`` [s]; when updates resume it
    ramps back up at the same rate."""

    def __init__(self, stale_s: float, fade_s: float, dt: float) -> None:
        self.stale_s = float(stale_s)
        self.step = dt / fade_s if fade_s > 0 else 1.0
        self.value = 0.0          # starts faded in: nothing published yet
        self.stale = True
        self.faded = True         # reached zero (the loop re-engages the ramp-in afterwards)

    def gain(self, now: float, last_update: float) -> float:
        """``now`` and ``last_update`` in seconds on the same monotonic clock."""
        self.stale = last_update <= 0.0 or (now - last_update) > self.stale_s
        if self.stale:
            self.value = max(0.0, self.value - self.step)
        else:
            self.value = min(1.0, self.value + self.step)
        self.faded = self.value == 0.0
        return self.value


def is_finite3(f: np.ndarray) -> bool:
    """True if all three components are finite (no allocation)."""
    return math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2])
