"""What the law prior's own step costs, and how near the data it stays (no network).

``model=law_prior`` steps the dataset's hyperelastic law in torch (``HyperelasticNewmarkPrior``:
the FE's law, Prony history, mass, damping and Newmark rule, without dolfinx) with a Newton
budget, and a network learns what is left. This script rolls the law alone (remainders G = 0)
over a split of a dataset from each trajectory's first state under its stored loads, and prints,
per trajectory and as the split's mean, the whole-rollout relative errors of q, v and σ against
the data (``evaluate``'s metric), the Newton iterations, tangents formed, steps, unconverged and
cut steps, and the ms a step (mean, median, p99, max): the accuracy the law prior's budget buys
and its time.

    .venv/bin/python benchmarks/law_step.py runs/s71_shell/dataset.h5 --iterations 1 --max 12 --rtol 1e-4 --cuts 4
    .venv/bin/python benchmarks/law_step.py runs/s71_liver96/dataset.h5 --iterations 1 --split test,val
    .venv/bin/python benchmarks/law_step.py runs/s79_shell/dataset.h5 --law runs/s79_shell_ll/learned_law.pt ...

``--law F`` steps a learned law instead of the dataset's (``model.prior_material=learned``: the fit
``train`` keeps in ``learned_law.pt``, its Prony terms too where it fitted them).

``--iterations k`` alone is a fixed budget of k; ``--max m --rtol r`` lets a step that has not
converged take up to m (``model.prior_newton_max``, ``model.prior_newton_rtol``), ``--cuts c``
halve it up to c times (``model.prior_step_cuts``), ``--tangent kept`` keep its tangent between
iterations and steps while it contracts (``model.prior_tangent``), ``--prior-substeps k`` take
each step as the prior's k sub-steps, each cut where it has not converged (``rollout.prior_substeps``;
``--substeps L`` is the older uncut reference). The split is the training default (seed 0,
0.8/0.1/0.1); ``--names`` picks trajectories instead. A rollout that stops being finite is
reported as such and counts as an infinite error in the mean. docs/accuracy.md (sessions 71–73)
quotes its figures (2 threads, the default ``--threads``).
"""

from __future__ import annotations

import argparse
import math
import time

import torch

from thermognn.train.data import load_data
from thermognn.train.hybrid import build_prior
from thermognn.train.rollout import trajectory_error

GROUPS = ("q", "v", "sigma")


