"""Structural checks of the FE core: energy conservation, beam bending, snap-through."""

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from thermognn.generate import cases  # noqa: E402


def test_undamped_dynamics_conserves_energy():
    """Tiny clamped block (48 P1 tets) released with a bending velocity, no load, trapezoidal
    Newmark (β = 1/4, γ = 1/2), 200 steps of 2 ms (~5 oscillation periods): total energy
    (kinetic + strain) drifts by less than 0.1 %."""
    energy = cases.energy_history(n_steps=200, dt=2e-3)
    assert np.all(np.isfinite(energy))
    assert (energy.max() - energy.min()) / energy[0] < 1e-3


def test_generalized_alpha_conserves_at_rho_1_and_damps_below():
    """Generalized-α: ρ∞ = 1 conserves the energy (< 0.1 % drift, 200 steps); ρ∞ = 0.5 removes
    energy from the coarse-mesh high frequencies (> 1 % lost)."""
    conserved = cases.energy_history(integrator="generalized_alpha", rho_inf=1.0)
    assert (conserved.max() - conserved.min()) / conserved[0] < 1e-3
    damped = cases.energy_history(integrator="generalized_alpha", rho_inf=0.5)
    assert np.all(np.isfinite(damped)) and damped[-1] < 0.99 * damped[0]


def test_rayleigh_damping_dissipates():
    """With Rayleigh damping (αM = 5 1/s, βK = 1e-4 s) the same motion loses energy monotonically
    up to round-off (and more than 20 % over 200 steps)."""
    energy = cases.energy_history(n_steps=200, dt=2e-3, rayleigh=(5.0, 1e-4))
    assert np.all(np.diff(energy) <= 1e-12 * energy[0])
    assert energy[-1] < 0.8 * energy[0]


def test_cantilever_tip_deflection_matches_euler_bernoulli():
    """Clamped beam L/h = 20, P2 tetrahedra (20 x 2 x 2 boxes, 6 tets each), ν = 0, tip shear
    δ/L = 1e-4: tip deflection within 2 % of P L³ / (3 E I)."""
    r = cases.cantilever(n_length=20, n_section=2, degree=2)
    assert r.rel_error < 0.02, r


def test_shallow_arch_snaps_through():
    """Clamped shallow cylindrical arch (span 0.2 m, rise 0.02 m, thickness 5 mm, P2 tets) under
    displacement control at the crown: the load rises to a limit point, falls (by more than 30 %)
    and rises again after snap-through; no solver failure on the whole path."""
    path = cases.snap_through(n_steps=20)
    assert path.ok, path.reason
    f = path.force
    assert len(f) == 21 and np.all(np.isfinite(f))
    peak = int(np.argmax(f[: len(f) // 2 + 1]))
    assert 0 < peak < len(f) - 1
    valley = peak + int(np.argmin(f[peak:]))
    assert f[valley] < 0.7 * f[peak]
    assert np.all(np.diff(f[: peak]) > 0)                 # rises to the limit point
    assert np.all(np.diff(f[peak + 1: valley + 1]) < 0)   # falls past it (unstable branch)
    assert f[-1] > f[valley]                               # stiffens again after snapping


def test_arc_length_traces_the_same_snap_through_under_load_control():
    """Riks/Crisfield arc-length on the same arch under a crown line load: the load factor rises,
    passes its maximum and falls while the deflection keeps growing (through the limit point), and
    the limit load agrees with the displacement-controlled path within 3 %."""
    riks = cases.snap_through_arc_length()
    assert riks.ok, riks.reason
    lam, w = riks.force, riks.displacement
    assert np.all(np.isfinite(lam)) and np.all(np.diff(w) > 0)
    before = w < 0.02                                   # the limit point lies at w ≈ 8 mm
    peak = int(np.argmax(np.where(before, lam, -np.inf)))
    assert 0 < peak and before[peak + 2] and lam[peak + 2] < lam[peak]
    valley = peak + int(np.argmin(np.where(w[peak:] < 0.03, lam[peak:], np.inf)))
    assert lam[valley] < 0.7 * lam[peak] and lam[-1] > lam[valley]
    disp = cases.snap_through(n_steps=20)
    limit_disp = disp.force[disp.displacement < 0.02].max()
    assert abs(lam[peak] - limit_disp) < 0.03 * lam[peak]
