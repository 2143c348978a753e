"""Evaluate a trained model: rollouts of the test (and some training) trajectories from their
initial states, relative errors per variable group, figures and tables in ``cfg.paths.eval_dir``.

Files written (all atomically)::

    rrmse_vs_time.csv / .png        mean RRMSE over the test trajectories per step and group (paper Fig. 8)
    rrmse_per_trajectory.csv / .png per-trajectory errors (per snapshot and whole rollout) with each
                                    trajectory's peak load and load point (and the linearised FE model's
                                    whole-rollout errors); box plots of the per-snapshot ones, train vs test
    one_step_vs_time.csv            one step from each true state: error of its change per step and group
                                    (what the network learned, apart from the rollout's drift)
    energy_entropy.csv / .png       learned E, S and the degeneracy residual along each test rollout (a law
                                    prior's: the law's energy, the loads' work and what the body absorbed)
    rest_drift.csv                  the unloaded body left at rest for 10x the horizon: how far it drifts
                                    (the summary adds the growth factor of a disturbance at rest)
    snapshot_<traj>_<step>.vtu      predicted vs ground truth point data (datasets with tets only)
    summary.md                      the numbers above in one page (and, for datasets made with a list of
                                    load magnitudes, the test errors at each peak load; test trajectories
                                    that repeat training ones up to a mirror of the mesh, named)
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from thermognn.core.config import project_path
from thermognn.core.corotated import CorotatedSolid
from thermognn.core.hyperelastic import HyperelasticSolid
from thermognn.core.errors import ConfigError, DataError
from thermognn.core.io import atomic_path
from thermognn.core.schema import Dataset
from thermognn.core.state import describe_step

from .checkpoint import (law_phrase, load_checkpoint, model_from_checkpoint, model_step, served_law_hht,
                         served_law_settings, torch_dtype, with_law_rollout, with_rollout)
from .data import (Graph, LoadedData, TrajectoryTensors, check_fingerprint, load_data, rest_trajectory,
                   spread, velocity_columns)
from .loop import held_out_sentence, print_rrmse_table, rest_growth
from .device import cpu_randn
from .hybrid import LinearPriorModel
from .law_prior import HyperelasticNewmarkPrior
from .prior import CorotatedNewmarkPrior
from .model import parameter_count, readout_weight_count
from .rollout import one_step_errors, rollout, rrmse_per_step, trajectory_error, trajectory_rrmse


def _write_csv(path: Path, header: list[str], rows: list[list]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            w.writerows(rows)


def _save_fig(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    plt.close(fig)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _fmt(x: float) -> str:
    return f"{x:.3e}" if math.isfinite(x) else "nan"


def energy_entropy_along(model, graph: Graph, pred: torch.Tensor, forces: torch.Tensor, dt: float) -> np.ndarray:
    """[S, 4]: learned E, S, the degeneracy residual ||L dS/dw||^2 + ||M dE/dw||^2 (mean over
    nodes, balanced units) and the step's energy error E_s - E_{s-1} - dt P((z_{s-1} + z_s) / 2)
    (0 at s = 0) at every state of a rollout pred [S, N, D], with the load f_s of the step: the
    change of the learned energy that the port's power P does not account for. The continuous
    dynamics make it zero for Hamiltonian (and exactly degenerate GENERIC) models; what remains
    is the integrator's drift plus the port-power quadrature (and, for GENERIC models, the
    energy M moves where the learned degeneracy is not exact)."""
    rows = []
    g = graph
    with torch.enable_grad():
        for s in range(pred.shape[0]):
            f = forces[min(s, forces.shape[0] - 1)]
            e, s_ = model.energy_entropy(pred[s], g.edge_index, g.node_type, g.ref_pos, f)
            deg = model.rates(pred[s], f, g.edge_index, g.node_type, g.ref_pos, False, False)[5]
            err = 0.0
            if s > 0:
                e_prev = model.energy_entropy(pred[s - 1], g.edge_index, g.node_type, g.ref_pos, f)[0]
                power = model.energy_power(0.5 * (pred[s - 1] + pred[s]), f, g.edge_index, g.node_type, g.ref_pos)[2]
                err = float((e - e_prev - dt * power).detach())
            rows.append([float(e.detach()), float(s_.detach()), float(deg.detach()), err])
    return np.asarray(rows)


#: energy_entropy.csv's columns after the step and time (a graph network's E and S, a law's energy)
ENERGY_COLUMNS = ["energy", "entropy", "degeneracy", "energy_error", "work", "absorbed"]
#: absorbed energy this far below zero, over the largest work, still reads as passive (the
#: trapezoidal work's error over a step of a curved law)
PASSIVE_TOL = 1e-6


def law_energy_along(prior, X: torch.Tensor, z: torch.Tensor, forces: torch.Tensor) -> np.ndarray:
    """[S, 6] in ``ENERGY_COLUMNS``' order along states z [S, N, D] (positions q [m] and velocities
    v [m/s] first) under nodal loads ``forces`` [S, N, 3] N, for a law prior's rollout or the data
    it follows (``HyperelasticNewmarkPrior``, X [N, 3] m its reference positions):

    - energy E_s = ½ vᵀ M v + Σ_e V_e (Ψ_vol + g∞ Ψ_iso) − f_body · u [J] (``prior.energy``);
    - entropy and degeneracy nan: the law has no learned S, L or M;
    - work W_s = Σ_k≤s ½ (f_k−1 + f_k) · (u_k − u_k−1) [J], the loads' work by the trapezoidal rule
      (Newmark's average acceleration balances exactly that against ½ vᵀ M v and the internal
      forces' trapezoidal work, so only the law's curvature over a step is left);
    - absorbed A_s = W_s − (E_s − E_0) [J]: what the loads put in that the body no longer holds
      as kinetic or elastic energy, dissipated or held in its Prony terms; ≥ 0 at every step for a
      passive body (one that never gives back more than it took, the condition for stable haptic
      rendering), 0 up to the integrator's drift for an elastic, undamped law;
    - energy_error E_s − E_s−1 − (W_s − W_s−1) (0 at s = 0): −(A_s − A_s−1)."""
    with torch.no_grad():
        dtype = prior.cell_volume.dtype
        zz = z.to(dtype)
        u = prior.gather(zz[..., 0:3] - torch.as_tensor(X, dtype=dtype))                        # [S, n]
        v = prior.gather(zz[..., 3:6]) if zz.shape[-1] >= 6 else torch.zeros_like(u)
        f = prior.gather(forces.to(dtype))                                                      # [S, n]
        kinetic, potential = prior.energy(u, v)
        E = (kinetic + potential).numpy()
        steps = (0.5 * (f[1:] + f[:-1]) * (u[1:] - u[:-1])).sum(-1).numpy()                    # [S - 1]
    W = np.concatenate([[0.0], np.cumsum(steps)])
    error = np.concatenate([[0.0], np.diff(E) - steps])
    nan = np.full_like(E, np.nan)
    return np.stack([E, nan, nan, error, W, W - (E - E[0])], axis=1)


def law_energy_figures(pred_rows: list[np.ndarray], data_rows: list[np.ndarray]) -> dict:
    """From ``law_energy_along``'s rows of the test rollouts and of their data under the same law,
    each trajectory's absorbed energy over the largest |work| along it, W_max: ``law_work`` (the
    largest W_max [J]); ``law_absorbed_least`` and ``law_data_absorbed_least`` (the least absorbed
    share after the start: ≥ 0 passive); ``law_absorbed_end`` (the share at the end, mean over the
    trajectories); ``law_drift`` and ``law_data_drift`` (the largest |absorbed| share: an elastic,
    undamped law's drift) and ``law_energy_off`` (max_s |E_pred − E_data| / max_s |E_data|, mean over
    the trajectories)."""
    def shares(r: np.ndarray) -> np.ndarray:                      # A_s / W_max of one trajectory [S]
        return r[:, 5] / max(float(np.nanmax(np.abs(r[:, 4]))), 1e-300)

    least = lambda rows: min(float(np.nanmin(shares(r)[1:])) for r in rows)  # noqa: E731
    drift = lambda rows: max(float(np.nanmax(np.abs(shares(r)))) for r in rows)  # noqa: E731
    off = [float(np.nanmax(np.abs(p[:, 0] - d[:, 0]))) / max(float(np.nanmax(np.abs(d[:, 0]))), 1e-300)
           for p, d in zip(pred_rows, data_rows)]
    return {"law_work": max(float(np.nanmax(np.abs(r[:, 4]))) for r in pred_rows),
            "law_absorbed_least": least(pred_rows), "law_data_absorbed_least": least(data_rows),
            "law_absorbed_end": float(np.mean([shares(r)[-1] for r in pred_rows])),
            "law_drift": drift(pred_rows), "law_data_drift": drift(data_rows), "law_energy_off": float(np.mean(off))}


def law_energy_sentence(fig: dict, elastic: bool) -> str:
    """One line of ``law_energy_figures``' ``fig`` (``elastic``: an elastic, undamped law)."""
    if elastic:
        held = (f"an elastic, undamped law: its energy changes by the loads' work up to the integrator's drift, "
                f"at most {_fmt(fig['law_drift'])} of a trajectory's largest work (the data under the same law: "
                f"{_fmt(fig['law_data_drift'])})")
    else:
        held = (f"the energy the body absorbed (W - (E - E_0): dissipated or held in its Prony terms) is at "
                f"least {_fmt(fig['law_absorbed_least'])} of a trajectory's largest work at every step after the "
                "start" + (" (passive: it never gives back more than the loads put in)"
                           if fig["law_absorbed_least"] >= -PASSIVE_TOL else
                           " (below zero: the model gave back more energy than the loads put in)")
                + f" and {_fmt(fig['law_absorbed_end'])} at the end (mean); the data under the same law: "
                f"{_fmt(fig['law_data_absorbed_least'])} at least")
    return (f"law energy: along the test rollouts the loads do up to {_fmt(fig['law_work'])} J of work; {held}; "
            f"the rollouts' energy E = kinetic + strain - body force . u is off the data's (under the same law) "
            f"by {_fmt(fig['law_energy_off'])} of its largest, mean over the trajectories "
            "(`energy_entropy.csv`: energy, work, absorbed)")


