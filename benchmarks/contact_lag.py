"""Why an undamped body can ring up under serve's tool: the contact load found a step late.

``serve``'s physics process (and ``thermognn.serve.lockstep.press_rollout``) finds the tool's
penalty contact on the body's surface *before* a step and applies that load at the step's end.
For one mass m [kg] under Newmark's average-acceleration rule (implicit in its own stiffness k_b
[N/m]) pressed by a penalty spring k_c [N/m] so, this prints the growth of |x| + |v| over 400
steps from x = 1 for r = k_c dt² / m: the lagged load grows an undamped body's motion at every r
(the lag does positive work each cycle), where the same load found at the Newmark predictor
x + dt v + dt²/4 a stays bounded up to r = 4. The shell (dt 5 ms, a thin 20 g strip, the tool's
300 N/m on a few grams: r ~ 1-4) chattered under the sim device's press and left its law's states;
found at the predictor the contact still chattered there (unilateral, on a few light nodes). Found
at the step's end (the load the end position meets: serve's implicit coupling since session 98,
``thermognn/serve/coupling.py``) the rule keeps the spring's energy and |x| + |v| stays bounded at
every r; so did the shell under the press (docs/accuracy.md, sessions 97-98).

    .venv/bin/python benchmarks/contact_lag.py
"""

from __future__ import annotations

import argparse


def growth(r: float, stiffness_ratio: float = 0.0, at: str = "start", steps: int = 400) -> float:
    """|x| + |v| after ``steps`` steps of the 1-DOF model (m = dt = 1, k_c = r, k_b = stiffness_ratio
    k_c) from x = 1 at rest: the contact load -k_c x found at the step's ``at`` = "start" (serve's
    explicit coupling) or "predictor" (x + dt v + dt²/4 a) and applied at its end, or at the "end"
    (-k_c x1: serve's implicit coupling, solved here in closed form)."""
    m, dt, kc = 1.0, 1.0, r
    kb = stiffness_ratio * kc
    x, v, a = 1.0, 0.0, -(kc + kb)
    for _ in range(steps):
        predictor = x + dt * v + dt * dt / 4 * a
        if at == "end":                                                               # m a1 + (k_b + k_c) x1 = 0
            a1 = -(kb + kc) * predictor / (m + (kb + kc) * dt * dt / 4)
        else:
            f1 = -kc * (x if at == "start" else predictor)
            a1 = (f1 - kb * predictor) / (m + kb * dt * dt / 4)                      # m a1 + k_b x1 = f1
        x1 = x + dt * v + dt * dt / 4 * (a + a1)
        v, x, a = v + dt / 2 * (a + a1), x1, a1
    return abs(x) + abs(v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args()
    ratios = (0.01, 0.1, 0.5, 1.0, 2.0, 4.0, 8.0)
    print("growth of |x| + |v| over", args.steps, "steps; columns r = k_c dt^2 / m:", " ".join(f"{r:g}" for r in ratios))
    for kb in (0.0, 1.0, 10.0):
        for at in ("start", "predictor", "end"):
            row = " ".join(f"{growth(r, kb, at, args.steps):9.1e}" for r in ratios)
            print(f"k_b/k_c {kb:4g}, load found at the {at:9s}: {row}")


if __name__ == "__main__":
    main()
