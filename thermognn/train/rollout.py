"""Rollouts of a trained integrator and the paper's relative error metric."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from thermognn.core.state import StateLayout

from .data import Graph, TrajectoryTensors


def rollout(model, graph: Graph, z0: Tensor, forces: Tensor, dt: float, steps: int | None = None) -> Tensor:
    """Integrate from z0 [N, D] with the loads forces [S, N, 3] (force[s] drives z[s-1] -> z[s]).

    Returns z [S, N, D] (z[0] = z0 with the clamped nodes imposed). ``steps`` (default S - 1)
    may exceed S - 1: the last load is then held."""
    steps = forces.shape[0] - 1 if steps is None else steps
    dt_t = torch.tensor(dt, dtype=z0.dtype)
    out = [model.impose(z0, graph.node_type, graph.ref_pos)]
    with torch.enable_grad():  # the model differentiates E and S: never under no_grad
        for s in range(1, steps + 1):
            f = forces[min(s, forces.shape[0] - 1)]
            out.append(model.step(out[-1], f, graph.edge_index, graph.node_type, graph.ref_pos, dt_t).detach())
    return torch.stack(out)


def rrmse_per_step(pred: Tensor, truth: Tensor, layout: StateLayout) -> dict[str, np.ndarray]:
    """Relative L2 error per snapshot and variable group: ||z_pred - z_gt|| / ||z_gt|| over all
    nodes of the group. pred, truth [S, N, D] -> {group: [S]} (NaN where ||z_gt|| = 0, e.g. t = 0)."""
    out = {}
    for name in layout.names:
        sl = layout.slice(name)
        num = (pred[:, :, sl] - truth[:, :, sl]).double().flatten(1).norm(dim=1)
        den = truth[:, :, sl].double().flatten(1).norm(dim=1)
        r = torch.where(den > 1e-300, num / den.clamp(min=1e-300), torch.full_like(num, math.nan))
        out[name] = r.numpy()
    return out


def trajectory_rrmse(per_step: dict[str, np.ndarray]) -> dict[str, float]:
    """Average over the rollout steps s >= 1 (NaN steps skipped)."""
    res = {}
    for k, v in per_step.items():
        v = v[1:]
        v = v[np.isfinite(v)]
        res[k] = float(v.mean()) if v.size else float("nan")
    return res


def rollout_errors(model, graph: Graph, trajs: list[TrajectoryTensors], layout: StateLayout,
                   dt: float) -> tuple[dict[str, float], list[dict[str, float]], list[dict[str, np.ndarray]]]:
    """Roll out every trajectory from its initial state. Returns (mean RRMSE per group over the
    trajectories, per-trajectory RRMSE, per-step RRMSE per trajectory)."""
    per_traj, per_step = [], []
    for t in trajs:
        pred = rollout(model, graph, t.z[0], t.force, dt)
        ps = rrmse_per_step(pred, t.z, layout)
        per_step.append(ps)
        per_traj.append(trajectory_rrmse(ps))
    mean = {k: float(np.nanmean([r[k] for r in per_traj])) if per_traj else float("nan")
            for k in layout.names}
    return mean, per_traj, per_step


def trajectory_error(pred: Tensor, truth: Tensor, layout: StateLayout) -> dict[str, float]:
    """||z_pred - z_gt|| / ||z_gt|| over all steps s >= 1 and nodes of each group of one rollout
    (pred, truth [S, N, D]): unlike the per-snapshot mean it stays meaningful where a group passes
    near zero (the velocity of a body coming to rest)."""
    out = {}
    for name in layout.names:
        sl = layout.slice(name)
        num = (pred[1:, :, sl] - truth[1:, :, sl]).double().norm()
        den = truth[1:, :, sl].double().norm()
        out[name] = float(num / den) if float(den) > 0 else float("nan")
    return out


def validation_error(model, graph: Graph, trajs: list[TrajectoryTensors], layout: StateLayout, dt: float) -> float:
    """One number for model selection and early stopping: :func:`trajectory_error` of the rollouts
    from each trajectory's initial state, averaged over the finite groups and the trajectories
    (inf if none is finite)."""
    vals = []
    for t in trajs:
        errors = trajectory_error(rollout(model, graph, t.z[0], t.force, dt), t.z, layout)
        vals += [v for v in errors.values() if math.isfinite(v)]
    return float(np.mean(vals)) if vals else float("inf")