def energy_balance(rows: list[np.ndarray]) -> float:
    """sum |energy error| / sum |E_s - E_{s-1}| over rollouts (arrays of :func:`energy_entropy_along`)."""
    err = sum(float(np.abs(r[1:, 3]).sum()) for r in rows)
    change = sum(float(np.abs(np.diff(r[:, 0])).sum()) for r in rows)
    return err / change if change > 0 else float("nan")


def write_vtu(path: Path, ds: Dataset, traj: TrajectoryTensors, pred: torch.Tensor, step: int) -> None:
    """Predicted vs ground-truth point data at one snapshot on the reference mesh (ParaView:
    'Warp By Vector' with u_pred or u_true shows the deformed shapes)."""
    import meshio

    layout = ds.layout
    X = ds.mesh.nodes
    point_data = {"node_type": np.asarray(ds.mesh.node_type, np.int32)}
    z_pred, z_true = pred[step].double().cpu().numpy(), traj.z[step].double().cpu().numpy()   # [N, D]
    for label, z in (("pred", z_pred), ("true", z_true)):
        point_data[f"u_{label}"] = z[:, 0:3] - X
        for name in layout.names[1:]:
            point_data[f"{name}_{label}"] = z[:, layout.slice(name)]
    for name in layout.names:
        sl = layout.slice(name)
        point_data[f"{name}_error"] = np.linalg.norm(z_pred[:, sl] - z_true[:, sl], axis=1)
    mesh = meshio.Mesh(X, [("tetra", np.asarray(ds.mesh.tets, np.int64))], point_data=point_data)
    with atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")


#: the rest-drift rollout is this many times the data's horizon
REST_HORIZONS = 10


def rest_drift(model, graph: Graph, rest: TrajectoryTensors, steps: int, velocity_cols: list[int]) -> np.ndarray:
    """Leave the unloaded body at rest (``rest.z[0]``, zero force) for ``steps`` steps, as ``serve``
    does while nothing touches it. Returns [steps + 1, 2] per step: the largest displacement from
    the start over all nodes, max |q - q0| (m), and the largest velocity entry, max |v| (m/s).
    A body at rest in its reference configuration stays there; a model with exact kinematics
    integrates any rate bias at rest into a drift (``train.rest_samples`` trains against it)."""
    dt = float(rest.time[1] - rest.time[0])
    pred = rollout(model, graph, rest.z[0], rest.force[:1], dt, steps)      # [steps + 1, N, D]
    q = (pred[:, :, 0:3] - pred[:1, :, 0:3]).abs().flatten(1).amax(1)
    v = pred[:, :, velocity_cols].abs().flatten(1).amax(1) if velocity_cols else torch.zeros_like(q)
    return torch.stack([q, v], 1).double().cpu().numpy()


#: power iterations for the growth factor at rest
REST_POWER_ITERATIONS = 40
#: disturbances of the rest state evaluate probes, RMS per free entry in typical steps' changes:
#: the linear step (0.3), and the sizes a drift reaches before it shows (3, 30)
REST_PROBE_SIZES = (0.3, 3.0, 30.0)


def rest_growth_factors(model, graph: Graph, rest: TrajectoryTensors, dt: float,
                        sizes=REST_PROBE_SIZES, iterations: int = REST_POWER_ITERATIONS) -> dict[float, float]:
    """The factor by which one step of the model multiplies a disturbance of the unloaded rest
    state of RMS ``size`` typical steps per free entry, along its fastest-growing mode, for each
    of ``sizes`` ({size: g}): the power iterations of ``loop.rest_growth``, the probe
    ``train.rest_stability`` trains against, all sizes in one pass per iteration, each started
    from the same seeded direction. Above 1 the rest state is unstable at that size: the drift
    grows geometrically from any rate bias; at or below 1 it stays bounded."""
    start = cpu_randn((1, *rest.z.shape[1:]), torch.Generator().manual_seed(0), rest.z)
    direction = start.repeat(len(sizes), 1, 1)                          # [K, N, D]
    growth = torch.full((len(sizes),), math.nan)
    for _ in range(iterations):
        growth, direction = rest_growth(model, rest, graph, dt, direction, sizes, create_graph=False)
    return {size: float(g) for size, g in zip(sizes, growth.detach())}


def shortened_updates(model) -> torch.Tensor | None:
    """The law prior's count of shortened Newton updates (``HyperelasticNewmarkPrior.admissible``:
    where the budget would have crushed a cell), a 0-dim tensor to read and zero; None for
    other models."""
    prior = getattr(model, "prior", None)
    return prior.shortened if isinstance(prior, HyperelasticNewmarkPrior) else None


def shortened_sentence(names: list[str], counts: list[int]) -> str:
    """"the law prior shortened Newton updates on traj_136 (41), ...: ..." for the rollouts in
    which it did, else ""."""
    cases = [f"{n} ({c})" for n, c in zip(names, counts) if c]
    if not cases:
        return ""
    return ("the law prior shortened Newton updates that would have crushed or inverted a cell on "
            + ", ".join(cases) + ": its iteration budget does not hold those steps, and their rollouts "
            "are not the law's")


def newton_sentence(budget: int, most: int, taken: int, steps: int, unconverged: int, cut: int = 0,
                    step_cuts: int = 0) -> str:
    """"the law prior took 4.21 Newton iterations a step (1 at least, 8 at most a solve, over 1360
    prior steps)", how many steps it cut into sub-steps (``model.prior_step_cuts``; their tries'
    iterations included), and how many spent the most without converging where any did, from the
    law prior's ``newton_taken`` counts (iterations, prior steps, such steps, cut steps)."""
    text = (f"the law prior took {taken / max(steps, 1):.2f} Newton iterations a step ({budget} at least, {most} "
            f"at most a solve, over {steps} prior steps)")
    if cut:
        text += (f"; it cut {cut} step{'s' if cut > 1 else ''} that had not converged after {most} into "
                 f"sub-steps (down to Δt/{2 ** step_cuts}), their tries' iterations included")
    if unconverged:
        where = f" (at Δt/{2 ** step_cuts})" if step_cuts else ""
        text += (f"; {unconverged} step{'s' if unconverged > 1 else ''} had not converged after {most}{where}: those "
                 f"rollouts are not the law's" + ("" if step_cuts else " (where the FE itself cut a step, no number "
                                                 "of full steps converges: model.prior_step_cuts)"))
    return text


def _rollouts(model, data: LoadedData, trajs: list[TrajectoryTensors]):
    """Roll out each trajectory; returns predictions, per-step and per-trajectory RRMSE, the
    mean wall time per step [ms] and, per trajectory, how many updates the law prior shortened
    (:func:`shortened_updates`; zeros for other models)."""
    preds, per_step, per_traj, shortened = [], [], [], []
    elapsed, steps = 0.0, 0
    counter = shortened_updates(model)
    for t in trajs:
        if counter is not None:
            counter.zero_()
        t0 = time.perf_counter()
        pred = rollout(model, data.graph, t.z[0], t.force, data.dt)
        elapsed += time.perf_counter() - t0
        shortened.append(int(counter) if counter is not None else 0)
        steps += pred.shape[0] - 1
        ps = rrmse_per_step(pred, t.z, data.layout)
        preds.append(pred)
        per_step.append(ps)
        per_traj.append(trajectory_rrmse(ps))
    return preds, per_step, per_traj, 1e3 * elapsed / max(steps, 1), shortened


def served_errors(ckpt: dict, cfg, data: LoadedData, trajs: list[TrajectoryTensors], trained: dict | None = None) -> dict:
    """A law model that ``export`` serves otherwise than it is evaluated here, rolled out so over
    ``trajs``: its scene's rule (``served_law_hht``: the liver's HHT 0.02) and a law iterated to a
    tolerance with its tangent kept and its updates line-searched (``served_law_settings`` of the
    checkpoint as ``trained``, None: ``ckpt`` is; ``ckpt`` as ``cfg``'s rollout.* steps it). Returns
    {"hht": h (0: the data's rule), "step": the served step in words, "whole": {group: mean
    whole-rollout error}, "worst": {group: the largest trajectory's}, "ms": ms a step,
    "unconverged": law steps left unconverged}, so that the accuracy of what a user feels stands
    beside the data's rule's; {} where the model is served as evaluated (a note printed where the
    scene's rule does not apply)."""
    h, note = served_law_hht(ckpt, OmegaConf.select(cfg, "scene", default=None), data.dataset)
    if note:
        print(f"evaluate: {note}: served at its data's rule")
    want = served_law_settings(ckpt if trained is None else trained, cfg)
    if h is not None:
        want["prior_hht"] = h
    if not want:
        return {}
    served, _ = with_law_rollout(ckpt, want)
    model = model_from_checkpoint(served, data.dataset).eval()
    model.prior.newton_taken.zero_()
    preds, _, _, ms, _ = _rollouts(model, data, trajs)
    whole = [trajectory_error(p, t.z, data.layout) for p, t in zip(preds, trajs)]
    groups = data.layout.names
    return {"hht": h or 0.0, "step": law_phrase(served["prior"]), "whole": _mean_groups(whole, groups),
            "worst": {g: max(w[g] for w in whole) for g in groups}, "ms": ms,
            "unconverged": int(model.prior.newton_taken[2])}