def roll_law(prior, X: torch.Tensor, z: torch.Tensor, f: torch.Tensor, level: int = 0
             ) -> tuple[torch.Tensor, list[float]]:
    """The law alone from the state z[0] [N, 12] under the loads f [S, N, 3] N: the predicted
    states [S, N, 12] (q m, v m/s, σ Pa) and each step's wall time [ms]; with ``level`` > 0 each
    step as 2^level sub-steps of Δt / 2^level (the loads linear between the step's), each to
    the prior's tolerance (a finer rollout of the same law: what the time step costs)."""
    u, v = z[..., 0:3] - X, z[..., 3:6]
    G = torch.zeros(1, prior.n_free, dtype=torch.float64)
    uf, vf = prior.gather(u[:1]), prior.gather(v[:1])
    h = prior.internal_variables(uf)
    a = prior.initial_acceleration(uf, vf, prior.gather(f[:1]), G)
    us, vs, hs, times = [uf], [vf], [h], []
    with torch.no_grad():
        for k in range(1, f.shape[0]):
            t0 = time.perf_counter()
            if level == 0:
                uf, vf, a, h = prior.step(uf, vf, a, prior.gather(f[k:k + 1]), G, G, h)
            else:
                for j in range(1, 2 ** level + 1):
                    prior.use_level(level)
                    fj = prior.gather(f[k - 1:k] + (j / 2 ** level) * (f[k:k + 1] - f[k - 1:k]))
                    loads = fj + prior.body_force
                    u1, predictor, S_iso0, extra, damping0 = prior.fresh_first_iteration(uf, vf, a, h, loads)
                    u1, _, _ = prior.iterate(u1, uf, vf, a, predictor, extra, loads + damping0)
                    a, vf = prior.end_rates(u1, vf, a, predictor)
                    h = prior.relax_from(S_iso0, u1, h)
                    uf = u1
                prior.use_level(0)
            times.append(1e3 * (time.perf_counter() - t0))
            us.append(uf)
            vs.append(vf)
            hs.append(h)
    return prior.physical_state(X, torch.cat(us), torch.cat(vs), None, torch.cat(hs)), times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--iterations", type=int, default=1, help="Newton iterations every step takes")
    ap.add_argument("--max", type=int, default=None, help="the most a step that has not converged takes")
    ap.add_argument("--rtol", type=float, default=1e-4, help="converged: the last update below this share of "
                    "the largest displacement (with --max)")
    ap.add_argument("--cuts", type=int, default=0, help="halvings of a step still not converged (with --max)")
    ap.add_argument("--tangent", default="fresh", choices=("fresh", "kept"),
                    help="a tangent formed every iteration, or kept while it contracts (with --max)")
    ap.add_argument("--split", default="test", help="comma-separated parts: train, val, test")
    ap.add_argument("--names", default="", help="comma-separated trajectory names (of the split's parts)")
    ap.add_argument("--law", default="", help="a learned law's learned_law.pt (model.prior_material=learned)")
    ap.add_argument("--search", type=int, default=0,
                    help="halvings of a Newton update that does not lower the residual (model.prior_line_search)")
    ap.add_argument("--hht", type=float, default=0.0,
                    help="HHT's numerical dissipation, α = -hht, 0 to 1/3 (model.prior_hht; 0: the data's Newmark rule)")
    ap.add_argument("--rule", default="newmark", choices=("newmark", "energy"),
                    help="the time rule: the data's Newmark, or the trapezoid with the stored energy's discrete "
                         "gradient (model.prior_rule)")
    ap.add_argument("--substeps", type=int, default=0,
                    help="L: each step as 2^L sub-steps (loads linear between), L <= --cuts (a finer reference)")
    ap.add_argument("--prior-substeps", type=int, default=1,
                    help="k: the prior's own sub-steps (model.prior_substeps / rollout.prior_substeps, 1 2 4 8 16), "
                         "each cut up to --cuts more times where it has not converged, as evaluate and export step it")
    ap.add_argument("--save", default="", help="torch.save the predicted states {name: [S, N, 12]} here")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    parts = tuple(p for p in args.split.split(",") if p)
    data = load_data(args.dataset, [0.8, 0.1, 0.1], 0, torch.float64, parts=parts, state_dtype=torch.float64)
    stretch = args.max is not None and args.max > args.iterations
    learned = torch.load(args.law, weights_only=True) if args.law else None
    prior = build_prior(data.dataset, data.dt, law=args.iterations,
                        **(dict(law_max=args.max, law_rtol=args.rtol, law_cuts=args.cuts, law_tangent=args.tangent)
                           if stretch else {}),
                        **(dict(learned_law=learned["key"]["hidden"], prony=learned["report"].get("prony"))
                           if learned else {}), law_search=args.search, law_hht=args.hht, law_rule=args.rule,
                        law_substeps=args.prior_substeps)
    if learned:
        prior.learned_law.load_state_dict(learned["state"])
    X = torch.as_tensor(data.reference_positions(), dtype=torch.float64)
    names = {n for n in args.names.split(",") if n}
    budget = (f"{args.iterations} to {args.max} iterations to {args.rtol:g}, cuts {args.cuts}, {args.tangent} tangent"
              if stretch else f"{args.iterations} iteration{'s' if args.iterations > 1 else ''}")
    budget += f", line search {args.search}" if args.search else ""
    budget += f", HHT α = -{args.hht:g}" if args.hht else ""
    budget += ", energy rule" if args.rule == "energy" else ""
    budget += f", {2 ** args.substeps} sub-steps a step" if args.substeps else ""
    budget += f", the prior's {args.prior_substeps} sub-steps a step" if args.prior_substeps > 1 else ""
    print(f"{args.dataset}: the {'learned law of ' + args.law if learned else 'law'} alone, {budget}, "
          f"{args.threads} threads")
    saved: dict = {}
    for part in parts:
        errors, times = [], []
        prior.newton_taken.zero_()
        prior.tangents_formed.zero_()
        for traj in data.of(part):
            if names and traj.name not in names:
                continue
            z, f = traj.z.double(), traj.force.double()
            prior.forget()                  # each rollout from scratch, as a model's rollout begins
            try:
                pred, step_ms = roll_law(prior, X, z, f, args.substeps)
                saved[traj.name] = pred.float()
            except RuntimeError as exc:
                print(f"  {part} {traj.name}: {exc}")
                errors.append({g: math.inf for g in GROUPS})
                continue
            e = trajectory_error(pred, z[..., :12], data.layout)
            errors.append(e)
            times += step_ms
            print(f"  {part} {traj.name}: whole q {e['q']:.3g} v {100 * e['v']:.3g} % σ {100 * e['sigma']:.3g} % "
                  f"| {sum(step_ms) / len(step_ms):.0f} ms/step", flush=True)
        if not errors:
            continue
        mean = {g: sum(e[g] for e in errors) / len(errors) for g in GROUPS}
        s = sorted(times) or [math.nan]
        iterations, steps, unconverged, cut = prior.newton_taken.tolist()
        print(f"{part} ({len(errors)}): whole q {mean['q']:.3g} v {100 * mean['v']:.3g} % σ {100 * mean['sigma']:.3g} % "
              f"| {iterations} Newton iterations and {int(prior.tangents_formed)} tangents in {steps} steps, "
              f"{unconverged} unconverged, {cut} cut "
              f"| {sum(s) / len(s):.1f} ms/step (median {s[len(s) // 2]:.1f}, p99 {s[int(0.99 * (len(s) - 1))]:.1f}, "
              f"max {s[-1]:.1f})")

    if args.save:
        torch.save(saved, args.save)


if __name__ == "__main__":
    main()
