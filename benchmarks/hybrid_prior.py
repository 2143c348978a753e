"""Experiment (not yet a model option): the linearised FE step with a learned GENERIC correction
inside its solve, trained on whole rollouts. Prints test errors beside the linearised FE model.

Why (docs/accuracy.md, session 11): where a dataset's strain energy sits in modes its time step
does not resolve (the block: all of them), an explicit learned step must produce the tiny
remainder of a load and an elastic force that cancel; the linearised FE model alone
(``/linear`` in the dataset, ``thermognn.core.linear``) is then 10x more accurate than the learned
models. Here the step is the linear model's implicit trapezoidal (Crank-Nicolson) solve over the
free DOFs, C = alpha_M M + beta_K K, S = M + dt/2 C + dt^2/4 K::

    S v1 = (M - dt/2 C - dt^2/4 K) v0 - dt K u0 + dt (f0 + f1)/2 + dt g        [m/s]
    u1 = u0 + dt (v0 + v1)/2,   sigma1 = sigma0 + Sigma (u1 - u0) + dt r_sigma

with the network's GENERIC rates r = L dE/dz + M dS/dz at (z0, f1) read as a corrective nodal
force g [N] (v columns) and a stress rate r_sigma [Pa/s]; its q rate is unused. The solve spreads
the correction over the body, so the network only has to learn a local one (on the block 99.5 %
of the ideal g lies within 2 hops of the load). Trained on one step at a time it fails (the
linear step meets, from the data's nonlinear states, an imbalance it never meets in its own
rollout), so the loss is the whole rollout's, back-propagated through the linear solves.

Needs a dataset written by ``thermognn generate`` (with ``/linear``); torch and numpy only::

    .venv/bin/python benchmarks/hybrid_prior.py /tmp/b3/dataset.h5 --minutes 20 --out /tmp/hyb

The split is the one ``thermognn train`` uses (``train.split`` fractions, seed 0). The best
weights by validation go to ``<out>/hybrid.pt`` (state dict), the figures to ``<out>/result.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from thermognn.core.errors import DataError
from thermognn.core.io import atomic_path
from thermognn.train.data import compute_stats, load_data, velocity_columns
from thermognn.train.model import TIGNN, hyperparameters
from thermognn.train.rollout import rrmse_per_step, trajectory_error, trajectory_rrmse


class LinearPrior:
    """The Crank-Nicolson step of the linearised solid over its n free DOFs, as dense matrices
    in float64: v1 = P_v v0 + P_u u0 + P_f (f0 + f1) + P_g g [n], and the stress operator
    Sigma [6N, 3N] (zero columns at clamped DOFs)."""

    def __init__(self, linear, n_nodes: int, dt: float) -> None:
        dense = lambda A: torch.as_tensor(A.toarray() if hasattr(A, "toarray") else np.asarray(A))  # noqa: E731
        K, M = dense(linear.stiffness), dense(linear.mass)                               # [n, n]
        alpha_m, beta_k = linear.rayleigh
        C = alpha_m * M + beta_k * K
        S_inv = torch.linalg.inv(M + dt / 2 * C + dt**2 / 4 * K)
        self.P_v = S_inv @ (M - dt / 2 * C - dt**2 / 4 * K)
        self.P_u, self.P_f, self.P_g = -dt * S_inv @ K, dt / 2 * S_inv, dt * S_inv
        self.free = torch.as_tensor(linear.free)                                         # [3N] bool
        self.stress = torch.zeros(6 * n_nodes, 3 * n_nodes, dtype=torch.float64)
        if linear.stress is None:
            raise DataError("the dataset's /linear has no stress operator (P1 meshes only)")
        self.stress[:, self.free] = dense(linear.stress)
        self.dt = dt

    def to(self, dtype: torch.dtype) -> "LinearPrior":
        for k in ("P_v", "P_u", "P_f", "P_g", "stress"):
            setattr(self, k, getattr(self, k).to(dtype))
        return self

    def step(self, z0, f0, f1, rate, ref_pos):
        """z0 [B, N, D] (q, v, sigma), f0, f1 [B, N, 3] [N], rate [B, N, D] (SI: g in the v
        columns, r_sigma in sigma's) -> z1 [B, N, D]; clamped nodes keep q = X, v = 0."""
        B, N, D = z0.shape
        fr, dt = self.free, self.dt
        u0 = (z0[..., 0:3] - ref_pos).reshape(B, -1)[:, fr]                                 # [B, n]
        v0 = z0[..., 3:6].reshape(B, -1)[:, fr]
        v1 = (v0 @ self.P_v.T + u0 @ self.P_u.T + (f0 + f1).reshape(B, -1)[:, fr] @ self.P_f.T
              + rate[..., 3:6].reshape(B, -1)[:, fr] @ self.P_g.T)
        du = z0.new_zeros(B, 3 * N)                                                        # [B, 3N]
        du[:, fr] = dt / 2 * (v0 + v1)
        v = z0.new_zeros(B, 3 * N)
        v[:, fr] = v1
        sigma = z0[..., 6:12] + (du @ self.stress.T).reshape(B, N, 6) + dt * rate[..., 6:12]
        return torch.cat([z0[..., 0:3] + du.reshape(B, N, 3), v.reshape(B, N, 3), sigma], -1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset")
    ap.add_argument("--out", default="runs/hybrid")
    ap.add_argument("--minutes", type=float, default=20.0, help="training wall time")
    ap.add_argument("--lr", type=float, default=1e-3, help="Adam's rate, decayed 10x over the run")
    ap.add_argument("--batch", type=int, default=4, help="trajectories rolled out together")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    data = load_data(args.dataset, [0.8, 0.1, 0.1], args.seed, torch.float32)
    ds, g, dt, layout = data.dataset, data.graph, data.dt, data.layout
    if layout.names != ["q", "v", "sigma"]:
        raise DataError(f"{ds.path}: state_layout {layout.names}, this experiment needs q, v, sigma")
    linear = ds.linear_solid()
    if linear is None:
        raise DataError(f"{ds.path}: no /linear operators (regenerate it with thermognn generate)")
    N, D = g.n_nodes, layout.dim
    prior64 = LinearPrior(linear, N, dt)
    prior = LinearPrior(linear, N, dt).to(torch.float32)
    train, val, test = data.of("train"), data.of("val"), data.of("test")

    hp = hyperparameters(OmegaConf.create({"kinematics": "exact"}), D, velocity_columns(layout), False)
    model = TIGNN(**hp)
    stats = compute_stats(train, g, dt, hp)
    # the network's outputs are corrections: scale them by the ideal corrections from true states
    Z = torch.stack([t.z for t in train]).double()                                   # [T, S, N, D]
    F = torch.stack([t.force for t in train]).double()
    z0, z1 = Z[:, :-1].reshape(-1, N, D), Z[:, 1:].reshape(-1, N, D)
    f0, f1 = F[:, :-1].reshape(-1, N, 3), F[:, 1:].reshape(-1, N, 3)
    lin = prior64.step(z0, f0, f1, torch.zeros_like(z0), g.ref_pos.double())         # the prior alone
    fr = prior64.free
    g_ideal = torch.linalg.solve(prior64.P_g, (z1 - lin)[..., 3:6].reshape(len(z0), -1)[:, fr].T).T
    r_sigma = (z1 - lin)[..., 6:12] / dt
    scale = stats["dzdt_std"].clone()
    scale[3:6] = g_ideal.pow(2).mean().sqrt()
    scale[6:12] = r_sigma.reshape(-1, 6).pow(2).mean(0).sqrt()
    stats["dzdt_std"] = scale
    model.set_stats(stats)
    with torch.no_grad():                                   # start at the prior: small corrections
        for p in [*model.decoder.net[-1].parameters(), *model.port.parameters(),
                  *(p for dec in model.edge_decoders for p in dec.net[-1].parameters())]:
            p.mul_(0.01)

    def rollout(net, traj, pr, dtype):
        """The hybrid's rollout [S, N, D] from traj.z[0] under traj.force."""
        z = traj.z[0].to(dtype).unsqueeze(0)
        out = [z[0]]
        for s in range(1, traj.z.shape[0]):
            f = traj.force[s].to(dtype)
            rate = net.rates(z[0].float(), f.float(), g.edge_index, g.node_type, g.ref_pos, False)[0]
            rate = (rate.detach() * net.dzdt_std).to(dtype).unsqueeze(0)
            z = pr.step(z, traj.force[s - 1].to(dtype).unsqueeze(0), f.unsqueeze(0), rate, g.ref_pos.to(dtype))
            out.append(z[0])
        return torch.stack(out)

    def errors(net, trajs):
        per, whole = [], []
        with torch.enable_grad():
            for t in trajs:
                pred = rollout(net, t, prior64, torch.float64).float()
                per.append(trajectory_rrmse(rrmse_per_step(pred, t.z, layout)))
                whole.append(trajectory_error(pred, t.z, layout))
        mean = lambda rows: {k: float(np.mean([r[k] for r in rows])) for k in layout.names}  # noqa: E731
        return mean(per), mean(whole)

    # whole-rollout training: back-propagation through the linear solves
    group_scale = [(slice(0, 3), (Z[..., 0:3] - g.ref_pos.double()).pow(2).mean().sqrt().float()),
                   (slice(3, 6), Z[..., 3:6].pow(2).mean().sqrt().float()),
                   (slice(6, 12), Z[..., 6:12].pow(2).mean().sqrt().float())]
    Zf, Ff = Z.float(), F.float()
    B = min(args.batch, len(train))
    gb = g.copies(B)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    gen = torch.Generator().manual_seed(args.seed)
    best, log, t0, epoch = math.inf, [], time.perf_counter(), 0
    while time.perf_counter() - t0 < 60 * args.minutes:
        epoch += 1
        for group in opt.param_groups:
            group["lr"] = args.lr * 0.1 ** min((time.perf_counter() - t0) / (60 * args.minutes), 1.0)
        perm = torch.randperm(len(train), generator=gen)
        total, batches = 0.0, 0
        for i in range(0, len(train) - B + 1, B):
            idx = perm[i:i + B]
            z, loss = Zf[idx, 0], 0.0
            for s in range(1, Zf.shape[1]):
                r = model.rates(z.reshape(B * N, D), Ff[idx, s].reshape(B * N, 3), gb.edge_index, gb.node_type,
                                gb.ref_pos, True)[0]
                z = prior.step(z, Ff[idx, s - 1], Ff[idx, s], (r * model.dzdt_std).reshape(B, N, D), g.ref_pos)
                loss = loss + sum(((z[..., sl] - Zf[idx, s][..., sl]) / sc).pow(2).mean() for sl, sc in group_scale)
            loss = loss / (Zf.shape[1] - 1)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
            opt.step()
            total, batches = total + float(loss.detach()), batches + 1
        v_whole = errors(model, val)[1]
        val_error = float(np.mean(list(v_whole.values())))
        if val_error < best:
            best = val_error
            with atomic_path(out / "hybrid.pt") as tmp:
                torch.save(model.state_dict(), tmp)
        log.append({"epoch": epoch, "seconds": time.perf_counter() - t0, "loss": total / batches, "val": val_error,
                    **v_whole})
        print(f"epoch {epoch:3d} {log[-1]['seconds']:6.0f} s  loss {total / batches:.3e}  val {val_error:.4f}  "
              + " ".join(f"{k} {v:.3g}" for k, v in v_whole.items()), flush=True)

    model.load_state_dict(torch.load(out / "hybrid.pt", weights_only=True))
    hybrid = errors(model, test)
    X = g.ref_pos.double().numpy()
    lin_rows = []
    for t in test:
        pred = torch.as_tensor(linear.rollout_states(t.z.double().numpy(), t.force.double().numpy(), X, layout, dt))
        lin_rows.append((trajectory_rrmse(rrmse_per_step(pred.float(), t.z, layout)), trajectory_error(pred.float(), t.z, layout)))
    lin_mean = [{k: float(np.mean([r[j][k] for r in lin_rows])) for k in layout.names} for j in (0, 1)]
    t = test[0]
    z5, f4, f5 = t.z[5].double().unsqueeze(0), t.force[4].double().unsqueeze(0), t.force[5].double().unsqueeze(0)

    def one_step():                                     # one hybrid step as a rollout takes it
        rate = model.rates(t.z[5], t.force[5], g.edge_index, g.node_type, g.ref_pos, False)[0]
        return prior64.step(z5, f4, f5, (rate.detach() * model.dzdt_std).double().unsqueeze(0), g.ref_pos.double())

    with torch.enable_grad():
        for _ in range(3):
            one_step()
        t1 = time.perf_counter()
        for _ in range(20):
            one_step()
    ms = 1e3 * (time.perf_counter() - t1) / 20
    result = {"hybrid": {"snapshot": hybrid[0], "whole": hybrid[1]},
              "linearised_fe": {"snapshot": lin_mean[0], "whole": lin_mean[1]},
              "ms_per_step": ms, "epochs": epoch, "minutes": args.minutes, "best_val": best, "log": log}
    with atomic_path(out / "result.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    print(f"\ntest ({len(test)} trajectories)          per snapshot q / v / sigma        whole rollout q / v / sigma")
    for name, (ps, wh) in (("linearised FE", lin_mean), ("hybrid", hybrid)):
        print(f"{name:24s} " + " / ".join(f"{ps[k]:.3g}" for k in layout.names) + "      "
              + " / ".join(f"{wh[k]:.3g}" for k in layout.names))
    print(f"hybrid: {ms:.1f} ms per step ({args.threads} threads), {epoch} epochs in {args.minutes:g} min")


if __name__ == "__main__":
    main()