def served_sentence(served: dict, groups: list[str]) -> str:
    """One line for :func:`served_errors`' figures."""
    return (f"as served (the law prior's step {served['step']}, as export gives it): whole rollout "
            + ", ".join(f"{g} {_fmt(served['whole'][g])}" for g in groups)
            + " (the largest trajectory's " + ", ".join(f"{g} {_fmt(served['worst'][g])}" for g in groups)
            + f") at {served['ms']:.1f} ms a step" + (f", {served['unconverged']} law steps unconverged"
                                                     if served["unconverged"] else ""))


def _mean_groups(per_traj: list[dict[str, float]], groups: list[str]) -> dict[str, float]:
    out = {}
    for g in groups:
        vals = [r[g] for r in per_traj if math.isfinite(r[g])]
        out[g] = float(np.mean(vals)) if vals else float("nan")
    return out


#: an exact stress remainder below this share of σ: the prior's stress is the data's law
#: (``model.prior_stress=material``), and the learned H is measured against σ alone
EXACT_LAW = 1e-9


def stress_split(model: LinearPriorModel, preds: list[torch.Tensor], trajs: list[TrajectoryTensors]) -> dict[str, float]:
    """Where a ``model.prior=linear`` model's σ comes from, pooled over the rollouts ``preds``
    [S, N, D] of ``trajs``: σ = the prior's stress of the displacement (and, relaxing, of its
    history) + the learned remainder H. {"learned_H": ||H_pred|| / ||H_exact|| (the learned
    remainder's size along the predicted path relative to the exact one's along the data;
    near 0: H is not learned), "exact_H": ||H_exact|| / ||σ|| (what the prior alone leaves of σ
    at the true displacement), "prior_stress_gap": ||σ_prior(u_pred) − σ_prior(u_true)|| / ||σ||
    (what the displacement's error costs σ through the prior; above the model's σ error, the
    predicted displacement stands in for part of H)}, over the steps s >= 1."""
    sums = torch.zeros(4, dtype=torch.float64)         # ||H_pred||², ||H_exact||², gap², ||σ||²
    for pred, t in zip(preds, trajs):
        parts = []
        for z in (pred.double(), t.z.double()):
            h = model.trajectory_internal_variables(z) if model.prior.n_terms else None
            H = model.unpack(z, h)[2]                                               # [S, N, 6] Pa
            parts.append((H[1:], z[1:, :, 6:12] - H[1:]))                           # H, the prior's σ
        (Hp, prior_p), (Ht, prior_t) = parts
        sums += torch.stack([Hp.pow(2).sum(), Ht.pow(2).sum(), (prior_p - prior_t).pow(2).sum(),
                             t.z[1:, :, 6:12].double().pow(2).sum()])
    learned, exact, gap, sigma = sums.sqrt().tolist()
    ratio = lambda a, b: a / b if b > 0 else math.nan  # noqa: E731
    return {"learned_H": ratio(learned, exact) if exact > EXACT_LAW * sigma else math.nan,
            "learned_H_of_sigma": ratio(learned, sigma), "exact_H": ratio(exact, sigma),
            "prior_stress_gap": ratio(gap, sigma)}


def stress_split_sentence(split: dict[str, float], sigma: str = "sigma") -> str:
    """The split of :func:`stress_split` in words (``sigma``: how σ is written)."""
    if math.isfinite(split["learned_H"]):
        head = (f"{sigma}'s learned remainder H is {_fmt(split['learned_H'])} of the exact one's size (which is "
                f"{_fmt(split['exact_H'])} of {sigma}: what the prior alone misses at the true displacement)")
    else:
        head = (f"the prior's stress is the data's own law (the exact remainder H is {_fmt(split['exact_H'])} of "
                f"{sigma}), and the learned H is {_fmt(split['learned_H_of_sigma'])} of {sigma}")
    return (head + f"; the prior's stress of the predicted displacement is {_fmt(split['prior_stress_gap'])} of "
            f"{sigma} off its stress of the true one")


#: evaluate tabulates the test errors by peak load when the test trajectories have from 2 to this
#: many distinct ones (a dataset generated with a list of magnitudes); random loads are not grouped
MAX_LOAD_GROUPS = 8


def peak_load(force: torch.Tensor) -> float:
    """A trajectory's peak load [N]: the largest over its snapshots of the sum of the nodal load
    magnitudes, from its loads ``force`` [S, N*3] or [S, N, 3] [N] (for ``generate``'s pressing
    loads, the scene's ``loads.magnitude`` the case was pressed with)."""
    nodal = force.reshape(force.shape[0], -1, 3)                       # [S, N, 3]
    return float(nodal.norm(dim=-1).sum(-1).max()) if nodal.numel() else 0.0


def by_peak_load(loads: list[float], snapshot: list[dict[str, float]], whole: list[dict[str, float]],
                 groups: list[str]) -> dict[float, dict[str, float]]:
    """Per-trajectory errors (per snapshot, whole rollout; one dict per trajectory) grouped by the
    trajectories' peak loads ``loads`` [N]: sorted, a load more than 1 % above its group's smallest
    starts the next group, labelled by its mean to 3 significant figures (6 where 3 would
    give two groups one label).
    {load: {"trajectories": count, g: mean per-snapshot error, "whole_" + g: mean whole-rollout
    error}}, in increasing load. Empty unless there are 2 to ``MAX_LOAD_GROUPS`` groups."""
    clusters: list[list[int]] = []
    for k in sorted(range(len(loads)), key=lambda k: loads[k]):
        if clusters and loads[k] <= 1.01 * loads[clusters[-1][0]]:
            clusters[-1].append(k)
        else:
            clusters.append([k])
    if not 2 <= len(clusters) <= MAX_LOAD_GROUPS:
        return {}
    means = [float(np.mean([loads[k] for k in rows])) for rows in clusters]
    labels = [float(f"{m:.3g}") for m in means]
    if len(set(labels)) < len(labels):          # groups closer than 3 figures tell apart
        labels = [float(f"{m:.6g}") for m in means]
    out = {}
    for load, rows in zip(labels, clusters):
        out[load] = {"trajectories": float(len(rows)),
                     **_mean_groups([snapshot[k] for k in rows], groups),
                     **{f"whole_{g}": v for g, v in _mean_groups([whole[k] for k in rows], groups).items()}}
    return out


#: evaluate names this many test trajectories with the largest whole-rollout errors (where the error is)
HARDEST = 3


def hardest(whole: list[dict[str, float]], mean: dict[str, float], groups: list[str]) -> list[int]:
    """Indices of the trajectories by decreasing whole-rollout error ``whole`` (one dict per
    trajectory), each scored by the mean over the groups of its error relative to the groups'
    mean ``mean`` (so that q's scale does not hide v's and sigma's); groups without a finite
    positive mean are left out."""
    used = [g for g in groups if math.isfinite(mean[g]) and mean[g] > 0]
    score = [float(np.mean([w[g] / mean[g] for g in used if math.isfinite(w[g])] or [np.nan])) for w in whole]
    return sorted(range(len(whole)), key=lambda k: -score[k] if math.isfinite(score[k]) else math.inf)


#: displacements this close (relative L2 over all steps and nodes) are one load case
REPEAT_TOL = 1e-6


def modes_sentence(modes: int, miss: dict[str, float]) -> str:
    """One line on how far the test and training displacements lie outside a stress readout's modes."""
    return (f"the test trajectories' true displacements lie {100 * miss['test']:.3g} % outside the stress "
            f"readout's {modes} displacement modes (training: {100 * miss['train']:.3g} %); well above the "
            "training share, the test loads are not combinations of the training ones and the projection "
            "cuts real deformation (model.stress_readout_modes)")


def repeated_cases(ref_pos: np.ndarray, edge_index: np.ndarray, node_type: np.ndarray, positions: slice,
                   test: list[TrajectoryTensors], train: list[TrajectoryTensors]) -> list[tuple[str, str, float]]:
    """The test trajectories that repeat a training one up to a symmetry of the mesh (X = ``ref_pos``
    [N, 3], its ``edge_index`` [2, E] and ``node_type`` [N]; q = z[..., positions]): for each, (its
    name, the training trajectory's, their distance), where the displacements u = q - X of the two,
    one seen in a frame of ``mesh_symmetries`` (the reflections and axis swaps that take the mesh's
    nodes, edges and node types onto themselves; an unstructured mesh has the identity alone), agree
    to ``REPEAT_TOL`` relative L2 over all steps and nodes. On such test cases the test error
    measures the fit to training cases, not generalisation to new loads: the TIGNN beam's reference
    split tests 6 of 6 mirror images of training trajectories, to 6e-15 (docs/accuracy.md, session 54)."""
    from .stress_readout import mesh_symmetries, mirrored_vectors

    X, q = np.asarray(ref_pos, dtype=np.float64), positions
    symmetries = mesh_symmetries(X, np.asarray(edge_index), np.asarray(node_type))
    found = []
    for length in sorted({t.z.shape[0] for t in test}):
        pool = [t for t in train if t.z.shape[0] == length]
        if not pool:
            continue
        u_train = np.stack([t.z[:, :, q].detach().cpu().double().numpy() - X for t in pool])   # [M, S, N, 3]
        size = np.linalg.norm(u_train.reshape(len(pool), -1), axis=1)                          # [M]
        for t in (t for t in test if t.z.shape[0] == length):
            u = t.z[:, :, q].detach().cpu().double().numpy() - X                                # [S, N, 3]
            best, near = np.inf, 0
            for image in mirrored_vectors(u, symmetries).reshape(len(symmetries), *u.shape):   # [S, N, 3] each
                gap = np.linalg.norm((u_train - image).reshape(len(pool), -1), axis=1) / np.maximum(size, 1e-300)
                if gap.min() < best:
                    best, near = float(gap.min()), int(gap.argmin())
            if best <= REPEAT_TOL:
                found.append((t.name, pool[near].name, best))
    return found


