"""What a served step's speed costs in force: exported models pressed by the sim device's scripted
tool in body time, each against its own surface, against a reference model's rollout of the same
path (``thermognn.serve.lockstep``).

``serve_bench.py`` measures how fast the physics runs under the haptic loop, not how right its
force is: the tool there moves with the wall clock, so every session loads the body differently.
Here step k reads the tool at k Δt, so every model sees the same path, and each row is the
whole-path relative error of the force on the user and of the body's displacement against the
reference (and the force's over each period of the path, each press, where ``--seconds`` runs
longer than one); its magnitude's alone; the force's envelope (``--envelope``, a moving
average) against the reference's, and each model's own step-to-step jitter about it (``lockstep.compare``); the
largest force error beside the largest force; and the body step's median, mean and p99 time (one
process, ``--threads``, the physics process's default 1), with a law's Newton updates. With
``--rounds R`` the models are pressed R times in turn (a model's force is the same every round)
and each time figure is the median over the rounds: a quiet comparison of step times on a noisy
machine (docs/accuracy.md, session 102: the liver law's mixed chords, ``rollout.prior_anderson``).

    .venv/bin/python benchmarks/serve_accuracy.py --reference runs/liver/kept.pt \
        runs/liver/model.pt runs/liver/two.pt --path press scene=liver

The reference is typically the same law-prior model stepped to convergence (exported with
``rollout.prior_newton_max=16 rollout.prior_newton_rtol=1e-7 rollout.prior_tangent=kept``); the
same export with ``rollout.remainders=zero`` is its law alone, without the network, so that row is
what the network adds under the tool (docs/accuracy.md, session 78). Any
further arguments are config overrides for serve's contact (``serve.tool_radius``,
``serve.contact_stiffness``, ``serve.load_radius``, which follows ``scene=...``'s load radius, and
``serve.contact_coupling``, ``serve.contact_rtol``, ``serve.contact_trials``).
Prints figures, asserts nothing; docs/accuracy.md (session 77) quotes them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("models", type=Path, nargs="+", help="exported model files to compare")
    ap.add_argument("--reference", type=Path, required=True, help="exported model the others are compared with")
    ap.add_argument("--path", default="press", choices=("press", "palpate", "drag"))
    ap.add_argument("--period", type=float, default=2.0, help="sim path period [s]")
    ap.add_argument("--depth", type=float, default=None, help="press depth below the surface [m] (default: 20 %% of the height)")
    ap.add_argument("--seconds", type=float, default=None, help="body time [s] (default: one period)")
    ap.add_argument("--envelope", type=float, default=0.1,
                    help="the force's envelope: a centred moving average over this long [s] (odd steps)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=1, help="press the models this many times in turn (times: medians)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args, overrides = ap.parse_known_args(argv)

    from thermognn.core.config import load_config
    from thermognn.serve.lockstep import compare, force_envelope, press_rollout
    from thermognn.serve.physics import load_exported

    cfg = load_config(list(overrides))
    contact = {"tool_radius": float(cfg.serve.tool_radius), "contact_stiffness": float(cfg.serve.contact_stiffness),
               "load_radius": float(cfg.serve.load_radius), "coupling": str(cfg.serve.contact_coupling),
               "contact_rtol": float(cfg.serve.contact_rtol), "contact_trials": int(cfg.serve.contact_trials)}
    dt = float(load_exported(args.reference)[2]["dt"])
    seconds = args.period if args.seconds is None else args.seconds
    steps = max(1, int(round(seconds / dt)))
    envelope_steps = max(3, 2 * int(round(args.envelope / dt / 2)) + 1)    # odd, centred, >= 3
    run = dict(steps=steps, path=args.path, period=args.period, depth=args.depth, threads=args.threads, **contact)
    print(f"serve accuracy: path {args.path}, period {args.period:g} s, {steps} steps of {dt:g} s, "
          f"tool radius {contact['tool_radius']:g} m, contact {contact['contact_stiffness']:g} N/m, "
          f"load radius {contact['load_radius']:g} m, {contact['coupling']} coupling, {args.threads} thread(s); "
          f"the force's envelope over "
          f"{envelope_steps} steps")
    reference = press_rollout(args.reference, **run)
    pressed = {model: [] for model in args.models}            # each model's rollouts, round after round
    for _ in range(max(1, args.rounds)):
        for model in args.models:
            pressed[model].append(press_rollout(model, **run))
    rows = []
    for model in [args.reference, *args.models]:
        rounds = [reference] if model == args.reference else pressed[model]
        r = rounds[0]
        row = {"model": str(model), **compare(r, reference, envelope_steps),
               **{f"step_ms_{name}": float(np.median([stat(x.step_ms) for x in rounds]))
                  for name, stat in (("median", np.median), ("mean", np.mean),
                                     ("p99", lambda ms: np.percentile(ms, 99)))},
               "rounds": len(rounds)}
        period_steps = max(1, int(round(args.period / dt)))   # the force's error over each period of the path
        periods = range(0, min(len(r.times), len(reference.times)), period_steps)
        row["force_per_period"] = [period_force_error(r.force, reference.force, p, p + period_steps) for p in periods]
        env, env_ref = force_envelope(r.force, envelope_steps), force_envelope(reference.force, envelope_steps)
        row["envelope_per_period"] = [period_force_error(env, env_ref, p, p + period_steps) for p in periods]
        if r.law_counts is not None:                # a law prior's steps: Newton updates, not converged, cut
            row.update(law_updates=int(r.law_counts[0]), law_steps=int(r.law_counts[1]),
                       law_unconverged=int(r.law_counts[2]), law_cut=int(r.law_counts[3]))
        rows.append(row)
        print(f"  {str(model):48s} force {100 * row['force']:9.3g} %  peak error {row['peak_force_error_N']:9.3g} N "
              f"of {row['peak_force_N']:.3f} N  displacement {100 * row['displacement']:9.3g} %  "
              f"{row['step_ms_median']:7.1f} ms (mean {row['step_ms_mean']:.1f}, p99 {row['step_ms_p99']:.1f}"
              + (f", medians of {row['rounds']} rounds" if row["rounds"] > 1 else "") + f")  {row['steps']} steps"
              + (f"  law updates {row['law_updates']}, steps not converged {row['law_unconverged']}, cut {row['law_cut']}"
                 if "law_steps" in row else "")
              + ("" if row["finite"] else "  NOT FINITE")
              + ("" if row["healthy"] else f"  CELLS CRUSHED OR INVERTED (body reset {row['resets']}x)")
              + ("" if row["first_beyond_states"] is None
                 else f"  cells beyond the law's states from step {row['first_beyond_states']}"))
        print(f"    magnitude {100 * row['force_magnitude']:.3g} %, envelope {100 * row['force_envelope']:.3g} %, its own jitter {100 * row['force_jitter']:.3g} % "
              f"(the reference's {100 * row['reference_jitter']:.3g} %)")
        if len(row["force_per_period"]) > 1:
            print("    per period: force " + ", ".join(f"{100 * e:.3g} %" for e in row["force_per_period"])
                  + "; envelope " + ", ".join(f"{100 * e:.3g} %" for e in row["envelope_per_period"]))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


def period_force_error(force: np.ndarray, reference: np.ndarray, start: int, stop: int) -> float:
    """‖f − f_ref‖ / ‖f_ref‖ over steps [start, stop) (one period of the path: one press) of two
    forces [T, 3] N."""
    f, g = force[start:stop], reference[start:stop]                        # [n, 3] N
    n = min(len(f), len(g))
    norm = float(np.linalg.norm(g[:n]))
    return float(np.linalg.norm(f[:n] - g[:n])) / norm if norm > 0 else float("nan")


if __name__ == "__main__":
    main(sys.argv[1:])
