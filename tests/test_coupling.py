"""serve's implicit contact coupling (thermognn/serve/coupling.py) on a body with a closed-form step.

The body is a flat square plate (four loadable nodes at z = 0, two surface triangles, a fifth node
below it, off the surface) that moves as one: a mass M [kg] on a spring K [N/m] along z, under the
vertical sum of its nodal loads, stepped by Newmark's average-acceleration rule (the data's and the
served laws' rule). Pressed by the tool it stays flat, so the tool's penetration is exact:
delta = r - (h - w) for the tool centre at height h above the rest plane and the plate at w.
"""

from __future__ import annotations

import numpy as np
import pytest

from thermognn.serve.contact import SurfaceContact
from thermognn.serve.coupling import ContactCoupling, implicit_contact_step

X = np.array([[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0], [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0], [0.0, 0.0, -0.05]])
FACES = np.array([[0, 1, 2], [0, 2, 3]])
NODE_TYPE = np.array([2, 2, 2, 2, 0])
M, K, DT = 0.01, 900.0, 0.005          # [kg], [N/m], [s]
K_C, R = 300.0, 0.003                  # contact stiffness [N/m], tool radius [m]


def plate_step(z: np.ndarray, loads: np.ndarray) -> np.ndarray:
    """One Newmark (beta 1/4, gamma 1/2) step of the plate: z = [w, v, a] (m, m/s, m/s^2)."""
    w, v, a = z
    f = float(np.asarray(loads)[:, 2].sum())                          # [N] vertical load
    predictor = w + DT * v + DT * DT / 4 * a
    a1 = (f - K * predictor) / (M + K * DT * DT / 4)                  # M a1 + K w1 = f
    return np.array([predictor + DT * DT / 4 * a1, v + DT / 2 * (a + a1), a1])


def plate_positions(z: np.ndarray) -> np.ndarray:
    """[5, 3] m: the plate's nodes moved by w (the node below moves with it)."""
    return X + np.array([0.0, 0.0, z[0]])


def tool(h: float) -> np.ndarray:
    """The tool centre [3] m at height h above the rest plane, over the plate's middle."""
    return np.array([0.01, -0.005, h])


def contact() -> SurfaceContact:
    return SurfaceContact(X, NODE_TYPE, FACES, R, K_C, 0.0)


def energy(z: np.ndarray, h: float) -> float:
    """[J]: the plate's kinetic and spring energy and the penalty spring's."""
    depth = max(R - (h - z[0]), 0.0)
    return 0.5 * M * z[1] ** 2 + 0.5 * K * z[0] ** 2 + 0.5 * K_C * depth ** 2


def test_the_load_is_the_one_the_surface_at_the_step_end_meets():
    """From rest with the tool 2 mm into the plate, the load solves f = k_c (r - h + w1(f)) with
    w1 = -c f, c = (dt²/4) / (M + K dt²/4): f = k_c (r - h) / (1 + k_c c). The body is linear, so
    the secant lands on it at the third trial (the first two follow the default slope g' = 2), and
    g' = 1 + k_c c gives the body's one-step stiffness; passed that slope (as serve passes the
    previous step's), at the first: a body at rest has no motion of its own over the step."""
    h = R - 0.002
    c = DT * DT / 4 / (M + K * DT * DT / 4)                          # [m/N] one step's compliance
    step = implicit_contact_step(plate_step, plate_positions, np.zeros(3), tool(h), contact())
    assert step.steps == 3 and step.chosen == 2 and step.measured
    assert step.magnitude == pytest.approx(K_C * 0.002 / (1 + K_C * c), rel=1e-9)
    assert step.converged(1e-9, 1e-12) and abs(step.residual) < 1e-9
    reaction = -step.loads.sum(axis=0)                                   # [3] N on the tool: pushes it up
    assert reaction == pytest.approx([0.0, 0.0, step.magnitude], rel=1e-12, abs=1e-15)
    assert step.z[0] == pytest.approx(-c * step.magnitude, rel=1e-9)
    assert step.slope == pytest.approx(1 + K_C * c, rel=1e-6)          # k_b = k_c / (g' - 1) = 1 / c
    assert step.contact.depth == pytest.approx(step.magnitude / K_C, rel=1e-6)
    again = implicit_contact_step(plate_step, plate_positions, np.zeros(3), tool(h), contact(), slope=step.slope)
    assert again.steps == 1 and again.magnitude == pytest.approx(step.magnitude, rel=1e-9)
    guessed = implicit_contact_step(plate_step, plate_positions, np.zeros(3), tool(h), contact(), guess=step.magnitude)
    assert guessed.steps == 1 and guessed.magnitude == step.magnitude        # the previous step's load, kept
    # the explicit load (k_c * 2 mm, found before the step) is the larger: the plate yields under it
    assert K_C * 0.002 > 1.1 * step.magnitude