def repeated_sentence(found: list[tuple[str, str, float]], n_test: int) -> str:
    """One line on ``repeated_cases``' finding ('' when there is none)."""
    if not found:
        return ""
    return (f"{len(found)} of {n_test} test trajectories repeat a training one up to a symmetry of the mesh "
            f"(displacements within {max(d for *_, d in found):.1e}): "
            + ", ".join(f"{a} = {b}" for a, b, _ in found)
            + "; on these the test error measures the fit to training cases, not generalisation to new loads")


def linear_baseline(data: LoadedData, trajs: list[TrajectoryTensors], corotated: bool = False,
                    newton: int = 0) -> dict:
    """The linearised FE model (the dataset's ``/linear`` operators, ``thermognn.core.linear``; no
    learning) rolled out over the same trajectories, from the same first states under the same
    loads; with ``corotated`` the same solid corotated per cell (``thermognn.core.corotated``:
    each cell's linear force and stress in its rotated frame, implicit in the rotations); with
    ``newton`` > 0 the data's own law (``thermognn.core.hyperelastic``, neo-Hookean and Ogden) with
    that many Newton iterations a step (1: the linearly implicit step of real-time FE), whose
    rollouts that fail (a cell crushed through: non-finite) score inf and are named in "blown". Returns
    {"snapshot": {group: mean per-snapshot RRMSE}, "whole": {group: mean whole-rollout error},
    "whole_per_trajectory": [{group: whole-rollout error}, one per trajectory], "ms_per_step":
    wall time of one step [ms], "sweeps": mean fixed-point sweeps a step (corotated; 1 else),
    "note": ""}; groups the model does not predict (Prony internal variables; sigma without a
    stress operator) are NaN. Without operators (datasets written before them, or too large for
    dense operators), without the moduli the corotated model needs, or for an integrator it
    does not reproduce: {"note": why} alone."""
    lin = data.dataset.linear_solid()
    if lin is None:
        return {"note": "the dataset holds no linearised FE operators (regenerate it to add them)"}
    groups = data.layout.names
    X = data.reference_positions()
    try:
        if newton:
            solid = HyperelasticSolid.of(lin, X, data.dataset.mesh.tets, data.dataset.material, iterations=newton)
        else:
            solid = CorotatedSolid.of(lin, X, data.dataset.mesh.tets) if corotated else lin
    except (ValueError, KeyError) as exc:
        return {"note": str(exc) if isinstance(exc, ValueError) else f"the dataset's scene.material has no {exc}"}
    predicted = {"q"} | ({"v"} if lin.integrator == "newmark" else set()) \
        | ({"sigma"} if lin.stress is not None or corotated or newton else set())
    per_traj, whole, elapsed, steps, inverted, blown = [], [], 0.0, 0, [], []
    try:
        for t in trajs:
            t0 = time.perf_counter()
            z, force = t.z.double().cpu().numpy(), t.force.double().cpu().numpy()
            if not newton:
                pred = solid.rollout_states(z, force, X, data.layout, data.dt)
            else:                                  # the law on a budget may crush a cell through
                try:
                    with np.errstate(all="ignore"):
                        pred = solid.rollout_states(z, force, X, data.layout, data.dt)
                except (RuntimeError, np.linalg.LinAlgError):       # a singular tangent
                    pred = np.full_like(z, math.inf)
                if not np.all(np.isfinite(pred)):
                    blown.append(t.name)
                    pred = np.where(np.isfinite(pred), pred, math.inf)
            elapsed += time.perf_counter() - t0
            steps += pred.shape[0] - 1
            crushed = solid.first_inversion(pred[..., 0:3]) if corotated else None
            if crushed is not None:
                inverted.append((t.name, *crushed))
            pred_t, truth = torch.as_tensor(pred), t.z.double()
            per_traj.append(trajectory_rrmse(rrmse_per_step(pred_t, truth, data.layout)))
            whole.append(trajectory_error(pred_t, truth, data.layout))
    except ValueError as exc:                                       # e.g. generalized-alpha data
        return {"note": str(exc)}
    hide = lambda d: {g: (d[g] if g in predicted else math.nan) for g in groups}  # noqa: E731
    return {"snapshot": hide(_mean_groups(per_traj, groups)), "whole": hide(_mean_groups(whole, groups)),
            "whole_per_trajectory": [hide(w) for w in whole], "ms_per_step": 1e3 * elapsed / max(steps, 1),
            "sweeps": solid.count.mean if corotated else 1.0, "note": "", "inverted": inverted, "blown": blown}


def fe_sentence(fe: dict) -> str:
    """What the data's own FE solve of the test trajectories cost (``Dataset.fe_cost``): the
    exact answer's price, beside which a learned model's speed and error are read."""
    return (f"the FE model itself (the data: error 0) took {fe['ms_per_step']:.1f} ms a step on these "
            f"test trajectories ({fe['iterations_per_step']:.1f} Newton iterations a step"
            + (f", {fe['cuts']} step cuts" if fe["cuts"] else "")
            + "; dolfinx, as `generate` timed it on the machine that generated the dataset)")


def blown_clause(base: dict) -> str:
    """" (it fails on traj_31, ...: inf there)" for the trajectories a budgeted FE model's rollouts
    do not finish (``linear_baseline``'s "blown"), else ""."""
    cases = base.get("blown") or []
    return f" (it fails on {', '.join(cases)}: inf there)" if cases else ""


def inversion_clause(base: dict) -> str:
    """" (it turns cells inside out on traj_14 from step 5 (1 cell), ...)" for the trajectories a
    baseline's rollouts crush a cell through (``linear_baseline``'s "inverted"), else ""."""
    cases = base.get("inverted") or []
    if not cases:
        return ""
    return (" (it turns cells inside out on " + ", ".join(f"{name} from step {step} ({cells} cell"
                                                          f"{'s' if cells != 1 else ''})" for name, step, cells in cases)
            + ": its rollout is meaningless there)")


def linear_validation_error(data: LoadedData, trajs: list[TrajectoryTensors], corotated: bool = False) -> str:
    """The linearised FE model's score by ``validation_error``'s metric (``trajectory_error``
    averaged over the finite groups and trajectories) on ``trajs``, as a clause for ``train``'s
    opening line: the number a learned model's ``val_error`` has to beat ("" where the dataset
    holds no operators or the linear model cannot step it). Groups the linear model does not
    predict (Prony internal variables) are left out of its mean and say so. With ``corotated``
    the corotated FE model's too (a corotated prior's own baseline)."""
    if not trajs:
        return ""
    clause = linear_validation_error(data, trajs) if corotated else ""
    linear = linear_baseline(data, trajs, corotated=corotated)
    if linear.get("note") or "whole_per_trajectory" not in linear:
        return clause
    values = [v for w in linear["whole_per_trajectory"] for v in w.values() if math.isfinite(v)]
    if not values:
        return clause
    left_out = [g for g in data.layout.names if not math.isfinite(linear["whole"][g])]
    if corotated:
        return clause + f"; the corotated FE model's {float(np.mean(values)):.3e}" + inversion_clause(linear)
    return (f"; the linearised FE model's validation error {float(np.mean(values)):.3e}"
            + (f" (without {', '.join(left_out)})" if left_out else "") + ", the number val_error has to beat")


def error_left(model: list[dict[str, float]], linear: list[dict[str, float]], groups: list[str]) -> dict[str, float]:
    """The share of the linearised FE model's error that a learned model leaves: per group, the mean
    over trajectories of the model's whole-rollout error divided by the linear model's on the same
    trajectory (one dict per trajectory in each list). NaN for a group without a finite, positive
    ratio (one the linear model does not predict). On the training trajectories it says how well
    the network fits the nonlinearity, on the test ones how well it generalises: a test share above
    the training one is a generalisation gap (more load cases help), equal shares point to the fit
    (capacity, training)."""
    return _mean_groups([{g: m[g] / lin[g] if lin[g] > 0 else math.nan for g in groups}
                         for m, lin in zip(model, linear)], groups)


#: the load scale of the gentle-load check (:func:`gentle_load_gaps`): 1 % of the data's loads
#: (at 0.1 % the float32 network's positions, rounded by 2e-9 m at 4 cm, blur a 1e-7 m displacement)
GENTLE = 1e-2


