"""Rollouts of a trained integrator and the paper's relative error metric."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from thermognn.core.state import StateLayout

from .data import Graph, TrajectoryTensors
from .hybrid import LinearPriorModel
from .prior import DIVERGED, RAN_AWAY, state_reach, stop_if_run_away

#: a validation rollout whose state exceeds this many times its trajectory's largest in any column
#: (the positions' as displacements) is stopped there and counted diverged (``validation_error``):
#: its error is already over 900 %, and a runaway's later steps cost most (the bunny's learned law
#: on traj_14, the FE cut 205 times: 4.4e9 after 2882 s of validation, session 86)
RUNAWAY_FACTOR = 10.0


def rollout(model, graph: Graph, z0: Tensor, forces: Tensor, dt: float, steps: int | None = None,
            bound: Tensor | None = None) -> Tensor:
    """Integrate from z0 [N, D] with the loads forces [S, N, 3] (force[s] drives z[s-1] -> z[s]).

    Returns z [S, N, D] (z[0] = z0 with the clamped nodes imposed). ``steps`` (default S - 1)
    may exceed S - 1: the last load is then held. ``bound`` [D]: a state past it (each column's
    largest |z|, the positions' as displacements, ``prior.stop_if_run_away``) stops the rollout with a
    RuntimeError holding ``RAN_AWAY``."""
    steps = forces.shape[0] - 1 if steps is None else steps
    if isinstance(model, LinearPriorModel):  # the linearised FE step, carrying a and G between steps
        # weights frozen meanwhile: else every step's solve hangs on their graph until the rollout
        # ends (the bunny's corotated prior: 24 GB by a 30-step validation rollout, killed)
        weights = [p for p in model.parameters() if p.requires_grad]
        try:
            for p in weights:
                p.requires_grad_(False)
            with torch.enable_grad():
                pred = model.rollouts(z0.unsqueeze(0), forces.unsqueeze(0), graph.edge_index, graph.node_type,
                                      graph.ref_pos, steps, False, bound)[0]
        finally:
            for p in weights:
                p.requires_grad_(True)
        return pred.detach().to(z0.dtype)
    dt_t = torch.tensor(dt, dtype=z0.dtype)
    loads = [forces[min(s, forces.shape[0] - 1)] for s in range(steps + 1)]      # each state's load [N, 3]
    out = [model.impose(z0, graph.node_type, graph.ref_pos)]
    with torch.enable_grad():  # the model differentiates E and S: never under no_grad
        for s in range(1, steps + 1):
            out.append(model.step(out[-1], loads[s], graph.edge_index, graph.node_type, graph.ref_pos, dt_t).detach())
            if bound is not None:
                stop_if_run_away(out[-1], graph.ref_pos, bound, s)
    if getattr(model, "use_readout", False):    # the stress reported: read off the positions (and loads)
        return read_off(torch.stack(out), model.readout, graph, forces)
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
        out[name] = r.cpu().numpy()
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


def read_off(pred: Tensor, readout, graph: Graph, forces: Tensor) -> Tensor:
    """A rollout pred [S, N, D] with its stress columns read off its positions by ``readout``
    (a ``StressReadout``), state s under the load ``rollout`` stepped it with, forces[min(s, F-1)]
    [N, 3]: the stress the product reports (``TIGNN.read_stress``, state by state), from the model's
    own readout (``rollout``) or from one kept apart (``validation_error``)."""
    cols = list(readout.columns)
    S = pred.shape[0]
    loads = forces[torch.arange(S, device=forces.device).clamp(max=forces.shape[0] - 1)]   # [S, N, 3]
    with torch.no_grad():                # read in chunks of snapshots: the stencil gathers K nodes each
        read = torch.cat([readout(pred[a: a + 64, :, :3] - graph.ref_pos, loads[a: a + 64])
                          for a in range(0, S, 64)])                                  # [S, N, C]
    out = pred.clone()
    out[:, :, cols] = read.to(out.dtype)
    return out


def runaway_bound(z: Tensor, ref_pos: Tensor, layout: StateLayout) -> Tensor:
    """[D] ``RUNAWAY_FACTOR`` times a trajectory's z [S, N, D] largest |z| in each variable group
    (the positions' as displacements from ref_pos [N, 3] m; a group that stays zero: 1e-12):
    ``validation_error``'s bound on its rollout."""
    reach = state_reach(z, ref_pos).double()                                                # [D]
    bound = torch.empty_like(reach)
    for name in layout.names:
        sl = layout.slice(name)
        bound[sl] = RUNAWAY_FACTOR * max(float(reach[sl].max()), 1e-12)
    return bound


def validation_error(model, graph: Graph, trajs: list[TrajectoryTensors], layout: StateLayout, dt: float,
                     readout=None) -> float:
    """One number for model selection and early stopping: :func:`trajectory_error` of the rollouts
    from each trajectory's initial state, averaged over the finite groups and the trajectories
    (inf if none is finite, where the corotated prior's rollout diverges, or where a rollout runs
    away, past ``runaway_bound``: it is stopped there, and the run goes on). With ``readout`` the
    rollouts' stress is read off their positions by it (:func:`read_off`)."""
    vals = []
    for t in trajs:
        try:
            pred = rollout(model, graph, t.z[0], t.force, dt, bound=runaway_bound(t.z, graph.ref_pos, layout))
            if readout is not None:
                pred = read_off(pred, readout, graph, t.force)
            errors = trajectory_error(pred, t.z, layout)
        except RuntimeError as exc:          # the corotated prior met a non-finite state, or it ran away
            if DIVERGED not in str(exc) and RAN_AWAY not in str(exc):
                raise
            return float("inf")
        vals += [v for v in errors.values() if math.isfinite(v)]
    return float(np.mean(vals)) if vals else float("inf")


#: at most this many snapshots are stepped together in :func:`one_step_errors` (disjoint mesh
#: copies in one pass) ...
ONE_STEP_CHUNK = 16
#: ... and at most this many nodes in all: larger passes are slower per snapshot on a CPU
#: (bunny, 1911 nodes, 1 thread: 3021 ms a snapshot in chunks of 16, 1685 in 4, 1279 alone)
ONE_STEP_NODES = 2048


def one_step_errors(model, graph: Graph, trajs: list[TrajectoryTensors], layout: StateLayout,
                    dt: float, linear_fe: bool = False) -> tuple[dict[str, float], dict[str, np.ndarray]]:
    """How well one step is learned, apart from any drift: every true state z[s] is stepped once
    (the model's own step: its integrator and kinematics, clamped nodes imposed) and the step's
    change compared with the data's, ||dz_pred - dz_gt|| / ||dz_gt|| per group with
    dz = z[s+1] - z[s] (dimensionless).

    Returns (the ratio over all steps, nodes and trajectories per group; per step, the ratio
    over the nodes and trajectories of that step, {group: [S - 1]}); NaN where the data's group
    does not change. A ``LinearPriorModel`` steps each true state with the data's own Newmark
    acceleration there (``LinearPriorModel.accelerations``) and the network's G; with ``linear_fe``
    its prior alone (G = H = 0, no network): the linearised FE model's own one step, the figure to
    compare with. A rollout error far above this one comes from the rollout drifting off the data;
    a one-step error near 1 means the step itself is not learned. Where the body moves nearly
    quasi-statically, a step's change is a small difference of large forces and the ratio can
    exceed 1 for a model whose rollouts track (the liver's linearised FE model: q 1.55, v 7.21,
    its rollouts 3 % and 46 %; docs/accuracy.md, session 41). Up to ``ONE_STEP_CHUNK``
    snapshots, and ``ONE_STEP_NODES`` nodes, go through the network in one pass, on disjoint copies
    of the mesh."""
    if linear_fe and not isinstance(model, LinearPriorModel):
        raise ValueError("one_step_errors(linear_fe=True) needs a LinearPriorModel (model.prior=linear), "
                         f"got {type(model).__name__}")
    steps = max((t.z.shape[0] - 1 for t in trajs), default=0)
    num = {g: np.zeros(steps) for g in layout.names}
    den = {g: np.zeros(steps) for g in layout.names}
    N = graph.n_nodes
    chunk = max(1, min(ONE_STEP_CHUNK, ONE_STEP_NODES // max(N, 1)))
    copies: dict[int, Graph] = {}                  # k -> k mesh copies (a full chunk, a short tail)
    with torch.enable_grad():                      # the model differentiates E and S
        for t in trajs:
            S = t.z.shape[0] - 1
            dt_t = torch.tensor(dt, dtype=t.z.dtype)
            if isinstance(model, LinearPriorModel):        # Newmark's a along the trajectory [S + 1, n]
                accelerations = model.accelerations(t.z, t.force)
                internal = model.trajectory_internal_variables(t.z)             # [S + 1, T, n + 6N]
                seen = model.trajectory_inputs(t.z)           # what the network sees of each state [S + 1, N, D]
            for s0 in range(0, S, chunk):
                k = min(chunk, S - s0)
                if k not in copies:
                    copies[k] = graph.copies(k)
                many = copies[k]
                z = t.z[s0: s0 + k]                                                     # [k, N, D]
                f = t.force[s0 + 1: s0 + k + 1]                                         # [k, N, 3]
                if isinstance(model, LinearPriorModel):   # the true state with the data's own Newmark a
                    mesh = (many.edge_index, many.node_type, many.ref_pos)
                    h = internal[s0: s0 + k]
                    u, v, H = model.unpack(z.double(), h)
                    if linear_fe:                                   # the prior alone: G = H = 0
                        G0 = torch.zeros_like(u)
                        f1 = model.prior.gather(f.to(torch.float64))
                        u, v, _, h = model.prior.step(u, v, accelerations[s0: s0 + k], f1, G0, G0, h,
                                                      model.start_loads(t.force[s0: s0 + k]))
                        H = torch.zeros_like(H)
                    else:
                        G, _ = model.remainders(seen[s0: s0 + k], t.force[s0: s0 + k], *mesh, False)
                        u, v, _, _, H, h = model.advance(u, v, accelerations[s0: s0 + k], G, H, h, f, *mesh,
                                                         False, None, t.force[s0: s0 + k])
                    z_next = model.state(u, v, H, h).to(z.dtype)
                else:
                    z_next = model.step(z.reshape(k * N, -1), f.reshape(k * N, -1), many.edge_index,
                                        many.node_type, many.ref_pos, dt_t).detach().reshape(k, N, -1)
                miss = (z_next - t.z[s0 + 1: s0 + k + 1]).double()                      # [k, N, D]
                change = (t.z[s0 + 1: s0 + k + 1] - z).double()
                for g in layout.names:
                    sl = layout.slice(g)
                    num[g][s0: s0 + k] += miss[:, :, sl].pow(2).flatten(1).sum(1).cpu().numpy()
                    den[g][s0: s0 + k] += change[:, :, sl].pow(2).flatten(1).sum(1).cpu().numpy()

    def ratio(a, b):
        return np.where(b > 0, np.sqrt(a / np.where(b > 0, b, 1.0)), np.nan)

    whole = {g: float(ratio(num[g].sum(), den[g].sum())) for g in layout.names}
    return whole, {g: ratio(num[g], den[g]) for g in layout.names}