def test_a_tool_out_of_reach_takes_one_unloaded_step_and_a_rising_surface_meets_it():
    far = implicit_contact_step(plate_step, plate_positions, np.zeros(3), tool(0.05), contact())
    assert far.steps == 1 and far.magnitude == 0.0 and not far.loads.any() and not far.contact.in_contact
    # the plate rising at 1 m/s reaches a tool 2 mm out of reach (r + 2 mm) within the step
    z = np.array([0.0, 1.0, 0.0])
    rising = implicit_contact_step(plate_step, plate_positions, z, tool(R + 0.002), contact())
    free = plate_step(z, np.zeros((5, 3)))
    assert free[0] > 0.002 and rising.magnitude > 0.0 and rising.converged(0.01, 1e-4)
    assert rising.z[0] < free[0]                                        # the tool held it back


def test_an_undamped_body_held_by_the_tool_keeps_its_energy_where_the_late_load_rings_it_up():
    """The tool held 2 mm into the plate at rest: the plate oscillates about its equilibrium in
    contact throughout (K > k_c). The trapezoidal rule keeps a linear system's energy, and so it
    does with the load found at the step's end (to the secant's round-off; within serve's default
    tolerance, 1 % of the load, to 2 %); found before the step (serve's explicit coupling) it lags
    and grows the energy (benchmarks/contact_lag.py)."""
    h = R - 0.002
    rest = np.array([0.0, 0.0, -K_C * 0.002 / M])                     # at rest, its acceleration the load's
    e0 = energy(rest, h)
    c = contact()
    for rtol, atol, drift in ((1e-12, 1e-15, 1e-9), (0.01, 1e-4, 0.02)):
        z, trials = rest, []                   # ContactCoupling carries the slope and the load between steps
        coupler = ContactCoupling(plate_step, plate_positions, c, "implicit", rtol, atol, 6)
        for _ in range(2000):
            assert coupler.begin(z, tool(h)).in_contact
            step = coupler.step()
            z = step.z
            trials.append(step.steps)
            assert step.contact.in_contact
        assert energy(z, h) == pytest.approx(e0, rel=drift), rtol
        assert np.mean(trials) <= 2.01 and coupler.calls == sum(trials) and coupler.loaded == 2000, rtol
        assert coupler.unsettled <= 2000 and coupler.unsettled_max <= 0.05 * K_C * 0.002, rtol
    # the body's one-step stiffness from a step whose trials measured the slope: 1 / c
    c_b = DT * DT / 4 / (M + K * DT * DT / 4)                        # [m/N]
    coupler = ContactCoupling(plate_step, plate_positions, c, "implicit", 1e-12, 1e-15)
    coupler.begin(np.zeros(3), tool(h))
    assert coupler.body_stiffness(coupler.step()) == pytest.approx(1 / c_b, rel=1e-6)
    late, coupler = rest, ContactCoupling(plate_step, plate_positions, c, "explicit")
    for _ in range(2000):
        res = coupler.begin(late, tool(h))
        step = coupler.step()                  # one call, the load found before the step
        assert step.steps == 1 and step.magnitude == pytest.approx(np.linalg.norm(res.force), rel=1e-12)
        assert coupler.body_stiffness(step) is None
        late = step.z
    assert energy(late, h) > 2.0 * e0 and coupler.calls == 0      # (the implicit steps' counts only)


def test_the_coupling_steps_only_from_a_state_it_has_begun_at():
    coupler = ContactCoupling(plate_step, plate_positions, contact())
    with pytest.raises(RuntimeError, match="begin"):
        coupler.step()
    coupler.begin(np.zeros(3), tool(R - 0.002))
    coupler.step()
    with pytest.raises(RuntimeError, match="begin"):              # once a step
        coupler.step()
    with pytest.raises(ValueError, match="coupling = 'late'"):
        ContactCoupling(plate_step, plate_positions, contact(), "late")


def test_a_step_that_is_not_finite_is_returned_at_once():
    def broken(z, loads):
        return np.full(3, np.nan)

    step = implicit_contact_step(broken, plate_positions, np.zeros(3), tool(R - 0.002), contact())
    assert step.steps == 1 and np.isnan(step.z).all() and step.residual == np.inf
    with pytest.raises(ValueError, match="max_steps"):
        implicit_contact_step(plate_step, plate_positions, np.zeros(3), tool(R - 0.002), contact(), max_steps=0)