def gentle_load_gaps(model: LinearPriorModel, data: LoadedData, traj: TrajectoryTensors,
                     scales=(1.0, GENTLE)) -> dict[float, dict[str, float]]:
    """A linear-prior model against the linearised FE model (the dataset's ``/linear``) under the
    loads of ``traj`` (which starts at rest) times each scale: {scale: {group: ||z_model −
    z_linear|| / ||z_linear − z_rest||}} over the rollout (dimensionless; q: the displacements).
    The true remainders start at second order in the load, so where the network's do too
    (``model.prior_order=2``) the gap shrinks in proportion to the load, and gentle loads give the
    linear model; a gap that does not shrink is a first-order error of the learned remainders."""
    lin = data.dataset.linear_solid()
    X = data.reference_positions()
    z0, out = traj.z.double(), {}
    for scale in scales:
        forces = traj.force.double() * scale
        pred = rollout(model, data.graph, z0[0], forces, data.dt).double()
        ref = torch.as_tensor(lin.rollout_states(z0.cpu().numpy(), forces.cpu().numpy(), X, data.layout, data.dt))
        gaps = {}
        for g in data.layout.names:
            sl = data.layout.slice(g)
            rest = z0[0, :, sl] if g != "q" else torch.as_tensor(X)
            num, den = (pred[1:, :, sl] - ref[1:, :, sl]).norm(), (ref[1:, :, sl] - rest).norm()
            gaps[g] = float(num / den) if float(den) > 0 else math.nan
        out[scale] = gaps
    return out


def _eval_split(cfg) -> str:
    """``train.eval_split``: ``checkpoint`` (default) or ``dataset`` (one-line ConfigError else)."""
    which = str(OmegaConf.select(cfg, "train.eval_split", default="checkpoint"))
    if which not in ("checkpoint", "dataset"):
        raise ConfigError(f"train.eval_split = {which!r}, expected checkpoint | dataset")
    return which


def _evaluation_split(which: str, stored: dict, data: LoadedData, ckpt_path) -> dict[str, list[str]]:
    """The parts evaluate rolls out. ``which`` (``_eval_split``) ``checkpoint``: the split the
    checkpoint trained with, where the dataset holds it (else the dataset's). ``dataset``: the
    dataset's own test part (a dataset grown since training) with the checkpoint's training part;
    a one-line DataError if a test trajectory is one the checkpoint trained or validated on."""
    names = set(data.dataset.names)
    held = stored and all(n in names for p in ("train", "test") for n in stored.get(p, []))
    if which == "checkpoint":
        return {k: list(stored.get(k, [])) for k in ("train", "val", "test")} if held else data.split
    seen = set(stored.get("train", [])) | set(stored.get("val", []))
    leaked = [n for n in data.split["test"] if n in seen]
    if leaked:
        raise DataError(f"train.eval_split=dataset: test trajectories {', '.join(leaked)} of {data.dataset.path} "
                        f"were trained or validated on by {ckpt_path}")
    trained = stored.get("train", [])
    return {"train": list(trained) if trained and all(n in names for n in trained) else data.split["train"],
            "val": [], "test": data.split["test"]}


def data_time_error(dataset) -> dict:
    """The data's own time error by generate's check (``Dataset.time_convergence``): whole-rollout
    relative error {"u", "v", "sigma"} of the data against the FE at twice its sub-steps, over the
    checked cases; {} where it was not measured (older files, imported data, quasi-static elastic)."""
    tc = getattr(dataset, "time_convergence", None) or {}
    if tc.get("u") is None:
        return {}
    return {g: float(tc[g]) for g in ("u", "v", "sigma") if tc.get(g) is not None}


def data_time_sentence(dataset) -> str:
    """summary.md's sentence on :func:`data_time_error`."""
    tc = dataset.time_convergence
    errors = data_time_error(dataset)
    names = ", ".join(c["name"] for c in tc["cases"] if "failed" not in c)
    parts = ", ".join(f"{'σ' if g == 'sigma' else g} {_fmt(e)}" for g, e in errors.items())
    k = int(tc["substeps"])
    solved = f"{k} FE steps of dt / {k} a stored step" if k > 1 else "one FE step a stored step"
    return (f"The data's own time error (generate's check on {names}: the data, {solved}, against the FE at "
            f"{tc['fine_substeps']} sub-steps a step): {parts} "
            "(whole rollout; `data_time_error_*` in `rrmse.json`). A model's error against the data "
            "below these measures how it follows the data's time stepping, not the converged motion "
            "(`scene.time.substeps` solves finer).")


