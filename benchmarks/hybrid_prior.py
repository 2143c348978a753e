"""Experiment (not yet a model option): the data's own Newmark step of the linearised solid with a
learned nonlinear remainder, trained on whole rollouts. Prints test errors beside the linearised
FE model.

Why (docs/accuracy.md, sessions 11-12): where a dataset's strain energy sits in modes its time step
does not resolve (the block: all of them), an explicit learned step must produce the tiny
remainder of a load and an elastic force that cancel; the linearised FE model alone is then 10x
more accurate than the learned models. Here the step is ``thermognn.train.prior.NewmarkPrior``:
the FE's Newmark step with the internal force split as f_int(u) = K u - G(u),

    M a1 + aM M v1 + c K (u1 - u0) + K u1 = f1 + (1 + c) G1 - c G0,   c = bK / dt
    sigma1 = Sigma u1 + H1

which is the FE step itself with the exact remainders G [N] and H [Pa] and the linearised FE
model with G = H = 0. The TIGNN network's GENERIC rates at a state are read as the remainders
(v columns: G, sigma columns: H, scaled by their RMS in the training data), so a network whose
outputs start at zero starts at the linearised FE model. Per step: the linear step with the
previous G predicts the state, the network gives G1, H1 there (``--sweeps`` times), the linear
step with them gives the state. With ``--inputs q`` the network sees the positions only (G and H
of a hyperelastic solid are functions of the displacement), with ``all`` the whole state.

Training: ``--fit-minutes`` of one-step regression on the exact remainders (the prior's
``remainders`` of each training trajectory), then ``--rollout-minutes`` on whole rollouts
(back-propagation through the linear solves). The fit alone leaves v far off (block: G 10-14 %
off per step gives v 8-10 % off, worse than no G): the solve amplifies whatever part of the
error reaches the soft, global modes, a small share of G's norm, and the trapezoidal rule
carries a velocity error in the stiff modes undamped (white noise of 10 % of G: v 135 % off; a
smooth 10 % scale error: v 0.3 %). Whole rollouts fix that. Two further fit terms, measured over
four fit epochs only so far (v far better early, sigma worse): ``--compliance`` weighs G's error
by the displacement it causes, (1 + c) S^-1 (G - G*); ``--increments`` adds the error of the
outputs' change between consecutive snapshots.

Needs a dataset written by ``thermognn generate`` (with ``/linear``); torch and numpy only::

    .venv/bin/python benchmarks/hybrid_prior.py /tmp/b3/dataset.h5 --fit-minutes 20 \
        --rollout-minutes 20 --out /tmp/hyb

The split is the one ``thermognn train`` uses (``train.split`` fractions, seed 0). The best
weights by validation go to ``<out>/hybrid.pt`` (state dict), the fit's last to ``fit.pt``, the
figures to ``<out>/result.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from thermognn.core.errors import DataError
from thermognn.core.io import atomic_path
from thermognn.train.data import compute_stats, load_data, velocity_columns
from thermognn.train.evaluation import linear_baseline
from thermognn.train.model import TIGNN, hyperparameters
from thermognn.train.prior import NewmarkPrior
from thermognn.train.rollout import rrmse_per_step, trajectory_error, trajectory_rrmse


class Hybrid:
    """The prior stepped with the network's remainders. Graph tensors in float32 (the network),
    the prior in float64."""

    def __init__(self, net: TIGNN, prior: NewmarkPrior, graph, inputs: str) -> None:
        self.net, self.prior, self.graph = net, prior, graph
        self.X = graph.ref_pos.double()                                          # [N, 3] m
        self.batched = {1: graph}                                                # B -> B copies of the mesh
        D = net.dim
        self.seen = torch.ones(D, dtype=torch.float64)
        if inputs == "q":
            self.seen[3:] = 0.0                                                  # positions only

    def remainders(self, z, f, train: bool):
        """Network remainders at states z [B, N, D] under f [B, N, 3]: G [B, n] N, H [B, N, 6] Pa."""
        B, N, D = z.shape
        if B not in self.batched:
            self.batched[B] = self.graph.copies(B)
        g = self.batched[B]
        r = self.net.rates((z * self.seen).float().reshape(B * N, D), f.float().reshape(B * N, 3), g.edge_index,
                           g.node_type, g.ref_pos.float(), train)[0]
        r = (r if train else r.detach()).reshape(B, N, D).double() * self.net.dzdt_std.double()
        return self.prior.gather(r[..., 3:6]), r[..., 6:12]

    def state(self, u, v, H):
        """[B, N, D] from free-DOF u, v [B, n] and the stress remainder H [B, N, 6]."""
        U = self.prior.scatter(u)
        return torch.cat([self.X + U, self.prior.scatter(v), self.prior.stress(U, H)], -1)

    def rollout(self, z0, forces, sweeps: int = 1, train: bool = False):
        """States [B, S, N, D] from z0 [B, N, D] under forces [B, S, N, 3] (forces[:, s] at t_s)."""
        P = self.prior
        z0, forces = z0.double(), forces.double()
        U0 = z0[..., 0:3] - self.X
        u, v = P.gather(U0), P.gather(z0[..., 3:6])
        G, _ = self.remainders(z0, forces[:, 0], train)
        H = z0[..., 6:12] - P.stress(U0)
        a = P.initial_acceleration(u, v, P.gather(forces[:, 0]), G)
        out = [z0]
        for s in range(1, forces.shape[1]):
            f1 = P.gather(forces[:, s])
            G1 = G
            for _ in range(sweeps):                      # predict with the last G, evaluate there
                u1, v1, _ = P.step(u, v, a, f1, G, G1)
                G1, H = self.remainders(self.state(u1, v1, H), forces[:, s], train)
            u, v, a = P.step(u, v, a, f1, G, G1)
            G = G1
            out.append(self.state(u, v, H))
        return torch.stack(out, 1)


def errors(hybrid: Hybrid, trajs, layout, sweeps: int):
    """(per-snapshot, whole-rollout) mean test metrics over trajs."""
    per, whole = [], []
    with torch.enable_grad():                            # the rates differentiate the energy
        for t in trajs:
            pred = hybrid.rollout(t.z[:1], t.force.unsqueeze(0), sweeps)[0].float()
            per.append(trajectory_rrmse(rrmse_per_step(pred, t.z.float(), layout)))
            whole.append(trajectory_error(pred, t.z.float(), layout))
    mean = lambda rows: {k: float(np.mean([r[k] for r in rows])) for k in layout.names}  # noqa: E731
    return mean(per), mean(whole)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--out", default="runs/hybrid")
    ap.add_argument("--fit-minutes", type=float, default=0.0, help="one-step regression on the exact remainders")
    ap.add_argument("--rollout-minutes", type=float, default=20.0, help="then training on whole rollouts")
    ap.add_argument("--lr", type=float, default=1e-3, help="Adam's rate, decayed 10x over each phase")
    ap.add_argument("--batch", type=int, default=4, help="snapshots (fit) or trajectories (rollouts) per step")
    ap.add_argument("--noise", type=float, default=0.1, help="fit: input noise in typical steps' changes")
    ap.add_argument("--increments", type=float, default=0.0,
                    help="fit: weight of the outputs' change between consecutive snapshots (0: values only)")
    ap.add_argument("--compliance", type=float, default=0.0,
                    help="fit: weight of G's error measured by the displacement it causes, (1 + c) S^-1 (G - G*)")
    ap.add_argument("--sweeps", type=int, default=1, help="network evaluations per step")
    ap.add_argument("--inputs", default="q", choices=["q", "all"], help="state columns the network sees")
    ap.add_argument("--start-scale", type=float, default=0.01, help="output layers scaled by this at the start")
    ap.add_argument("--init", default=None, help="start from these weights (a hybrid.pt)")
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--message-passing", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    data = load_data(args.dataset, [0.8, 0.1, 0.1], args.seed, torch.float64)
    ds, g, dt, layout = data.dataset, data.graph, data.dt, data.layout
    if layout.names != ["q", "v", "sigma"]:
        raise DataError(f"{ds.path}: state_layout {layout.names}, this experiment needs q, v, sigma")
    linear = ds.linear_solid()
    if linear is None:
        raise DataError(f"{ds.path}: no /linear operators (regenerate it with thermognn generate)")
    N, D = g.n_nodes, layout.dim
    prior = NewmarkPrior(linear, N, dt)
    train, val, test = data.of("train"), data.of("val"), data.of("test")
    Z = torch.stack([t.z for t in train])                                       # [T, S, N, D] float64
    F = torch.stack([t.force for t in train])                                   # [T, S, N, 3]
    T, S = Z.shape[:2]
    X = g.ref_pos

    # the exact remainders of the training data, and the network's output scale from them
    G_true, H_true = zip(*(prior.remainders(t.z[..., 0:3] - X, t.z[..., 3:6], t.z[..., 6:12], t.force)
                           for t in train))
    G_true = torch.stack([prior.scatter(G) for G in G_true])                    # [T, S, N, 3]
    H_true = torch.stack(H_true)                                                # [T, S, N, 6]
    free_nodes = prior.free.reshape(N, 3).all(1)                                # [N]
    hp = hyperparameters(OmegaConf.create({"kinematics": "exact", "hidden": args.hidden,
                                           "message_passing": args.message_passing}),
                         D, velocity_columns(layout), False)
    net = TIGNN(**hp)
    stats = compute_stats(train, g, dt, hp)
    scale = stats["dzdt_std"].clone()
    scale[3:6] = G_true[:, :, free_nodes].pow(2).mean().sqrt()
    scale[6:12] = H_true.reshape(-1, 6).pow(2).mean(0).sqrt()
    stats["dzdt_std"] = scale
    net.set_stats(stats)
    with torch.no_grad():                                       # start near the linearised model
        for p in [*net.decoder.net[-1].parameters(), *net.port.parameters(),
                  *(p for dec in net.edge_decoders for p in dec.net[-1].parameters())]:
            p.mul_(args.start_scale)
    if args.init:
        net.load_state_dict(torch.load(args.init, weights_only=True))
    hybrid = Hybrid(net, prior, g, args.inputs)

    log, t_start, epoch = [], time.perf_counter(), 0
    best = float(np.mean(list(errors(hybrid, val, layout, args.sweeps)[1].values())))
    with atomic_path(out / "hybrid.pt") as tmp:
        torch.save(net.state_dict(), tmp)
    print(f"start: val {best:.4f}", flush=True)

    def validate(phase, loss):
        nonlocal best
        v_whole = errors(hybrid, val, layout, args.sweeps)[1]
        val_error = float(np.mean(list(v_whole.values())))
        if val_error < best:
            best = val_error
            with atomic_path(out / "hybrid.pt") as tmp:
                torch.save(net.state_dict(), tmp)
        log.append({"phase": phase, "epoch": epoch, "seconds": time.perf_counter() - t_start, "loss": loss,
                    "val": val_error, **v_whole})
        print(f"{phase:7s} {epoch:3d} {log[-1]['seconds']:6.0f} s  loss {loss:.3e}  val {val_error:.4f}  "
              + " ".join(f"{k} {v:.3g}" for k, v in v_whole.items()), flush=True)

    def decay(opt, t_phase: float, minutes: float) -> None:
        """Adam's rate: args.lr decayed 10x exponentially over the phase's wall time."""
        for group in opt.param_groups:
            group["lr"] = args.lr * 0.1 ** min((time.perf_counter() - t_phase) / (60 * minutes), 1.0)

    def descend(opt, loss) -> float:
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
        opt.step()
        return float(loss.detach())

    gen = torch.Generator().manual_seed(args.seed)
    # phase 1: one-step regression of the network's outputs on the exact remainders
    target = torch.cat([torch.zeros_like(G_true), G_true, H_true], -1) / scale.double()   # [T, S, N, D]
    weight = torch.zeros(N, D)
    weight[:, 3:] = 1.0
    weight[~free_nodes, 3:6] = 0.0
    noise = (Z.diff(dim=1).reshape(-1, D).pow(2).mean(0).sqrt() * args.noise).float()     # [D]
    # with --increments, each sample is a pair of consecutive snapshots (the same input noise on
    # both), and the change of the outputs between them is fitted too, relative to its own scale
    stride = 2 if args.increments > 0 else 1
    pairs = [(i, s) for i in range(T) for s in range(stride - 1, S)]
    increment_scale = target.diff(dim=1).pow(2).mean((0, 1, 2)).sqrt().clamp(min=1e-12).float()   # [D]
    # G's effect on the step's displacement, u1 = ... + (1 + c) S^-1 G1, and its scale in the data
    compliance = ((1.0 + prior.c) * prior.from_force).float()                          # [n, n] m/N
    scale32 = scale.float()
    du_true = prior.gather(G_true.reshape(T * S, N, 3).float()) @ compliance.T           # [T S, n]
    du_scale = du_true.pow(2).mean().sqrt()
    inc_du = (du_true.reshape(T, S, -1).diff(dim=1).pow(2).mean() / du_scale**2).clamp(min=1e-12)
    B = min(args.batch, len(pairs))
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    t_phase = time.perf_counter()
    while time.perf_counter() - t_phase < 60 * args.fit_minutes:
        epoch += 1
        perm, total, batches = torch.randperm(len(pairs), generator=gen), 0.0, 0
        gb = g.copies(B * stride)
        for k in range(0, len(pairs) - B + 1, B):
            decay(opt, t_phase, args.fit_minutes)
            i, s = zip(*(pairs[int(j)] for j in perm[k:k + B]))
            i, s = list(i) * stride, list(s) if stride == 1 else [x - 1 for x in s] + list(s)
            eps = torch.randn(B, N, D, generator=gen) * noise * free_nodes.float().view(1, N, 1)
            z = Z[i, s].float() + eps.repeat(stride, 1, 1)                       # [stride * B, N, D]
            r, _, _, _, _, degeneracy = net.rates((z * hybrid.seen.float()).reshape(-1, D),
                                                  F[i, s].float().reshape(-1, 3), gb.edge_index,
                                                  gb.node_type, gb.ref_pos.float(), True)
            r, y = r.reshape(-1, N, D), target[i, s].float()
            loss = 100.0 * ((r - y).pow(2) * weight).sum() / (weight.sum() * len(i)) + degeneracy
            if args.compliance > 0:              # the displacement the error in G causes [stride * B, n]
                du = prior.gather((r[..., 3:6] - y[..., 3:6]) * scale32[3:6]) @ compliance.T / du_scale
                loss = loss + 100.0 * args.compliance * du.pow(2).mean()
                if stride == 2:
                    du_change = (du[B:] - du[:B]).pow(2).mean() / inc_du
                    loss = loss + 100.0 * args.compliance * args.increments * du_change
            if stride == 2:                                                       # increments [B, N, D]
                dr, dy = (r[B:] - r[:B]) / increment_scale, (y[B:] - y[:B]) / increment_scale
                loss = loss + 100.0 * args.increments * ((dr - dy).pow(2) * weight).sum() / (weight.sum() * B)
            total, batches = total + descend(opt, loss), batches + 1
        validate("fit", total / batches)

    if args.fit_minutes > 0:                 # the fit's last weights (phase 2 goes on from them)
        with atomic_path(out / "fit.pt") as tmp:
            torch.save(net.state_dict(), tmp)

    # phase 2: whole rollouts, back-propagated through the linear solves
    group_scale = [(slice(0, 3), (Z[..., 0:3] - X).pow(2).mean().sqrt()),
                   (slice(3, 6), Z[..., 3:6].pow(2).mean().sqrt()),
                   (slice(6, 12), Z[..., 6:12].pow(2).mean().sqrt())]
    Bt = min(args.batch, T)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    t_phase = time.perf_counter()
    while time.perf_counter() - t_phase < 60 * args.rollout_minutes:
        epoch += 1
        perm, total, batches = torch.randperm(T, generator=gen), 0.0, 0
        for k in range(0, T - Bt + 1, Bt):
            decay(opt, t_phase, args.rollout_minutes)
            idx = perm[k:k + Bt]
            pred = hybrid.rollout(Z[idx, 0], F[idx], args.sweeps, train=True)   # [B, S, N, D]
            loss = sum(((pred[:, 1:, :, sl] - Z[idx, 1:, :, sl]) / sc).pow(2).mean() for sl, sc in group_scale)
            total, batches = total + descend(opt, loss), batches + 1
        validate("rollout", total / batches)

    net.load_state_dict(torch.load(out / "hybrid.pt", weights_only=True))
    results, ms = {}, {}
    for sweeps in sorted({1, 2, args.sweeps}):
        results[sweeps] = errors(hybrid, test, layout, sweeps)
        t = test[0]
        with torch.enable_grad():
            hybrid.rollout(t.z[:1], t.force[:3].unsqueeze(0), sweeps)
            t1 = time.perf_counter()
            hybrid.rollout(t.z[:1], t.force[:21].unsqueeze(0), sweeps)
            ms[sweeps] = 1e3 * (time.perf_counter() - t1) / (min(21, len(t.force)) - 1)
    lin = linear_baseline(data, test)                            # evaluate's own baseline rows
    result = {"hybrid": {str(k): {"snapshot": v[0], "whole": v[1], "ms_per_step": ms[k]} for k, v in results.items()},
              "linearised_fe": lin,
              "epochs": epoch, "best_val": best, "args": vars(args), "log": log}
    with atomic_path(out / "result.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    print(f"\ntest ({len(test)} trajectories)   per snapshot q / v / sigma      whole rollout q / v / sigma")
    rows = [("linearised FE", (lin["snapshot"], lin["whole"]), f"   {lin['ms_per_step']:.2f} ms/step")]
    rows += [(f"hybrid, {k} sweep(s)", v, f"   {ms[k]:.1f} ms/step") for k, v in results.items()]
    for name, (ps, wh), extra in rows:
        print(f"{name:24s} " + " / ".join(f"{ps[k]:.3g}" for k in layout.names) + "      "
              + " / ".join(f"{wh[k]:.3g}" for k in layout.names) + extra)
    print(f"{epoch} epochs ({args.threads} threads)")


if __name__ == "__main__":
    main()
