"""Hard cases finish without NaN; failures end a trajectory cleanly (real dolfinx solves)."""

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from thermognn.generate import cases  # noqa: E402
from thermognn.generate.materials import Material  # noqa: E402
from thermognn.generate.solid import Solid, SolverOptions  # noqa: E402


def _pressed_block(mat, node_pick, force_n=2.0, steps=10, effects=("elastic", "inertia"), dt=0.01):
    """Block 0.04 x 0.04 x 0.02 m (P1, 4x4x2 boxes) clamped at z = 0; a force ramped to force_n [N]
    over 5 steps at the node node_pick(solid) along -normal; returns (solid, reports)."""
    s = Solid(cases.box_mesh((0.04, 0.04, 0.02), (4, 4, 2)), mat, effects,
              SolverOptions(integrator="newmark" if "inertia" in effects else "quasi_static"))
    s.clamp(cases.nodes_where(s, lambda x: x[:, 2] < 1e-10))
    node, direction = node_pick(s)
    full = np.zeros_like(s.nodes)
    full[node] = force_n * np.asarray(direction)
    reports = [s.step(dt, lambda t: s.set_nodal_force(min(1.0, t / (5 * dt)) * full)) for _ in range(steps)]
    return s, reports


def _top_centre(s):
    return int(np.argmin(np.linalg.norm(s.nodes - [0.02, 0.02, 0.02], axis=1))), [0, 0, -1]


def test_near_incompressible_block_finishes():
    """D1 = 1e-9 1/Pa (K/μ = 1e5, ν ≈ 0.499995), P1 tets (locking, but no failure)."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-9})
    s, reports = _pressed_block(mat, _top_centre)
    assert all(r.ok for r in reports), [r.reason for r in reports if not r.ok]
    u = s.displacement()
    assert np.all(np.isfinite(u)) and np.all(np.isfinite(s.cauchy_stress_nodes()))


def test_load_next_to_clamped_boundary_finishes():
    """A 2 N side push on the free node closest to the clamped edge (x = 0, lowest z > 0)."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})

    def pick(s):
        cand = np.flatnonzero((s.nodes[:, 0] < 1e-10) & (s.nodes[:, 2] > 1e-10))
        return int(cand[np.argmin(s.nodes[cand, 2] + 1e-3 * np.abs(s.nodes[cand, 1] - 0.02))]), [1, 0, 0]

    s, reports = _pressed_block(mat, pick)
    assert all(r.ok for r in reports), [r.reason for r in reports if not r.ok]
    assert np.all(np.isfinite(s.displacement())) and np.all(np.isfinite(s.cauchy_stress_nodes()))


def test_ogden_block_compressed_by_point_load_finishes():
    """Ogden α = 16.19 block pressed at the top centre (large local compression), quasi-static."""
    mat = Material("ogden", {"mu": [2.0e3], "alpha": [16.19], "D": [1.0e-4]})
    s, reports = _pressed_block(mat, _top_centre, force_n=0.5, steps=6, effects=("elastic",))
    assert all(r.ok for r in reports), [r.reason for r in reports if not r.ok]
    assert np.all(np.isfinite(s.displacement()))


def test_impossible_step_fails_cleanly_at_the_floor():
    """A 1e4 N point load cannot be carried: the step fails after cutting down to the floor,
    reports why, and leaves the last converged (finite) state."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    s, reports = _pressed_block(mat, _top_centre, force_n=1e4, steps=3)
    failed = [r for r in reports if not r.ok]
    assert failed and "floor" in failed[0].reason
    assert failed[0].cuts >= 4
    assert np.all(np.isfinite(s.displacement()))


def test_gravity_effect_column_under_self_weight():
    """Effect 'gravity' (quasi-static): a clamped column (ν = 0) sags at its top by ρ g L² / (2E)
    within 1 %; without the effect nothing moves (the term is not assembled)."""
    mu = 1.0e6
    mat = Material("neo_hookean", {"C10": mu / 2, "D1": 2.0 / (2 * mu / 3)}, density=1000.0)
    L = 0.1
    sag = {}
    for effects in (("elastic", "gravity"), ("elastic",)):
        s = Solid(cases.box_mesh((0.02, 0.02, L), (2, 2, 8)), mat, effects,
                  SolverOptions(integrator="quasi_static", rtol=1e-10, atol=1e-12))
        s.clamp(cases.nodes_where(s, lambda x: x[:, 2] < 1e-10))
        assert s.step(1.0).ok
        top = cases.nodes_where(s, lambda x: np.abs(x[:, 2] - L) < 1e-10)
        sag[effects] = float(s.displacement()[top, 2].mean())
    exact = -1000.0 * 9.81 * L**2 / (2 * 2 * mu)
    assert abs(sag[("elastic", "gravity")] - exact) < 0.01 * abs(exact)
    assert sag[("elastic",)] == 0.0


def test_static_equilibrium_reactions_balance_the_load():
    """Quasi-static pressed block: the reactions at the clamped nodes balance the applied nodal
    force (global equilibrium, 1e-8 relative), i.e. the f_ext sign and units are consistent."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    s, reports = _pressed_block(mat, _top_centre, force_n=1.0, steps=6, effects=("elastic",))
    assert all(r.ok for r in reports)
    clamped = cases.nodes_where(s, lambda x: x[:, 2] < 1e-10)
    support = s.internal_force()[clamped].sum(axis=0)   # force of the clamp on the body [N]
    applied = s.f_ext.x.array.reshape(-1, 3).sum(axis=0)
    assert np.allclose(applied, [0, 0, -1.0])
    assert np.allclose(support + applied, 0.0, atol=1e-8)


def test_the_line_search_backs_off_along_the_last_update():
    """A non-finite residual's line search (``Solid._back_track``) moves u back towards where the
    last Newton update started, to 1/2, then 1/4, ... of the update (``du`` holds it as applied),
    not on along it."""
    mat = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    s = Solid(cases.box_mesh((0.04, 0.04, 0.02), (2, 2, 1)), mat, ("elastic", "inertia"), SolverOptions())
    rng = np.random.default_rng(0)
    start = 1e-4 * rng.standard_normal(s.u.x.array.shape)
    update = 1e-3 * rng.standard_normal(s.u.x.array.shape)
    s.u.x.array[:] = start + update              # where the update ended
    s.du.x.array[:] = update                     # ... as newton stores it: the update applied
    norm = s._back_track(0.5)
    assert np.allclose(s.u.x.array, start + 0.5 * update, rtol=0, atol=1e-15) and np.isfinite(norm)
    s._back_track(0.25)
    assert np.allclose(s.u.x.array, start + 0.25 * update, rtol=0, atol=1e-15)