def evaluate(cfg) -> dict:
    """Roll out the test trajectories with the checkpoint's model; print and write the errors.

    Returns {group: mean test RRMSE (per snapshot), ..., "whole_<group>": mean test whole-rollout
    error (:func:`trajectory_error`, the model-selection metric), "ms_per_step": wall time of one
    step [ms], for test trajectories of 2 to ``MAX_LOAD_GROUPS`` distinct peak loads F
    (:func:`by_peak_load`) "<group>@<F>N" and "whole_<group>@<F>N" (their means at each load),
    "energy_balance": see :func:`energy_balance`, "rest_drift", "rest_growth",
    "one_step_<group>": the test one-step error of :func:`one_step_errors`, for linear-prior
    models "linear_gap_<group>" / "gentle_gap_<group>" (:func:`gentle_load_gaps` at full load and
    at ``GENTLE`` of it), and for datasets with
    linearised FE operators "linear_fe_<group>" / "linear_fe_whole_<group>" (per-snapshot and
    whole-rollout test errors of :func:`linear_baseline`), "linear_fe_ms_per_step" and
    "linear_fe_left_<group>" / "linear_fe_left_train_<group>" (:func:`error_left` on the test
    trajectories and on the training ones evaluate rolls out), and for datasets with the moduli at
    rest the corotated FE model's "corotated_fe_<group>", "corotated_fe_whole_<group>",
    "corotated_fe_ms_per_step" and "corotated_fe_sweeps" (``linear_baseline(corotated=True)``), for
    hyperelastic scenes the linearly implicit FE model's "newton1_fe_<group>", "newton1_fe_whole_<group>",
    "newton1_fe_ms_per_step" (``linear_baseline(newton=1)``), and for
    datasets that record their FE solve's cost "fe_ms_per_step", "fe_iterations_per_step"
    (``Dataset.fe_cost``), for a law prior with ``model.prior_newton_max`` its test rollouts'
    "newton_iterations_per_step" and "unconverged_steps" (and with ``model.prior_step_cuts``
    "cut_steps"; :func:`newton_sentence`), and for a law prior whose rollouts shortened Newton updates
    "shortened_updates" (their number over the test rollouts, :func:`shortened_updates`), and
    where test trajectories repeat training ones up to a mirror of the mesh "test_repeats_train"
    (their number, :func:`repeated_cases`), and for a stress readout that ``train`` checked on
    held-out loads (``train.readout_folds``) "readout_held_out_sigma" / "readout_held_out_sigma_whole"
    (``stress_readout.held_out_loads_check``, from the checkpoint), and for a law model that
    export serves otherwise (its scene's ``scene.time.served_hht``; a law iterated to a tolerance:
    its tangent kept, its updates line-searched) the test errors so stepped, "served_hht" (0: the
    data's rule), "served_whole_<group>", "served_ms_per_step", "served_unconverged_steps"
    (:func:`served_errors`)}."""
    torch.set_num_threads(int(OmegaConf.select(cfg, "train.threads", default=2)))
    ckpt_path = project_path(cfg.paths.checkpoint)
    ckpt = load_checkpoint(ckpt_path)
    ds_path = project_path(cfg.paths.dataset)
    check_fingerprint(ckpt["fingerprint"], Dataset(ds_path), ckpt_path)
    dtype = torch_dtype(ckpt["dtype"])
    data = load_data(ds_path, cfg.train.split, int(cfg.seed), dtype, parts=(),
                     state_dtype=torch.float64 if ckpt.get("prior") else dtype)
    which_split = _eval_split(cfg)
    data.split = _evaluation_split(which_split, ckpt.get("split") or {}, data, ckpt_path)
    max_train = int(OmegaConf.select(cfg, "train.eval_max_train", default=10))
    train_names = spread(data.split["train"], max_train)        # covering every load level
    for n in data.split["test"] + train_names:
        data.read(n)
    trained_ckpt = ckpt
    ckpt, stepped = with_rollout(ckpt, cfg)
    if stepped:
        print(f"evaluate: stepping the trained model with {stepped}")
    solved = getattr(data.dataset, "substeps", 1)
    if (ckpt.get("prior") or {}).get("law") and solved > 1 and int(ckpt["prior"].get("law_substeps", 1)) != solved:
        print(f"evaluate: {ds_path} was solved with {solved} FE steps a stored step; the law prior takes "
              f"{int(ckpt['prior'].get('law_substeps', 1))}: rollout.prior_substeps={solved} steps it as the data were solved")
    model = model_from_checkpoint(ckpt, data.dataset).eval()
    prior = isinstance(model, LinearPriorModel)      # the network learned remainders, not E and S
    prior_name = ("hyperelastic" if prior and isinstance(model.prior, HyperelasticNewmarkPrior)
                  else "corotated" if prior and isinstance(model.prior, CorotatedNewmarkPrior) else "linearised")
    stress_name = ("the material law's stress (`model.prior_stress=material`)"
                   if prior and bool(getattr(model.prior, "material_stress", False)) else f"the {prior_name} prior's stress")
    groups = data.layout.names
    test = data.of("test")
    train_trajs = [data.trajectories[n] for n in train_names]
    newton = model.prior.newton_taken if prior and isinstance(model.prior, HyperelasticNewmarkPrior) else None
    if newton is not None:
        newton.zero_()
        model.prior.searched.zero_()
    preds, per_step, per_traj, ms, shortened = _rollouts(model, data, test)
    newton_test = newton.tolist() if newton is not None else None          # [iterations, steps, unconverged, cut]
    searched_test = int(model.prior.searched) if newton is not None else 0
    preds_train, _, per_traj_train, _, _ = _rollouts(model, data, train_trajs)
    mean_test, mean_train = _mean_groups(per_traj, groups), _mean_groups(per_traj_train, groups)
    whole_traj = [trajectory_error(p, t.z, data.layout) for p, t in zip(preds, test)]
    whole_traj_train = [trajectory_error(p, t.z, data.layout) for p, t in zip(preds_train, train_trajs)]
    whole = _mean_groups(whole_traj, groups)
    loads, loads_train = [peak_load(t.force) for t in test], [peak_load(t.force) for t in train_trajs]
    for n in data.split["train"]:                   # test cases that the training split holds, mirrored
        data.read(n)
    repeats = repeated_cases(data.reference_positions(), data.graph.edge_index.cpu().numpy(),
                             data.graph.node_type.cpu().numpy(), data.layout.slice("q"), test, data.of("train"))
    if repeats:
        mean_test["test_repeats_train"] = float(len(repeats))
    span_miss = {}                 # how far the true displacements lie outside the readout's modes
    if getattr(model, "use_readout", False) and model.readout.mode_count > 0:
        from .stress_readout import outside_modes

        q, X = data.layout.slice("q"), torch.from_numpy(data.reference_positions())     # [N, 3] float64
        span_miss = {part: outside_modes(model.readout, torch.cat([t.z[:, :, q].double() - X for t in trajs]))
                     for part, trajs in (("test", test), ("train", train_trajs))}
        mean_test["readout_modes_miss"], mean_test["readout_modes_miss_train"] = span_miss["test"], span_miss["train"]
    readout_check = ckpt.get("stress_readout_check") or {}        # train's check on held-out loads
    if readout_check.get("folds"):
        mean_test["readout_held_out_sigma"] = readout_check["per_snapshot"]
        mean_test["readout_held_out_sigma_whole"] = readout_check["whole"]
    by_load = by_peak_load(loads, per_traj, whole_traj, groups)
    served = served_errors(ckpt, cfg, data, test, trained_ckpt)   # as export serves it (served_errors)
    linear = linear_baseline(data, test)
    linear_train = linear_baseline(data, train_trajs) if "snapshot" in linear else {}
    corotated = linear_baseline(data, test, corotated=True)
    implicit = linear_baseline(data, test, newton=1)            # the data's law, one Newton iteration a step
    fe = data.dataset.fe_cost([t.name for t in test])           # the data's own FE solve (generate's record)
    split = stress_split(model, preds, test) if prior and "sigma" in groups else {}
    left = {}                      # the share of the linear model's error the model leaves, test and train
    if "snapshot" in linear and "snapshot" in linear_train:
        left = {"test": error_left(whole_traj, linear["whole_per_trajectory"], groups),
                "train": error_left(whole_traj_train, linear_train["whole_per_trajectory"], groups)}

    out = project_path(cfg.paths.eval_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = _pyplot()
    files = []

    # RRMSE vs time (mean over test trajectories), paper Fig. 8
    n_steps = max(p.shape[0] for p in preds)
    curve = {g: np.full(n_steps, np.nan) for g in groups}
    for g in groups:
        for s in range(n_steps):
            vals = [ps[g][s] for ps in per_step if s < len(ps[g]) and math.isfinite(ps[g][s])]
            curve[g][s] = np.mean(vals) if vals else np.nan
    times = np.arange(n_steps) * data.dt
    _write_csv(out / "rrmse_vs_time.csv", ["step", "time_s", *groups],
               [[s, times[s], *[curve[g][s] for g in groups]] for s in range(n_steps)])
    fig, ax = plt.subplots(figsize=(6, 4))
    for g in groups:
        ax.semilogy(times[1:], curve[g][1:], marker=".", label=g)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("RRMSE (mean over test trajectories)")
    ax.set_title("rollout error vs time")
    ax.legend()
    _save_fig(fig, out / "rrmse_vs_time.png")
    files += ["rrmse_vs_time.csv", "rrmse_vs_time.png"]

    # per-trajectory errors, train vs test, with each trajectory's peak load and load point
    def point(name: str) -> list[float]:                      # [m], nan where the file records none
        return [float(x) for x in data.dataset.load_points.get(name, np.full(3, np.nan))]

    def where(k: int) -> str:                     # a test trajectory's peak load and load point
        p = point(test[k].name)
        at = f" at ({', '.join(f'{x:.4g}' for x in p)}) m" if all(map(math.isfinite, p)) else ""
        return f"{loads[k]:.3g} N{at}"

    def linear_whole(baseline: dict, n: int) -> list[list[float]]:   # the linear model's, per trajectory
        per = baseline.get("whole_per_trajectory")
        return [[lw[g] for g in groups] for lw in per] if per else [[math.nan] * len(groups)] * n

    parts = (("train", train_trajs, loads_train, per_traj_train, whole_traj_train, linear_train),
             ("test", test, loads, per_traj, whole_traj, linear))
    rows = [[part, t.name, f, *point(t.name), *[r[g] for g in groups], *[w[g] for g in groups], *lw]
            for part, trajs, fs, snap, wh, baseline in parts
            for t, f, r, w, lw in zip(trajs, fs, snap, wh, linear_whole(baseline, len(trajs)))]
    _write_csv(out / "rrmse_per_trajectory.csv",
               ["split", "trajectory", "peak_load_N", "load_point_x_m", "load_point_y_m", "load_point_z_m",
                *groups, *[f"whole_{g}" for g in groups], *[f"linear_fe_whole_{g}" for g in groups]], rows)
    worst = hardest(whole_traj, whole, groups)[:HARDEST] if len(test) > 1 else []     # where the error is
    fig, axes = plt.subplots(1, len(groups), figsize=(3.2 * len(groups), 3.5), squeeze=False)
    for ax, g in zip(axes[0], groups):
        series = [[r[g] for r in per_traj_train if math.isfinite(r[g])],
                  [r[g] for r in per_traj if math.isfinite(r[g])]]
        ax.boxplot([s if s else [np.nan] for s in series])
        ax.set_xticks([1, 2], ["train", "test"])
        ax.set_yscale("log")
        ax.set_title(f"RRMSE {g}")
    _save_fig(fig, out / "rrmse_per_trajectory.png")
    files += ["rrmse_per_trajectory.csv", "rrmse_per_trajectory.png"]

    # one step from every true state: what the network learned, apart from the rollout's drift
    step_test, step_curve = one_step_errors(model, data.graph, test, data.layout, data.dt)
    step_train, _ = one_step_errors(model, data.graph, train_trajs, data.layout, data.dt)
    step_linear = (one_step_errors(model, data.graph, test, data.layout, data.dt, linear_fe=True)[0]
                   if prior else None)                    # the linearised FE model's own one step
    _write_csv(out / "one_step_vs_time.csv", ["step", "time_s", *groups],
               [[s + 1, times[s + 1], *[step_curve[g][s] for g in groups]]
                for s in range(len(step_curve[groups[0]]))])
    files.append("one_step_vs_time.csv")
    print("evaluate: one step from the true state, error of its change (test): "
          + ", ".join(f"{g} {_fmt(step_test[g])}" for g in groups)
          + (f"; the {prior_name} FE model's: " + ", ".join(f"{g} {_fmt(step_linear[g])}" for g in groups)
             if step_linear else ""))

    # energy, entropy and degeneracy along each test rollout
    # (a law prior's: the law's energy, the loads' work and what the body absorbed, ``law_energy_along``)
    law = prior and isinstance(model.prior, HyperelasticNewmarkPrior)
    rows, along, along_data = [], [], []
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for t, pred in zip(test, preds):
        if law:
            ees = law_energy_along(model.prior, data.graph.ref_pos, pred, t.force)
            along_data.append(law_energy_along(model.prior, data.graph.ref_pos, t.z, t.force))
        elif prior:
            ees = np.full((pred.shape[0], len(ENERGY_COLUMNS)), np.nan)
        else:
            ees = energy_entropy_along(model, data.graph, pred, t.force, data.dt)
            ees = np.concatenate([ees, np.full((ees.shape[0], 2), np.nan)], axis=1)
        along.append(ees)
        tt = np.arange(pred.shape[0]) * data.dt
        rows += [[t.name, s, tt[s], *ees[s]] for s in range(pred.shape[0])]
        for k, ax in zip((0, 5, 2) if law else (0, 1, 2), axes):
            ax.plot(tt, ees[:, k], label=t.name)
    titles = (("the law's energy E [J]", "absorbed W - (E - E_0) [J]", "degeneracy residual") if law
              else ("learned energy E", "learned entropy S", "degeneracy residual"))
    for ax, title in zip(axes, titles):
        ax.set_title(title)
        ax.set_xlabel("time [s]")
    if len(test) <= 10:
        axes[0].legend(fontsize=7)
    _write_csv(out / "energy_entropy.csv", ["trajectory", "step", "time_s", *ENERGY_COLUMNS], rows)
    balance = energy_balance(along)
    law_fig = law_energy_figures(along, along_data) if law and along else {}
    law_line = (law_energy_sentence(law_fig, model.prior.n_terms == 0 and model.prior.alpha_m == 0.0
                                    and model.prior.c == 0.0) if law_fig else "")
    if law_line:
        print(f"evaluate: {law_line}")
    _save_fig(fig, out / "energy_entropy.png")
    files += ["energy_entropy.csv", "energy_entropy.png"]

    # the unloaded body left at rest for 10x the horizon (datasets that start from rest)
    drift_line = "- rest drift: not measured (the trajectories do not all start from one unloaded rest state)"
    drift = growth = math.nan
    vel_cols = velocity_columns(data.layout)
    try:
        rest = rest_trajectory(test + train_trajs, data.dataset.effects, vel_cols)
    except ConfigError:
        rest = None
    if rest is not None:
        steps = REST_HORIZONS * (n_steps - 1)
        held = rest_drift(model, data.graph, rest, steps, vel_cols)
        _write_csv(out / "rest_drift.csv", ["step", "time_s", "max_displacement_m", "max_velocity_m_s"],
                   [[s, s * data.dt, *held[s]] for s in range(held.shape[0])])
        files.append("rest_drift.csv")
        reach = max((float((t.z[:, :, 0:3] - t.z[:1, :, 0:3]).abs().max()) for t in test), default=0.0)
        drift = float(np.nanmax(held[:, 0])) / max(reach, 1e-300) if np.isfinite(held).all() else math.inf
        drift_line = (f"- rest drift: unloaded and left at rest for {steps} steps ({REST_HORIZONS}x the horizon), "
                      f"the body moved at most {_fmt(float(np.nanmax(held[:, 0])))} m, {_fmt(drift)} of the "
                      f"largest displacement in the test data ({_fmt(reach)} m); `rest_drift.csv`")
        if not prior:                 # (the prior's growth at rest is the linear Newmark step's, <= 1)
            by_size = rest_growth_factors(model, data.graph, rest, data.dt)
            growth = max(by_size.values())
            drift_line += ("\n- rest stability: one step multiplies a disturbance of the rest state along its fastest "
                           "mode by " + ", ".join(f"{g:.4f} at {size:g}" for size, g in by_size.items())
                           + " typical steps' size (above 1: a drift of that size grows geometrically)")
        for line in drift_line.splitlines():
            print(f"evaluate: {line[2:]}")
    gentle_line = ""
    if prior and rest is not None and test:       # gentle loads: the linearised FE model's limit
        gaps = gentle_load_gaps(model, data, test[0])
        mean_test.update({f"linear_gap_{g}": gaps[1.0][g] for g in groups})
        mean_test.update({f"gentle_gap_{g}": gaps[GENTLE][g] for g in groups})
        gentle_line = (f"- gentle loads: against the linearised FE model under {test[0].name}'s loads, the model "
                       "differs by " + ", ".join(f"{g} {_fmt(gaps[1.0][g])}" for g in groups) + " at full load and by "
                       + ", ".join(f"{g} {_fmt(gaps[GENTLE][g])}" for g in groups) + f" at {GENTLE:g} of it "
                       "(relative to the linear response; remainders of second order, `model.prior_order=2`, "
                       f"make the second {GENTLE:g} of the first; a first-order error of the learned "
                       "remainders keeps it from shrinking)")
        print(f"evaluate: {gentle_line[2:]}")

    # predicted vs ground truth at one snapshot (VTU for ParaView; needs tets)
    if len(data.dataset.mesh.tets) and test:
        snap = int(OmegaConf.select(cfg, "train.eval_snapshot", default=-1))
        step = snap % preds[0].shape[0]
        name = f"snapshot_{test[0].name}_{step}.vtu"
        write_vtu(out / name, data.dataset, test[0], preds[0], step)
        files.append(name)

    mean_test["ms_per_step"] = ms
    mean_test["energy_balance"] = balance
    mean_test.update(law_fig)
    mean_test["rest_drift"] = drift
    mean_test["rest_growth"] = growth
    mean_test.update({f"one_step_{g}": step_test[g] for g in groups})
    mean_test.update({f"whole_{g}": whole[g] for g in groups})
    data_time = data_time_error(data.dataset)
    mean_test.update({f"data_time_error_{g}": e for g, e in data_time.items()})
    rows = {"test": {g: mean_test[g] for g in groups}, "train": mean_train}
    if "snapshot" in linear:
        mean_test.update({f"linear_fe_{g}": linear["snapshot"][g] for g in groups})
        mean_test.update({f"linear_fe_whole_{g}": linear["whole"][g] for g in groups})
        mean_test["linear_fe_ms_per_step"] = linear["ms_per_step"]
        rows["linearised FE, test"] = linear["snapshot"]
    if "snapshot" in corotated:
        mean_test.update({f"corotated_fe_{g}": corotated["snapshot"][g] for g in groups})
        mean_test.update({f"corotated_fe_whole_{g}": corotated["whole"][g] for g in groups})
        mean_test["corotated_fe_ms_per_step"] = corotated["ms_per_step"]
        mean_test["corotated_fe_sweeps"] = corotated["sweeps"]
        rows["corotated FE, test"] = corotated["snapshot"]
    if "snapshot" in implicit:
        mean_test.update({f"newton1_fe_{g}": implicit["snapshot"][g] for g in groups})
        mean_test.update({f"newton1_fe_whole_{g}": implicit["whole"][g] for g in groups})
        mean_test["newton1_fe_ms_per_step"] = implicit["ms_per_step"]
        rows["linearly implicit FE, test"] = implicit["snapshot"]
    if served:
        mean_test["served_hht"] = served["hht"]
        mean_test.update({f"served_whole_{g}": served["whole"][g] for g in groups})
        mean_test["served_ms_per_step"] = served["ms"]
        mean_test["served_unconverged_steps"] = float(served["unconverged"])
        print(f"evaluate: {served_sentence(served, groups)} (test)")
    if fe:
        mean_test["fe_ms_per_step"] = fe["ms_per_step"]
        mean_test["fe_iterations_per_step"] = fe["iterations_per_step"]
    mean_test.update({f"stress_{k}": v for k, v in split.items()})
    if left:
        mean_test.update({f"linear_fe_left_{g}": left["test"][g] for g in groups})
        mean_test.update({f"linear_fe_left_train_{g}": left["train"][g] for g in groups})
    print_rrmse_table(f"rollout RRMSE ({len(test)} test, {len(train_trajs)} train trajectories)", rows)
    for load, e in by_load.items():              # the test errors at each peak load
        mean_test.update({f"{k}@{load:g}N": v for k, v in e.items() if k != "trajectories"})
        print(f"evaluate: at {load:g} N peak load ({int(e['trajectories'])} test trajectories): per snapshot "
              + ", ".join(f"{g} {_fmt(e[g])}" for g in groups) + "; whole rollout "
              + ", ".join(f"{g} {_fmt(e['whole_' + g])}" for g in groups))
    if newton_test is not None and model.prior.max_iterations > model.prior.iterations:
        mean_test["newton_iterations_per_step"] = newton_test[0] / max(newton_test[1], 1)
        mean_test["unconverged_steps"] = float(newton_test[2])
        if model.prior.step_cuts:
            mean_test["cut_steps"] = float(newton_test[3])
        print(f"evaluate: {newton_sentence(model.prior.iterations, model.prior.max_iterations, *newton_test, step_cuts=model.prior.step_cuts)} (test)")
    if newton_test is not None and model.prior.line_search:
        mean_test["line_searched_updates"] = float(searched_test)
        print(f"evaluate: the law prior's line search shortened {searched_test} Newton update"
              f"{'s' if searched_test != 1 else ''} that did not lower the residual norm (up to "
              f"{model.prior.line_search} halvings each; model.prior_line_search) (test)")
    if any(shortened):
        mean_test["shortened_updates"] = float(sum(shortened))
        print(f"evaluate: {shortened_sentence([t.name for t in test], shortened)} (test)")
    if repeats:
        print(f"evaluate: {repeated_sentence(repeats, len(test))}")
    if span_miss:
        print(f"evaluate: {modes_sentence(model.readout.mode_count, span_miss)}")
    if readout_check:
        print(f"evaluate: {held_out_sentence(readout_check)} (train's check)")
    if worst:
        print("evaluate: largest whole-rollout test errors: " + "; ".join(
            f"{test[k].name} ({where(k)}): " + ", ".join(f"{g} {_fmt(whole_traj[k][g])}" for g in groups)
            for k in worst))
    if left:
        print("evaluate: of the linearised FE model's whole-rollout error the model leaves (mean ratio per "
              "trajectory) " + "; ".join(f"{part} " + ", ".join(f"{g} {_fmt(left[part][g])}" for g in groups)
                                         for part in ("train", "test")))
    if split:
        print(f"evaluate: {stress_split_sentence(split)} (test)")
    for label, base in (("linearised", linear), ("corotated", corotated), ("linearly implicit", implicit)):
        if "whole" in base:
            print(f"evaluate: the {label} FE model's whole-rollout test error "
                  + ", ".join(f"{g} {_fmt(base['whole'][g])}" for g in groups)
                  + f" at {base['ms_per_step']:.2f} ms a step"
                  + (f" ({base['sweeps']:.1f} sweeps)" + inversion_clause(base) if label == "corotated" else "")
                  + (" (the data's law, one Newton iteration a step)" + blown_clause(base)
                     if label == "linearly implicit" else ""))
    if fe:
        print(f"evaluate: {fe_sentence(fe)}")
    print(f"evaluate: {ms:.2f} ms per step ({data.graph.n_nodes} nodes, {torch.get_num_threads()} threads); "
          f"wrote {out}")

    def linear_rows(kind: str) -> list[str]:
        return [f"| {label} FE, test | " + " | ".join(_fmt(base[kind][g]) for g in groups) + " |"
                for label, base in (("linearised", linear), ("corotated", corotated), ("linearly implicit", implicit))
                if kind in base]

    linear_line = ("The linearised FE model (the dataset's own K, M and stress operator at rest, stepped by "
                   "the data's integrator; no learning; rows `linearised FE` above; nan: a group it does not "
                   f"predict) steps in {linear['ms_per_step']:.3f} ms (scipy, one sparse LU solve): the physics baseline a "
                   "learned model has to beat." if "snapshot" in linear
                   else f"Linearised FE baseline: not computed, {linear['note']}.")
    corotated_line = ("The corotated FE model (the same solid with each cell's linear force and stress in its "
                      "rotated frame, implicit in the rotations: no spurious strain from a rotation; rows "
                      f"`corotated FE`) steps in {corotated['ms_per_step']:.3f} ms ({corotated['sweeps']:.1f} "
                      "fixed-point sweeps of one sparse LU a step): the baseline where the cells turn far"
                      + inversion_clause(corotated) + "."
                      if "snapshot" in corotated else f"Corotated FE baseline: not computed, {corotated['note']}.")
    implicit_line = ("The linearly implicit FE model (the data's own law, `thermognn.core.hyperelastic`, with "
                     "one Newton iteration a step from the FE's predictor, as a real-time FE solver steps; rows "
                     f"`linearly implicit FE`) steps in {implicit['ms_per_step']:.3f} ms (one sparse LU of the exact "
                     "tangent a step): what the physics itself gives at about the cost of one linear solve"
                     + blown_clause(implicit) + "." if "snapshot" in implicit
                     else f"Linearly implicit FE baseline: not computed, {implicit['note']}.")
    parameters, readout_weights = parameter_count(model), readout_weight_count(model)
    lines = [f"# Evaluation of `{ckpt_path}`", "",
             f"- dataset: `{ds_path}` (scene `{data.dataset.scene}`, {data.graph.n_nodes} nodes, "
             f"D = {data.layout.dim}, dt = {data.dt} s)",
             f"- model: {ckpt['structure']}, {ckpt['dtype']}, {parameters} parameters"
             + (f" + {readout_weights} of the stress readout = {parameters + readout_weights}"
                if readout_weights else "")
             + ", "
             f"trained {ckpt.get('epoch', '?')} epochs (validation error {ckpt.get('val_error', float('nan')):.3e})",
             f"- trajectories: {len(test)} test, {len(train_trajs)} train (of {len(data.split['train'])})"
             + ("; test: the dataset's own test part (`train.eval_split=dataset`)"
                if which_split == "dataset" else ""),
             f"- speed: {ms:.2f} ms per step (forward + autograd, {torch.get_num_threads()} threads, CPU, "
             + describe_step(model_step(ckpt))
             + (f", each step the mean over {ckpt['hparams']['mirror_frames']['frames']} mirror frames of the mesh "
                "(`model.mirror_average`)" if (ckpt.get("hparams") or {}).get("mirror_frames") else "")
             + (f"; `rollout` overrides: {stepped}" if stepped else "") + ")"
             + (f"; {fe_sentence(fe)}" if fe else ""),
             (f"- {law_line}" if law_line else
              f"- energy balance: {_fmt(balance)} = sum |E_s - E_(s-1) - dt P| / sum |E_s - E_(s-1)| over the "
              "test rollouts (the learned energy's change that the port's work P does not explain: the "
              "integrator's drift, and for GENERIC models also what M changes where the learned "
              "degeneracy M dE/dz = 0 is not exact; with exact kinematics also dE/dq . (v - the "
              "network's dq/dt); `energy_error` in `energy_entropy.csv`)"), drift_line,
             *([gentle_line] if gentle_line else []),
             *([f"- model.prior = linear: the data's Newmark step of the {prior_name} solid "
                + ("alone, its remainders zero (the network not evaluated: its weights are untrained or "
                   "unused)" if not model.learned else "with the network's remainders G and H")
                + "; the network's E and S are not the body's energy and entropy ("
                + ("the energy columns are the law's" if law else "energy columns nan") + "); its one step from a true state takes the data's own Newmark acceleration "
                "there, recovered from the velocities"] if prior else []), "",
             "Relative L2 error per snapshot ||z_pred - z_gt|| / ||z_gt|| over all nodes of a group, "
             "averaged over the rollout steps (clamped nodes imposed) and trajectories.", "",
             "| split | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups),
             "| test | " + " | ".join(_fmt(mean_test[g]) for g in groups) + " |",
             "| train | " + " | ".join(_fmt(mean_train[g]) for g in groups) + " |", *linear_rows("snapshot"), "",
             "Whole-rollout relative error ||z_pred - z_gt|| / ||z_gt|| over all steps and nodes (the "
             "model-selection metric; unlike the per-snapshot mean it does not blow up where a group "
             "comes to rest):", "",
             "| split | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups),
             "| test | " + " | ".join(_fmt(whole[g]) for g in groups) + " |",
             *(["| test, as served | " + " | ".join(_fmt(served["whole"][g]) for g in groups)
                + " |"] if served else []), *linear_rows("whole"), "",
             *([served_sentence(served, groups) + " (`served_*` in `rrmse.json`).", ""] if served else []),
             *([data_time_sentence(data.dataset), ""] if data_time else []),
             *(["The test errors at each peak load (the largest sum of the nodal load magnitudes over a "
                "trajectory; loads within 1 % are one group, labelled by their mean to 3 significant figures; "
                "`peak_load_N` in `rrmse_per_trajectory.csv`), "
                "per snapshot and over the whole rollout:", "",
                "| peak load [N] | test trajectories | " + " | ".join(groups) + " | "
                + " | ".join(f"whole {g}" for g in groups) + " |", "|---|---|" + "---|" * (2 * len(groups)),
                *(f"| {load:g} | {int(e['trajectories'])} | " + " | ".join(_fmt(e[g]) for g in groups) + " | "
                  + " | ".join(_fmt(e['whole_' + g]) for g in groups) + " |" for load, e in by_load.items()), ""]
               if by_load else []),
             *([repeated_sentence(repeats, len(test)) + " (`test_repeats_train` in `rrmse.json`).", ""]
               if repeats else []),
             *([modes_sentence(model.readout.mode_count, span_miss) + " (`readout_modes_miss` in `rrmse.json`).", ""]
               if span_miss else []),
             *([held_out_sentence(readout_check) + " (train's check; `readout_held_out_sigma` in `rrmse.json`).", ""]
               if readout_check.get("folds") else []),
             *([f"The {len(worst)} test trajectories with the largest whole-rollout errors (ranked by the "
                "mean over the groups of each error relative to the test mean above; all of them in "
                "`rrmse_per_trajectory.csv`, with the load points):", "",
                "| trajectory | peak load, load point | " + " | ".join(f"whole {g}" for g in groups) + " |",
                "|---|---|" + "---|" * len(groups),
                *(f"| {test[k].name} | {where(k)} | " + " | ".join(_fmt(whole_traj[k][g]) for g in groups) + " |"
                  for k in worst), ""] if worst else []),
             linear_line, corotated_line, implicit_line, "",
             *(["The share of the linearised FE model's whole-rollout error that the model leaves (the mean "
                "over trajectories of the ratio of the two; `linear_fe_whole_*` in `rrmse_per_trajectory.csv`): "
                "on the training trajectories how well the network fits the nonlinearity, on the test ones how "
                "well it generalises. A test share above the training one is a generalisation gap (more load "
                "cases help); equal shares point to the fit (capacity, training).", "",
                "| split | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups),
                f"| train ({len(train_trajs)}) | " + " | ".join(_fmt(left["train"][g]) for g in groups) + " |",
                f"| test ({len(test)}) | " + " | ".join(_fmt(left["test"][g]) for g in groups) + " |", ""]
               if left else []),
             *([f"Where σ comes from (test rollouts, all steps and nodes pooled; `stress_*` in `rrmse.json`): "
                f"σ = {stress_name} of the displacement + the learned remainder H "
                f"(H along the predicted path, the exact H along the data): {stress_split_sentence(split, 'σ')}. "
                "A learned H far below the exact one with a gap above the model's whole σ error means the "
                "displacement stands in for H (its strains bent to fit σ): `train.stress_remainder_weight` "
                "gives H its own target, `model.prior_stress=material` (elastic neo-Hookean data) no H to learn.", ""]
               if split else []),
             "One step from every true state z[s] (the model's own step), error of its change "
             "||dz_pred - dz_gt|| / ||dz_gt|| over all steps and nodes, dz = z[s+1] - z[s]: what "
             "the network has learned, apart from any drift of its rollouts (near 1: the step is "
             "not learned; far below the rollout error: the rollout drifts off the data); per step "
             "in `one_step_vs_time.csv`:", "",
             "| split | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups),
             "| test | " + " | ".join(_fmt(step_test[g]) for g in groups) + " |",
             "| train | " + " | ".join(_fmt(step_train[g]) for g in groups) + " |",
             *([f"| {prior_name} FE, test | " + " | ".join(_fmt(step_linear[g]) for g in groups) + " |", "",
                f"The {prior_name} FE model's row is the model's prior alone from the same true states (no "
                "network): the figure the learned step is measured against. Where the body moves nearly "
                "quasi-statically (loads balanced by the internal force, little inertia) a step's change "
                "is a small difference of large forces, and both can exceed 1 while the rollouts track."]
               if step_linear else []), "",
             "Files: " + ", ".join(f"`{f}`" for f in files), ""]
    with atomic_path(out / "summary.md") as tmp:
        tmp.write_text("\n".join(lines))
    return mean_test
