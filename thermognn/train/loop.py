"""Training loop: Adam + exponential decay, noise injection, best checkpoint by validation rollout
error, early stopping, resume from ``model.last.ckpt`` (also from within an epoch), optional data
parallelism (torchrun)."""

from __future__ import annotations

import csv
import hashlib
import math
import os
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from thermognn.core.config import project_path, to_yaml
from thermognn.core.errors import ConfigError, DataError
from thermognn.core.io import atomic_path, versions_json
from thermognn.core.state import is_reversible

from .checkpoint import (FORMAT, last_path, load_checkpoint, model_from_checkpoint, save_checkpoint,
                         torch_dtype)
from .data import (LoadedData, check_fingerprint, compute_stats, fingerprint, load_data, make_batch,
                   make_window_batch, rest_rollout_steps, rest_samples, rest_trajectory, samples, state_images,
                   velocity_columns, window_starts)
from .device import cpu_randn, training_device
from .hybrid import prior_alone_candidate, prior_kind, prior_settings, train_linear_prior, training_phases
from .model import TIGNN, build_model, grown_blocks, hyperparameters, load_grown, parameter_count
from .rollout import rollout, rollout_errors, validation_error

METRIC_FIELDS = ["epoch", "lr", "loss", "data_loss", "degeneracy_loss", "rest_growth", "val_error", "seconds"]


def _sel(cfg, key: str, default):
    return OmegaConf.select(cfg, key, default=default)


def resolve_structure(structure: str, effects, dataset_config: str = "") -> str:
    """'auto' -> hamiltonian for reversible scenes, else generic.

    Reversible: no viscous effect (``is_reversible``), and, when the dataset's generating config
    says so, inertia present, no Rayleigh damping and a non-dissipative integrator (Newmark
    trapezoidal); quasi-static or damped data need the dissipative (GENERIC) part."""
    structure = str(structure)
    if structure == "auto":
        reversible = is_reversible(effects) and "inertia" in tuple(effects)
        if reversible and dataset_config:
            try:
                scene_time = OmegaConf.select(OmegaConf.create(dataset_config), "scene.time", default=None)
            except Exception:  # noqa: BLE001 - an unparsable config says nothing about damping
                scene_time = None
            if scene_time is not None:
                damping = [float(x) for x in (OmegaConf.select(scene_time, "rayleigh", default=None) or [])]
                integrator = str(OmegaConf.select(scene_time, "integrator", default="newmark"))
                reversible = not any(damping) and integrator == "newmark"
        return "hamiltonian" if reversible else "generic"
    if structure not in ("generic", "hamiltonian"):
        raise ConfigError(f"model.structure = {structure!r}, expected auto, generic or hamiltonian")
    return structure


class _Dist:
    """Data parallelism without DDP's wrapper (it does not support autograd.grad inside forward):
    each rank takes a shard of every epoch's batches, gradients are averaged with all_reduce."""

    def __init__(self) -> None:
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        if self.world > 1:
            import torch.distributed as dist

            if not dist.is_initialized():
                dist.init_process_group("gloo")
            self.dist = dist

    @property
    def main(self) -> bool:
        return self.rank == 0

    def average_gradients(self, model: torch.nn.Module) -> None:
        if self.world == 1:
            return
        for p in model.parameters():
            if p.grad is not None:
                self.dist.all_reduce(p.grad, op=self.dist.ReduceOp.SUM)
                p.grad /= self.world

    def mean(self, values: list[float]) -> list[float]:
        """The mean of each value over the processes (as given in one process)."""
        if self.world == 1:
            return list(values)
        t = torch.tensor(values, dtype=torch.float64)
        self.dist.all_reduce(t, op=self.dist.ReduceOp.SUM)
        return (t / self.world).tolist()

    def agree(self, flag: bool) -> bool:
        """Rank 0's ``flag`` in every process (e.g. its clock's call to write a checkpoint)."""
        if self.world == 1:
            return flag
        t = torch.tensor([1.0 if flag else 0.0], dtype=torch.float64)
        self.dist.broadcast(t, src=0)
        return bool(t.item())

    def gather(self, values: list[float]) -> list[list[float]]:
        """Each process's ``values``, in rank order (in every process)."""
        if self.world == 1:
            return [list(values)]
        parts = [torch.zeros(len(values), dtype=torch.float64) for _ in range(self.world)]
        self.dist.all_gather(parts, torch.tensor(values, dtype=torch.float64))
        return [t.tolist() for t in parts]

    def barrier(self) -> None:
        if self.world > 1:
            self.dist.barrier()

    def close(self) -> None:
        if self.world > 1 and self.dist.is_initialized():
            self.dist.destroy_process_group()


class EpochCheckpoints:
    """``train.checkpoint_minutes``: when ``model.last.ckpt`` is also written within an epoch, and
    the place in the epoch it keeps (checkpoint key ``mid_epoch``), in one process or under
    torchrun (rank 0's clock decides for all; every process's running sums are kept)."""

    def __init__(self, minutes: float, dist: _Dist) -> None:
        self.every_s, self.dist = 60.0 * float(minutes), dist
        self.saved_at = time.perf_counter()

    def start(self) -> None:
        """An epoch (or its resumed part) begins: the clock starts."""
        self.saved_at = time.perf_counter()

    def due(self, more_batches: bool) -> bool:
        """Whether to write now (the same answer in every process; a collective under torchrun)."""
        if self.every_s <= 0:
            return False
        return self.dist.agree(more_batches and time.perf_counter() - self.saved_at >= self.every_s)

    def place(self, order: list[int], batch: int, totals: list[float], **extra) -> dict:
        """``mid_epoch``: the epoch's whole sample ``order``, the next ``batch`` of this process's
        share and its running ``totals`` (every process calls this: it gathers all processes')."""
        self.saved_at = time.perf_counter()
        place = {"perm": order, "batch": batch, "totals": list(totals), **extra}
        if self.dist.world > 1:
            place.update(world=self.dist.world, rank_totals=self.dist.gather(list(totals)))
        return place

    def resume(self, place: dict, last: Path, epoch: int) -> tuple[list[int], int, list[float]]:
        """The order, next batch and this process's running totals of an interrupted ``epoch``
        (1-based); refused where it was written by another number of processes."""
        world = int(place.get("world", 1))
        if world != self.dist.world:
            raise ConfigError(f"{last}: written within epoch {epoch} by {world} process(es), resumed by "
                              f"{self.dist.world}; resume it with {world} (torchrun --nproc-per-node {world}) or "
                              f"pass train.resume=false to train from scratch")
        totals = place["rank_totals"][self.dist.rank] if world > 1 else place["totals"]
        return list(place["perm"]), int(place["batch"]), list(totals)


def step_loss(model: TIGNN, batch, dt: float, noise: float, generator: torch.Generator,
              lambda_data: float, lambda_degeneracy: float,
              gradient_weight: float = 0.0) -> tuple[torch.Tensor, float, float]:
    """Loss of one batch: lambda_data (MSE(dz/dt, normalised) + gradient_weight MSE of its
    differences across the mesh edges, ``rate_gradient_error``) + lambda_degeneracy degeneracy.

    Training noise perturbs the input state of the free entries by ``noise`` times a typical
    step's change of each column (dzdt_std * dt), and the target rate is taken from the perturbed
    input to the true next state: the network learns to bring a state that drifted off the data
    (e.g. a stress no longer consistent with the strain) back, the usual cure for rollout drift."""
    z, z_next = batch.z, batch.z_next                                   # [B*N, D]
    free = model.free_entries(batch.node_type, z)                      # [B*N, D]
    if noise > 0:
        eps = cpu_randn(z.shape, generator, z) * (noise * dt) * model.dzdt_std
        z = z + eps * free
    at = model.rate_state(z, z_next)                 # z (Euler) or the step's midpoint (midpoint rule)
    dzdt_n, _, _, _, _, deg = model.rates(at, batch.f, batch.edge_index, batch.node_type, batch.pos, True, False)
    target = (z_next - z) / dt / model.dzdt_std
    data_loss = ((dzdt_n - target).pow(2) * free).sum() / free.sum().clamp(min=1.0)
    if gradient_weight > 0:
        data_loss = data_loss + gradient_weight * rate_gradient_error(dzdt_n, target, free, batch.edge_index)
    loss = lambda_data * data_loss + lambda_degeneracy * deg
    return loss, float(data_loss.detach()), float(deg.detach())


def rate_gradient_error(rate: torch.Tensor, target: torch.Tensor, free: torch.Tensor,
                        edge_index: torch.Tensor) -> torch.Tensor:
    """The rate error's differences across the mesh edges (i, j), (e_i - e_j)^2, each column
    relative to the mean square of the target's own differences there (0-dim; rate, target,
    free [N, D], edge_index [2, E]). The plain MSE weighs an error by its size at each node; a
    stress read off the positions (``model.stress_readout``) is a strain, a difference of nearby
    displacements, so it feels the error's variation from node to node, which this term weighs
    (``train.rate_gradient_weight``: a Sobolev loss on the step). With training noise the target
    is taken from the perturbed input (``step_loss``), so the term also weighs how well the step
    takes back a perturbation that varies from node to node."""
    src, dst = edge_index[0], edge_index[1]
    err = (rate - target) * free                                                     # [N, D]
    diff = (err[src] - err[dst]).pow(2)                                              # [E, D]
    scale = (target[src] - target[dst]).pow(2).mean(0).detach().clamp(min=1e-30)     # [D]
    counted = ((free[src] + free[dst]) > 0).to(rate.dtype)                           # [E, D]
    return (diff / scale * counted).sum() / counted.sum().clamp(min=1.0)


def edge_step_scale(trajs: list, edge_index: torch.Tensor, step_change: torch.Tensor) -> torch.Tensor:
    """The mean square of a true step's change across the mesh edges, per state column, in units
    of a typical step's change ``step_change`` [D] (dzdt_std * dt), over every training step ([D]):
    the fixed scale of a training window's edge term (``window_loss``)."""
    src, dst = edge_index[0], edge_index[1]
    per = []
    with torch.no_grad():
        for t in trajs:
            change = (t.z[1:] - t.z[:-1]) / step_change                            # [S, N, D]
            per.append((change[:, src] - change[:, dst]).pow(2).mean((0, 1)))     # [D]
    scale = torch.stack(per).mean(0)
    # a column whose true steps never vary across the edges (e.g. the same at every node) is
    # measured against the columns' mean instead of ~0
    return torch.where(scale > 1e-6 * scale.mean(), scale, scale.mean()).clamp(min=1e-30)


def window_loss(model: TIGNN, batch, dt: float, column_weights: torch.Tensor, edge_scale: torch.Tensor,
                lambda_data: float, lambda_degeneracy: float,
                gradient_weight: float = 0.0, readout: torch.nn.Module | None = None,
                readout_weight: float = 0.0) -> tuple[torch.Tensor, float, float]:
    """Loss of a batch of training windows (``train.window_steps``, ``make_window_batch``): the
    model rolls each window out from its true first state, back-propagated through every step,
    and at each step k its accumulated error e_k = (z_k - z_true_k) / (dt * dzdt_std) [B*N, D]
    (the one-step MSE's units: at k = 1 it is that MSE) is weighed as

        lambda_data * (mean_k MSE(e_k) + gradient_weight * mean_k (e_k,i - e_k,j)^2 / edge_scale)
        + lambda_degeneracy * mean_k degeneracy,

    the squares weighted per column by ``column_weights`` [D] (``train.window_weights``) and the
    edge term over the mesh edges (i, j) relative to a true step's own (``edge_step_scale``, fixed:
    a window's own scale made windows of slow steps weigh 10-100x). A rollout's error is what the
    one-step loss only bounds step by step; a stress read off the positions feels its variation
    across the edges (``rate_gradient_error``).

    With a stress ``readout`` (``train.window_readout_weight``: the init's, fitted to its rollouts,
    kept fixed) the data term adds readout_weight * mean_k MSE(r_k) over the free stress entries,
    r_k = (readout(q_k - X, f_k) - σ_true_k) / (dt * dzdt_std_σ): the stress the product reports,
    read off the predicted positions, against the data's. Its gradient reaches the network through
    the positions only, so the network learns positions whose read-off stress is right.

    A model with mirror frames (``model.mirror_average``) rolls the windows out as it steps: each
    step the mean over the frames (``TIGNN.frame_images``, ``frame_mean``), at G times the cost, so
    the network learns the averaged rollouts the product gives rather than each frame's own."""
    Z, F = batch.z, batch.f                                            # [W+1, B*N, D], [W+1, B*N, 3]
    steps = Z.shape[0] - 1
    step_change = dt * model.dzdt_std                                  # [D]
    unweighted = model.free_entries(batch.node_type, Z[0])           # [B*N, D]
    free = unweighted * column_weights                                 # [B*N, D]
    src, dst = batch.edge_index[0], batch.edge_index[1]
    dt_t = torch.tensor(dt, dtype=Z.dtype, device=Z.device)
    reading = readout is not None and readout_weight > 0
    if reading:
        sig = list(readout.columns)                                    # the stress columns it reads
        free_sig = unweighted[:, sig]                                  # [B*N, S]
        n_nodes = int(readout.nodes)
        copies = Z.shape[1] // n_nodes                                 # B disjoint copies of the mesh
    z, data, deg = Z[0], Z.new_zeros(()), Z.new_zeros(())
    for k in range(1, steps + 1):
        if model.n_frames > 0:                     # the step the product takes: the mean over the mirror frames
            zg, fg, edges, types, pos = model.frame_images(z, F[k], batch.edge_index, batch.node_type, batch.pos)
            rate, _, _, _, _, d = model.rates(zg, fg, edges, types, pos, True, True)
            z = model.frame_mean(model.advance(zg, rate, dt_t, types, pos), batch.node_type, batch.pos)
        else:
            rate, _, _, _, _, d = model.rates(z, F[k], batch.edge_index, batch.node_type, batch.pos, True, True)
            z = model.advance(z, rate, dt_t, batch.node_type, batch.pos)
        e = (z - Z[k]) / step_change                                   # [B*N, D]
        data = data + (e.pow(2) * free).sum() / free.sum().clamp(min=1e-30)
        if gradient_weight > 0:
            ef = e * free
            data = data + gradient_weight * ((ef[src] - ef[dst]).pow(2) / edge_scale).mean()
        if reading:
            u = (z[:, :3] - batch.pos).reshape(copies, n_nodes, 3)      # [B, N, 3]
            f = F[k].reshape(copies, n_nodes, 3)                       # [B, N, 3]: state k's load
            read = readout(u, f).reshape(copies * n_nodes, -1)         # [B*N, S]
            r = (read - Z[k][:, sig]) / step_change[sig]               # [B*N, S]
            data = data + readout_weight * (r.pow(2) * free_sig).sum() / free_sig.sum().clamp(min=1e-30)
        deg = deg + d
    data, deg = data / steps, deg / steps
    return lambda_data * data + lambda_degeneracy * deg, float(data.detach()), float(deg.detach())


def readout_folds(tc) -> int:
    """``train.readout_folds``: folds of load groups the fitted stress readout is checked on (0: off)."""
    k = _sel(tc, "readout_folds", 0)
    if isinstance(k, bool) or not isinstance(k, int) or k < 0 or k == 1:
        raise ConfigError(f"train.readout_folds = {k!r}, expected 0 (off) or the number of folds of load groups "
                          "the stress readout is checked on (an integer >= 2)")
    return k


def readout_ridge(cfg, hops: int, folds: int, modes: int) -> float | list[float]:
    """``model.stress_readout_ridge``: the stress readout's ridge (relative; 0: the fit's round-off
    guard alone), or a list of ridges each neighbourhood shape chooses among by the held-out load
    groups of ``train.readout_folds`` (``fit_stress_readout``)."""
    from .stress_readout import AUTO_RIDGES

    given = _sel(cfg, "model.stress_readout_ridge", 0)
    given = 0 if given is None else given
    if OmegaConf.is_config(given):
        given = OmegaConf.to_container(given)
    values = list(AUTO_RIDGES) if given == "auto" else given if isinstance(given, list) else [given]
    if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0
                             for v in values):
        raise ConfigError(f"model.stress_readout_ridge = {given!r}, expected a ridge >= 0 (relative to the "
                          "fit's equations), a list of them to choose among per neighbourhood shape, or auto "
                          f"({len(AUTO_RIDGES)} of them: 0 and 1e-10 ... 1e-2 in half decades)")
    if any(values) and not hops:
        raise ConfigError(f"model.stress_readout_ridge = {given!r}: a ridge of a stress readout's fit; "
                          "set model.stress_readout to its reach in hops (>= 1)")
    if len(values) > 1 and (folds < 2 or modes):
        raise ConfigError(f"model.stress_readout_ridge = {given!r}: each shape chooses among these by the "
                          "held-out load groups of train.readout_folds, expected train.readout_folds >= 2 "
                          f"(it is {folds}) and model.stress_readout_modes = 0 (it is {modes})")
    return [float(v) for v in values] if len(values) > 1 else float(values[0])


def ridge_sentence(counts) -> str:
    """Words on ``stress_readout.ridge_counts``."""
    return ("ridge chosen per neighbourhood shape by the held-out load groups (model.stress_readout_ridge): "
            + ", ".join(f"{v:g} for {int(c)} shape{'s' if c > 1 else ''}" for v, c in counts))


def held_out_sentence(check: dict) -> str:
    """``train``'s line on the stress readout's check on held-out loads (``held_out_loads_check``)."""
    if not check.get("folds"):
        return f"stress readout on held-out loads: not checked ({check.get('reason', '')})"
    chosen = f"; {ridge_sentence(check['ridge'])}" if check.get("ridge") else ""
    if check.get("first_ridge"):
        alone = check["first_ridge"]
        chosen += (f"; every shape at ridge {alone['ridge']:g} instead: held out {alone['per_snapshot']:.2%}, "
                   f"on the loads fitted {alone['in_sample_per_snapshot']:.2%}")
    return (f"stress readout on held-out loads ({check['groups']} load groups in {check['folds']} folds, "
            f"each read by a readout fitted to the other folds' training rollouts; train.readout_folds): "
            f"sigma per snapshot {check['per_snapshot']:.2%}, whole {check['whole']:.2%}; "
            f"on the loads it was fitted to {check['in_sample_per_snapshot']:.2%}, {check['in_sample_whole']:.2%}; "
            f"worst held out: the group loaded at ({', '.join(f'{v:.4g}' for v in check['worst_group_load_point'])}) m, "
            f"{check['worst_group_per_snapshot']:.2%}{chosen}")


def window_steps(tc) -> int:
    """``train.window_steps``: the length of the training windows (0: one-step pairs)."""
    w = _sel(tc, "window_steps", 0)
    if isinstance(w, bool) or not isinstance(w, int) or w < 0:
        raise ConfigError(f"train.window_steps = {w!r}, expected 0 (one-step pairs) or the steps of each "
                          "training window (an integer >= 1)")
    return w


def window_column_weights(tc, layout, like: torch.Tensor) -> torch.Tensor:
    """``train.window_weights``: {state group: weight} -> a weight per state column [D] (groups not
    named weigh 1), e.g. {sigma: 0.1} where the stress reported is read off the positions."""
    given = _sel(tc, "window_weights", None) or {}
    given = OmegaConf.to_container(given) if OmegaConf.is_config(given) else given
    if not isinstance(given, dict):
        raise ConfigError(f"train.window_weights = {given!r}, expected a mapping of state groups "
                          f"{layout.names} to weights >= 0")
    weights = torch.ones(layout.dim, dtype=like.dtype, device=like.device)
    for name, w in given.items():
        if name not in layout.names:
            raise ConfigError(f"train.window_weights: unknown state group {name!r}, expected some of {layout.names}")
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w) or w < 0:
            raise ConfigError(f"train.window_weights.{name} = {w!r}, expected a finite number >= 0")
        weights[layout.slice(name)] = float(w)
    if float(weights.sum()) == 0.0:
        raise ConfigError("train.window_weights: every group weighs 0, nothing left to train")
    return weights


#: largest deviation of a rollout-pair input from the truth, in typical steps' changes per column
ROLLOUT_CLIP = 10.0


def drifted_states(model: TIGNN, graph, trajs: list, dt: float) -> list[torch.Tensor]:
    """The model's own rollout of each training trajectory ([S, N, D] each, from z[0]), each
    state's deviation from the truth clipped to ROLLOUT_CLIP typical steps' changes
    (dzdt_std * dt) per column so that an early, wild model gives bounded targets. Paired with
    the true next states (``train.rollout_pairs``), they teach the network to steer its own
    drift (a lagging stress, a sluggish response) back to the data, as DAgger does."""
    model.eval()
    bound = ROLLOUT_CLIP * dt * model.dzdt_std.detach()                 # [D]
    out = []
    for t in trajs:
        pred = rollout(model, graph, t.z[0], t.force, dt)
        dev = torch.nan_to_num(pred - t.z, nan=0.0, posinf=0.0, neginf=0.0)
        out.append(t.z + torch.maximum(torch.minimum(dev, bound), -bound))
    return out


#: RMS size of a rest-stability probe per free entry, in typical steps' changes (dzdt_std * dt),
#: small enough to measure the linear step at rest: the smallest of the default
#: ``train.rest_stability_probe`` sizes, and the only one before that key existed
STABILITY_PROBE = 0.3
#: at most this many probe sizes (each costs one more copy of the mesh in the probe's pass)
MAX_PROBES = 8


def rest_growth(model: TIGNN, rest, graph, dt: float, directions: torch.Tensor, sizes,
                create_graph: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """How much one step of the model amplifies disturbances of the unloaded rest state
    ``rest.z[0]``: one along each of ``directions`` [K, N, D] (in units of a typical step's change
    per column), of RMS ``sizes[k]`` typical steps per free entry, by finite differences of the
    step map Phi: g_k = |Phi(z0 + d_k) - Phi(z0)| / |d_k| ([K], differentiable in the weights), and
    the next directions of the power iterations, (Phi(z0 + d_k) - Phi(z0)) / |...| ([K, N, D],
    detached). Iterated once per batch, each d_k turns toward the step's fastest-growing mode at
    rest for its size, where a stable step has g <= 1 (``train.rest_stability`` penalises g above
    1; ``create_graph=False`` to measure only). A small probe measures the linear step (the
    Jacobian J); a larger one, the secant growth a drift of that size meets. All K + 1 states go
    through the network in one pass, on disjoint copies of the mesh."""
    z0, f = rest.z[0], rest.force[0]
    k, n = directions.shape[0], z0.shape[0]
    scale = dt * model.dzdt_std.detach()                                # [D]
    free = model.free_entries(graph.node_type, z0)                      # [N, D]
    d = directions * free                                               # [K, N, D]
    size = torch.as_tensor([float(x) for x in sizes], dtype=z0.dtype).view(k, 1, 1)
    d = d * (size * float(free.sum()) ** 0.5 / d.flatten(1).norm(dim=1).clamp(min=1e-30).view(k, 1, 1))
    dt_t = torch.tensor(dt, dtype=z0.dtype)
    copies = graph.copies(k + 1)
    z = torch.cat([z0.unsqueeze(0), z0 + d * scale]).reshape((k + 1) * n, -1)    # [(K+1) N, D]
    r = model.rates(z, f.repeat(k + 1, 1), copies.edge_index, copies.node_type, copies.ref_pos, create_graph, False)[0]
    stepped = model.advance(z, r, dt_t, copies.node_type, copies.ref_pos).view(k + 1, n, -1)
    jd = (stepped[1:] - stepped[:1]) / scale * free                     # [K, N, D], typical steps
    norm = jd.flatten(1).norm(dim=1)                                    # [K]
    return norm / d.flatten(1).norm(dim=1), (jd / norm.clamp(min=1e-30).view(k, 1, 1)).detach()


def stability_probe_sizes(value) -> tuple[float, ...]:
    """``train.rest_stability_probe``: the probe sizes (RMS per free entry, in typical steps'
    changes), one number or a list of up to MAX_PROBES; each size keeps its own power iteration."""
    sizes = OmegaConf.to_container(value) if OmegaConf.is_config(value) else value
    sizes = list(sizes) if isinstance(sizes, (list, tuple)) else [sizes]
    try:
        out = tuple(float(x) for x in sizes)
    except (TypeError, ValueError):
        out = ()
    if not (1 <= len(out) <= MAX_PROBES and all(0 < x < math.inf for x in out)):
        raise ConfigError(f"train.rest_stability_probe = {value}, expected a probe size > 0 or a list of up to "
                          f"{MAX_PROBES}, in typical steps' changes (e.g. 0.3 or [0.3, 3, 30])")
    return out


#: hyperparameters that change how the model steps but not its weights
STEP_ONLY = ("integrator", "implicit_iterations", "exact_kinematics", "mirror_frames")
#: what training fits anew at its end: a fine-tune may start from a checkpoint with or without it
REFITTED = ("stress_readout",)


def warm_start(model: TIGNN, src: dict, path: Path, ds, hparams: dict) -> dict:
    """Load weights and normalisation statistics of the checkpoint ``src`` (``train.init``, read from
    ``path``) into ``model``; it must fit the dataset and have the same hyperparameters, except those of the time
    step alone (``STEP_ONLY``: a model may be fine-tuned under another integrator), or more processor
    blocks (``model.message_passing``; the new ones start as the identity: ``load_grown``). Returns its stats."""
    check_fingerprint(src["fingerprint"], ds, path, hint="train.init must come from this dataset")
    grown = grown_blocks(src["hparams"], hparams)     # more processor blocks here: a grown model
    changed = sorted(k for k in set(hparams) | set(src["hparams"])
                     if k not in STEP_ONLY + REFITTED and src["hparams"].get(k) != hparams.get(k)
                     and not (grown and k == "message_passing"))
    if changed:
        raise ConfigError(f"train.init = '{path}': its model differs from this run's in "
                          + ", ".join(f"{k} ({src['hparams'].get(k)} there, {hparams.get(k)} here)" for k in changed))
    state = {k: v for k, v in src["state_dict"].items() if not k.startswith(("readout.", "frame_"))}  # refitted
    state.update({k: v for k, v in model.state_dict().items() if k.startswith("frame_")})   # this run's frames
    if grown:
        load_grown(model, state, grown)
    else:
        model.load_state_dict(state)
    return {k: v.clone() for k, v in src["stats"].items()}


#: train settings a resumed run must share with the interrupted one (besides model and dataset)
RESUME_KEYS = ("batch_size", "lr", "lr_decay", "lambda_data", "lambda_degeneracy", "noise", "split",
               "rollout_pairs", "start_repeats", "rest_samples", "init")
#: later training terms, part of the identity only when on: a run interrupted before they existed resumes
#: (with the value that leaves them as they were before: off, or the former fixed behaviour)
OPTIONAL_RESUME_KEYS = {"rest_rollout": 0, "rest_stability": 0, "rest_stability_probe": STABILITY_PROBE,
                        "rest_stability_every": 1, "symmetry_augment": False, "rate_gradient_weight": 0.0,
                        "window_steps": 0, "window_weights": None, "window_readout_weight": 0.0}
#: settings of the rest-stability penalty, which matter only while it is on
STABILITY_SETTINGS = ("rest_stability_probe", "rest_stability_every")


def _without_off_terms(identity: dict) -> dict:
    """``identity`` without the OPTIONAL_RESUME_KEYS that are absent (None) or at their former
    value, nor the penalty's settings while it is off."""
    def off(k):
        return identity.get(k) is None or identity.get(k) == OPTIONAL_RESUME_KEYS[k]
    drop = {k for k in OPTIONAL_RESUME_KEYS if off(k)} | (set(STABILITY_SETTINGS) if off("rest_stability") else set())
    return {k: v for k, v in identity.items() if k not in drop}


def training_identity(cfg, hparams: dict, dtype_name: str) -> dict:
    """What must not change for ``model.last.ckpt`` to be resumed (epochs, patience, threads may).
    With ``train.init`` its file's contents count too (``init_digest``), not only its path: a
    checkpoint written anew at the same path (the next of a chain of fine-tunes) starts afresh. Not
    where the init is the run's own checkpoint, which the run itself rewrites (it resumes)."""
    identity = _without_off_terms(
        {"hparams": hparams, "dtype": dtype_name, "seed": int(_sel(cfg, "seed", 0)),
         **{k: OmegaConf.to_container(v) if OmegaConf.is_config(v) else v
            for k in RESUME_KEYS + tuple(OPTIONAL_RESUME_KEYS) for v in [_sel(cfg.train, k, None)]}})
    init = _sel(cfg.train, "init", None)
    own = project_path(str(_sel(cfg, "paths.checkpoint", ""))).resolve()
    if init and project_path(str(init)).is_file() and project_path(str(init)).resolve() != own:
        identity["init_digest"] = hashlib.sha256(project_path(str(init)).read_bytes()).hexdigest()
    return identity


def identity_changes(stored: dict, identity: dict) -> list[str]:
    """The keys in which a checkpoint's stored training identity differs from this run's; one stored
    before ``init_digest`` existed is compared without it (it resumes as it did)."""
    if "init_digest" not in stored:
        identity = {k: v for k, v in identity.items() if k != "init_digest"}
    return sorted(k for k in set(identity) | set(stored) if stored.get(k) != identity.get(k))


def _fits(model: torch.nn.Module, state_dict: dict) -> bool:
    own = model.state_dict()
    return set(own) == set(state_dict) and all(own[k].shape == state_dict[k].shape for k in own)


def _base_checkpoint(cfg, data: LoadedData, hparams: dict, dtype_name: str, structure: str,
                     stats: dict) -> dict:
    ds = data.dataset
    return {"format": FORMAT, "hparams": hparams, "dtype": dtype_name,
            "stats": {k: v.clone() for k, v in stats.items()},
            "state_layout": ds.layout.to_json(), "dt": float(ds.dt), "effects": list(ds.effects),
            "structure": structure, "scene": ds.scene, "config": to_yaml(cfg), "versions": versions_json(),
            "dataset": str(data.path), "fingerprint": fingerprint(ds), "split": data.split}


def _write_metrics(path: Path, history: list[dict], fields: list[str] = METRIC_FIELDS) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            for row in history:
                w.writerow({k: row.get(k, "") for k in fields})


def _tensorboard(setting, log_dir: Path):
    """A TensorBoard SummaryWriter under ``log_dir`` (``train.tensorboard``: auto = when the
    tensorboard package is installed, true = required, false = off), or None."""
    mode = str(setting).lower()
    if mode in ("false", "off", "none"):
        return None
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        if mode == "true":
            raise ConfigError("train.tensorboard = true, but the tensorboard package is not installed "
                              "(pip install tensorboard, or train.tensorboard=auto)") from None
        return None
    return SummaryWriter(log_dir=str(log_dir))


def _progress(disable: bool = False):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    return Progress(TextColumn("[bold]train"), BarColumn(), MofNCompleteColumn(),
                    TextColumn("{task.fields[info]}"), TimeRemainingColumn(), disable=disable)


def print_rrmse_table(title: str, rows: dict[str, dict[str, float]]) -> None:
    """rows: {label: {group: rrmse}} as a rich table."""
    from rich.console import Console
    from rich.table import Table

    groups = list(next(iter(rows.values())))
    table = Table(title=title)
    table.add_column("")
    for g in groups:
        table.add_column(f"RRMSE {g}", justify="right")
    for label, r in rows.items():
        table.add_row(label, *[f"{r.get(g, float('nan')):.3e}" for g in groups])
    Console().print(table)


def training_images(data: LoadedData, where: str, key: str = "train.symmetry_augment") -> list:
    """``train.symmetry_augment`` (or ``model.mirror_average``, ``key``): the mesh's mirror frames that
    keep the supports, the node types and (with ``gravity``, the scene's ``gravity`` vector from the
    dataset's configuration) the body force; prints a line where the mesh has no symmetry but the
    identity (the option then changes nothing)."""
    gravity = None
    if "gravity" in data.dataset.effects:          # read as resolve_structure reads the dataset's config
        gravity = OmegaConf.select(OmegaConf.create(data.dataset.config_yaml or ""), "scene.gravity", default=None)
        if gravity is None:
            raise ConfigError(f"{key} = true: {where} has gravity but its stored configuration "
                              "names no scene.gravity vector, so no mirror is known to keep it")
    images = state_images(data.graph, data.layout, None if gravity is None else list(gravity), key=key)
    if len(images) == 1:
        print(f"{key}: the mesh of {where} has no mirror symmetry"
              + (" that keeps gravity" if gravity is not None else "") + "; training as without it")
    return images


def frame_name(rotation) -> str:
    """A mirror frame by where it sends (x, y, z), e.g. '(x, z, -y)'."""
    axes = []
    for row in rotation.tolist():
        k = max(range(3), key=lambda j: abs(row[j]))
        axes.append(("-" if row[k] < 0 else "") + "xyz"[k])
    return "(" + ", ".join(axes) + ")"


def averaged_frames(data: LoadedData, setting) -> list:
    """``model.mirror_average``: the mesh's mirror frames a step is averaged over, all of them
    (true) or those listed by index; a list must be a group (closed under composition: the
    mean is then exactly equivariant under it). Prints the mesh's frames and the choice."""
    images = training_images(data, str(data.path), "model.mirror_average")
    names = [f"{k} {frame_name(im.rotation)}" for k, im in enumerate(images)]
    chosen = list(range(len(images))) if setting is True else list(setting)
    if len(set(chosen)) != len(chosen) or not all(0 <= k < len(images) for k in chosen):
        raise ConfigError(f"model.mirror_average = {setting}: expected distinct frame indices from 0 to "
                          f"{len(images) - 1}, the mirror frames of {data.path}: {', '.join(names)}")
    sources = {tuple(images[k].source.tolist()): k for k in chosen}
    for a in chosen:
        for b in chosen:      # b's image of a's image: node k comes from source_a[source_b[k]]
            both = tuple(images[a].source[images[b].source].tolist())
            if both not in sources:
                c = next((k for k, im in enumerate(images) if tuple(im.source.tolist()) == both), None)
                raise ConfigError(f"model.mirror_average = {setting}: not a group, frame {a} then {b} is frame "
                                  f"{c}, not listed (the mean is exactly equivariant over a group only); the "
                                  f"mirror frames of {data.path}: {', '.join(names)}")
    if len(images) > 1:
        print(f"model.mirror_average: the mirror frames of {data.path}: {', '.join(names)}; averaging over "
              + ", ".join(str(k) for k in chosen))
    return [images[k] for k in chosen]


def rate_gradient_weight(tc) -> float:
    """``train.rate_gradient_weight`` (0 or absent: off), a ConfigError unless a finite number >= 0
    (as ``train.stress_remainder_weight``'s check in ``hybrid.training_phases``)."""
    raw = _sel(tc, "rate_gradient_weight", 0.0)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not (math.isfinite(raw) and raw >= 0):
        raise ConfigError(f"train.rate_gradient_weight = {raw!r}, expected a number >= 0 (the weight of the "
                          "rate error's differences across the mesh edges; 0: off)")
    return float(raw)


def window_readout(tc, cfg, window: int, like: torch.Tensor,
                   src: dict | None) -> tuple[torch.nn.Module | None, float]:
    """``train.window_readout_weight`` (0 or absent: off): (the stress readout of ``train.init``, its
    checkpoint ``src`` as loaded (None: no init), fitted to its rollouts and kept fixed, on ``like``'s
    device; the weight) for ``window_loss``, or
    (None, 0.0). A ConfigError, in one line, unless the weight is a finite number >= 0 and, where it is
    on, the run trains windows (``train.window_steps``) with a stress readout (``model.stress_readout``)
    from an init that has one fitted."""
    raw = _sel(tc, "window_readout_weight", 0.0)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not (math.isfinite(raw) and raw >= 0):
        raise ConfigError(f"train.window_readout_weight = {raw!r}, expected a number >= 0 (the weight of the "
                          "stress read off the predicted positions in the window loss; 0: off)")
    if raw == 0:
        return None, 0.0
    if not window:
        raise ConfigError(f"train.window_readout_weight = {raw}: the read-off stress is weighed along the "
                          "training windows; set train.window_steps >= 1")
    if not readout_hops(cfg):
        raise ConfigError(f"train.window_readout_weight = {raw}: trains the positions a stress readout reads; "
                          "set model.stress_readout")
    init = _sel(tc, "init", None)
    if src is None or not src["hparams"].get("stress_readout"):
        raise ConfigError(f"train.window_readout_weight = {raw}: needs train.init with a fitted stress readout "
                          f"(model.stress_readout), got {'no train.init' if src is None else repr(str(init))}")
    readout = model_from_checkpoint(src).readout.to(like.device).eval()
    for p in readout.parameters():
        p.requires_grad_(False)
    return readout, float(raw)


def readout_hops(cfg) -> int:
    """``model.stress_readout``: the stress readout's reach in hops (0 or absent: off)."""
    return int(_sel(cfg, "model.stress_readout", 0) or 0)


def train(cfg) -> Path:
    """Train on ``cfg.paths.dataset``; write the best checkpoint ``cfg.paths.checkpoint`` and
    ``<out>/metrics.csv``; resume from ``model.last.ckpt`` when present and compatible. It is also
    written every ``train.checkpoint_minutes`` within an epoch (the epoch's sample order, the batch
    reached, the running sums, and the weights the epoch's drifted states came from), and an
    interrupted epoch goes on at its next batch (under torchrun, resumed by as many processes).
    It runs on ``train.device`` (the CPU, or a CUDA GPU: ``thermognn.train.device``)."""
    device = training_device(_sel(cfg.train, "device", "cpu"))
    if device.type == "cuda":
        torch.cuda.set_device(device)
        print(f"train.device: {device} ({torch.cuda.get_device_name(device)})")
        with torch.device(device):           # every tensor the run makes is made there
            return _train_here(cfg)
    return _train_here(cfg)                  # (the CPU: no device mode intercepting each call)


def _train_here(cfg) -> Path:
    """``train`` on the default device."""
    tc = cfg.train
    torch.set_num_threads(int(_sel(tc, "threads", 2)))
    dist = _Dist()
    dtype_name = str(_sel(cfg, "model.dtype", "float32"))
    dtype = torch_dtype(dtype_name)
    seed = int(_sel(cfg, "seed", 0))
    epochs = int(tc.epochs)
    prior = prior_kind(cfg.model)
    if prior == "linear":                    # its three phases (the fit phase's epochs may be 0; all
        #                                          of them where the prior alone is a candidate: a learned law's fit)
        phases = training_phases(tc, none_ok=prior_alone_candidate(tc, prior_settings(cfg.model)))
    elif epochs < 0 or (epochs == 0 and not (_sel(tc, "init", None)
                                             and (readout_hops(cfg) or _sel(cfg, "model.mirror_average", False)))):
        raise ConfigError(f"train.epochs = {epochs}, expected >= 1 (or 0 with train.init and "
                          "model.stress_readout: the init's network as it is, its stress readout fitted anew; "
                          "or with model.mirror_average: the init's network stepped in the mesh's mirror frames)")
    ckpt_path = project_path(cfg.paths.checkpoint)
    out_dir = project_path(cfg.out)
    init = _sel(tc, "init", None)            # a fine-tune keeps its init's split (split_names' keep)
    init_ckpt = load_checkpoint(project_path(str(init))) if init else None   # read once, used thrice
    keep_split = init_ckpt.get("split") if init_ckpt else None
    data = load_data(project_path(cfg.paths.dataset), tc.split, seed, dtype,
                     state_dtype=torch.float64 if prior == "linear" else dtype,   # the prior steps float64 states
                     keep_split=keep_split)
    ds = data.dataset
    if keep_split and dist.main:
        kept = {n for k in ("train", "val", "test") for n in keep_split.get(k, [])}
        new = {k: sum(n not in kept for n in data.split[k]) for k in ("train", "val", "test")}
        print(f"train.init's split kept; new trajectories: {new['train']} train / {new['val']} val / {new['test']} test")
    structure = resolve_structure(_sel(cfg, "model.structure", "auto"), ds.effects, ds.config_yaml)
    hparams = hyperparameters(cfg.model, ds.layout.dim, velocity_columns(ds.layout), structure == "hamiltonian")
    from .evaluation import linear_validation_error     # (evaluation imports this module)
    train_trajs, val_trajs = data.of("train"), data.of("val")
    hops = readout_hops(cfg)                             # model.stress_readout
    folds = readout_folds(tc)                            # its check on held-out loads
    mirror_readout = bool(_sel(cfg, "model.stress_readout_symmetric", False))
    if mirror_readout and not hops:
        raise ConfigError("model.stress_readout_symmetric = true: ties the weights of a stress readout; "
                          "set model.stress_readout to its reach in hops (>= 1)")
    load_hops = _sel(cfg, "model.stress_readout_load", 0) or 0
    if isinstance(load_hops, bool) or not isinstance(load_hops, int) or load_hops < 0 or (load_hops and not hops):
        raise ConfigError(f"model.stress_readout_load = {load_hops!r}: the applied loads' reach in a stress "
                          "readout, expected 0 (off) or hops >= 1 with model.stress_readout set")
    modes = _sel(cfg, "model.stress_readout_modes", 0) or 0
    if isinstance(modes, bool) or not isinstance(modes, int) or modes < 0 or (modes and not hops):
        raise ConfigError(f"model.stress_readout_modes = {modes!r}: how many principal displacement fields a "
                          "stress readout projects onto, expected 0 (off) or >= 1 with model.stress_readout set")
    ridge = readout_ridge(cfg, hops, folds, modes)
    relative = _sel(cfg, "model.stress_readout_relative", False)
    if (not isinstance(relative, (bool, int, float)) or not 0 <= float(relative) <= 1
            or (relative and not hops)):
        raise ConfigError(f"model.stress_readout_relative = {relative!r}: weighs each snapshot by 1 / |σ|^p in a "
                          "stress readout's fit, expected true (p = 1), false or p in [0, 1] (other than 0 only "
                          "with model.stress_readout set)")
    augment = _sel(tc, "symmetry_augment", False)
    if not isinstance(augment, bool):
        raise ConfigError(f"train.symmetry_augment = {augment!r}, expected true (each training pair seen in a "
                          "random mirror of the mesh) or false")
    mirror_average = _sel(cfg, "model.mirror_average", False)
    if OmegaConf.is_config(mirror_average):
        mirror_average = OmegaConf.to_container(mirror_average)
    if not (isinstance(mirror_average, bool) or (isinstance(mirror_average, list) and mirror_average
                                                 and all(type(k) is int for k in mirror_average))):
        raise ConfigError(f"model.mirror_average = {mirror_average!r}, expected true (each step the mean of the "
                          "network's steps in every mirror frame of the mesh), false, or a list of frame "
                          "indices that form a group, e.g. [0, 3]")
    lam_grad = rate_gradient_weight(tc)
    window = window_steps(tc)
    if prior == "linear":                                # the linearised FE step + learned remainders
        if mirror_average:
            raise ConfigError(f"model.mirror_average = {str(mirror_average).lower()}: an option of the network stepping the whole "
                              "state; model.prior=linear steps its prior's FE operators (leave it false)")
        if lam_grad > 0:
            raise ConfigError("train.rate_gradient_weight: a term of the network's one-step loss; "
                              "model.prior=linear trains on rollouts (leave it 0)")
        if window:
            raise ConfigError("train.window_steps: an option of the network stepping the whole state; "
                              "model.prior=linear has its own rollout phases (train.rollout_window; leave it 0)")
        if augment:
            raise ConfigError("train.symmetry_augment = true: an option of the network stepping the whole "
                              "state; model.prior=linear steps its prior's FE operators (leave it false)")
        if hops:
            raise ConfigError("model.stress_readout: an option of the network stepping the whole state; "
                              "model.prior=linear takes its stress from the prior (leave it 0)")
        return train_linear_prior(cfg, data, hparams, dtype_name, structure, ckpt_path, out_dir, dist, phases,
                                  init_ckpt)

    if hops:                                     # refused now rather than after training
        from .stress_readout import check_determined

        if "sigma" not in data.layout.names:
            raise ConfigError(f"model.stress_readout = {hops}: the dataset's state "
                              f"{data.layout.names} has no stress (sigma) to read")
        check_determined(data.graph.ref_pos.cpu().numpy(), data.graph.edge_index.cpu().numpy(),
                         sum(t.z.shape[0] for t in train_trajs), hops, str(data.path))
        if isinstance(ridge, list):              # the shapes choose by held-out load groups: are there 2?
            from .stress_readout import load_folds

            groups = load_folds(data.graph, [t.force for t in train_trajs], folds, mirror_readout)[1]
            if len(set(groups.tolist())) < 2:
                raise DataError(f"{data.path}: model.stress_readout_ridge = {ridge}: each shape chooses its "
                                "ridge by held-out load groups, and the training trajectories load "
                                f"{len(set(groups.tolist()))} group of nodes; give one ridge")
    frames = averaged_frames(data, mirror_average) if mirror_average else []
    if len(frames) > 1:                          # each step averaged over the mesh's mirror frames
        hparams["mirror_frames"] = {"frames": len(frames), "nodes": data.graph.n_nodes}
    torch.manual_seed(seed)
    model = build_model(hparams, dtype)
    if len(frames) > 1:
        model.set_frames(frames)
    if _sel(tc, "init", None):                 # warm start (fine-tuning): weights and statistics
        stats = warm_start(model, init_ckpt, project_path(str(tc.init)), ds, hparams)
    else:
        stats = compute_stats(train_trajs, data.graph, ds.dt, hparams)
        model.set_stats(stats)
    base = _base_checkpoint(cfg, data, hparams, dtype_name, structure, stats)
    lr = float(tc.lr)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    gamma = float(_sel(tc, "lr_decay", 1.0)) ** (1.0 / max(epochs, 1))
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=gamma)
    gen = torch.Generator().manual_seed(seed)            # on the CPU, whatever train.device
    start_epoch, history, best_val, stale = 0, [], math.inf, 0
    resumed_direction = None
    mid = None                                   # an interrupted epoch's place (checkpoint "mid_epoch")
    saves = EpochCheckpoints(_sel(tc, "checkpoint_minutes", 10), dist)

    last = last_path(ckpt_path)
    identity = training_identity(cfg, hparams, dtype_name)     # once, before any file is written
    if bool(_sel(tc, "resume", True)) and last.exists() and epochs > 0:
        state = load_checkpoint(last)
        check_fingerprint(state["fingerprint"], ds, last,
                          hint="delete it or pass train.resume=false to train from scratch")
        stored = _without_off_terms(state.get("identity") or {})
        changed = identity_changes(stored, identity)
        if changed:
            print(f"{last}: configuration changed ({', '.join(changed)}); training from scratch")
        elif not _fits(model, state["state_dict"]):
            print(f"{last}: weights from another model version; training from scratch")
        else:
            model.load_state_dict(state["state_dict"])
            opt.load_state_dict(state["optimizer"])
            sched.load_state_dict(state["scheduler"])
            gen.set_state(state["rng"]["generator"])
            torch.set_rng_state(state["rng"]["torch"])
            resumed_direction = state.get("rest_direction")
            start_epoch, history = int(state["epoch"]), list(state["history"])
            best_val, stale = float(state["best_val"]), int(state["stale_rounds"])
            mid = state.get("mid_epoch")                             # written within epoch start_epoch + 1
            if mid:
                order, next_batch, _ = saves.resume(mid, last, start_epoch + 1)
                share = len(order) // dist.world
            if dist.main:
                print(f"resuming from {last} " + (
                    f"within epoch {start_epoch + 1}, at batch {next_batch + 1} of "
                    f"{-(-share // max(1, int(tc.batch_size)))}" if mid else f"at epoch {start_epoch}"))

    pairs = samples(train_trajs, _sel(tc, "start_repeats", 1))
    n_rest, rest = rest_samples(_sel(tc, "rest_samples", "auto"), train_trajs, ds.effects,
                                velocity_columns(ds.layout))
    rest_horizon, rest_steps = rest_rollout_steps(_sel(tc, "rest_rollout", 0), n_rest)
    if rest_horizon:                                 # held as long as the model is left alone there
        rest = rest_trajectory(train_trajs, ds.effects, velocity_columns(ds.layout), steps=rest_horizon)
    pairs += [(len(train_trajs), 0)] * n_rest        # the unloaded rest state stays put
    batch_trajs = train_trajs + ([rest] if rest is not None else [])
    lam_s = float(_sel(tc, "rest_stability", 0.0))
    if lam_s < 0 or (lam_s > 0 and rest is None):
        raise ConfigError(f"train.rest_stability = {lam_s}, expected 0 (off) or a weight > 0 where there is a "
                          f"rest state (train.rest_samples > 0)")
    probe_sizes = stability_probe_sizes(_sel(tc, "rest_stability_probe", STABILITY_PROBE))
    column_weights = edge_scale = None
    # with windows, the init's stress readout (fixed) may weigh the stress read off the positions
    readout_fixed, lam_read = window_readout(tc, cfg, window, train_trajs[0].z, init_ckpt)
    if window:                                       # training windows instead of one-step pairs
        shortest = min(t.z.shape[0] for t in train_trajs) - 1
        if window > shortest:
            raise ConfigError(f"train.window_steps = {window}: longer than the shortest training trajectory "
                              f"({shortest} steps) of {data.path}")
        if hparams["integrator"] != "euler":
            raise ConfigError(f"train.window_steps: windows step by the Euler rule; model.integrator = "
                              f"{hparams['integrator']} (leave window_steps 0)")
        clashing = [k for k, on in (("rollout_pairs", int(_sel(tc, "rollout_pairs", 0)) > 0),
                                    ("rest_rollout", bool(rest_horizon)), ("rest_stability", lam_s > 0)) if on]
        if clashing:
            raise ConfigError(f"train.window_steps = {window}: the windows are the model's own rollouts; "
                              f"leave train.{clashing[0]} off")
        column_weights = window_column_weights(tc, ds.layout, train_trajs[0].z)
        edge_scale = edge_step_scale(train_trajs, data.graph.edge_index, ds.dt * model.dzdt_std.detach())
        if rest is not None:                         # the unloaded body held still over a whole window
            rest = rest_trajectory(train_trajs, ds.effects, velocity_columns(ds.layout), steps=window)
            batch_trajs = train_trajs + [rest]
    probe_every = _sel(tc, "rest_stability_every", 1)
    if not isinstance(probe_every, int) or isinstance(probe_every, bool) or probe_every < 1:
        raise ConfigError(f"train.rest_stability_every = {probe_every!r}, expected an integer >= 1 "
                          f"(probe the rest state every k-th batch)")
    # power iterations toward the fastest mode at rest, one per probe size
    direction = resumed_direction                    # [K, N, D]; [N, D] from a run before sizes
    if direction is not None and direction.dim() == 2:
        direction = direction.unsqueeze(0)
    n_dirs = len(probe_sizes)
    if lam_s > 0 and (direction is None or direction.shape[0] != n_dirs):
        direction = cpu_randn((n_dirs, *rest.z.shape[1:]), torch.Generator().manual_seed(seed), rest.z)
    if direction is not None:                        # (a checkpoint's is on the CPU)
        direction = direction.to(rest.z.device)
    images = training_images(data, str(data.path)) if augment else None
    rollout_from = int(_sel(tc, "rollout_pairs", 0))
    rolled: list[torch.Tensor] | None = None
    batch_size = max(1, int(tc.batch_size))
    noise = float(_sel(tc, "noise", 0.0))
    lam_d, lam_g = float(_sel(tc, "lambda_data", 1.0)), float(_sel(tc, "lambda_degeneracy", 1.0))
    val_every = max(1, int(_sel(tc, "val_every", 1)))
    patience = int(_sel(tc, "patience", 0))
    if dist.main:
        print(f"train: {len(train_trajs)} train / {len(val_trajs)} val / {len(data.split['test'])} test "
              f"trajectories, {len(pairs)} steps ({n_rest} at rest"
              + (f", {len(rest_steps)} more from its own {rest_horizon}-step rollout at rest" if rest_horizon else "")
              + f"), structure {structure}, "
              f"{parameter_count(model)} parameters" + linear_validation_error(data, val_trajs)
              + (f"; each pair seen in one of the mesh's {len(images)} mirror frames at random"
                 if images is not None else "")
              + (f"; trained instead on the model's own rollouts over windows of {window} steps from true states, "
                 f"{len(window_starts(train_trajs, window, torch.Generator().manual_seed(seed))) + n_rest} windows an epoch "
                 "(train.window_steps; no training noise)" if window else "")
              + (f"; the stress read off the predicted positions by {tc.init}'s readout weighed "
                 f"{lam_read:g} in the window loss (train.window_readout_weight), and the validation rollouts' "
                 "stress read off by it" if lam_read else "")
              + (f"; each step the mean over the mesh's {len(frames)} mirror frames (model.mirror_average)"
                 + (", the training windows' steps too" if window else "") if len(frames) > 1 else ""))

    def resume_state(epoch_done: int, val: float, **extra) -> dict:
        """``model.last.ckpt``'s contents: everything a resumed run needs to go on exactly."""
        return {**base, "state_dict": model.state_dict(), "epoch": epoch_done, "val_error": val,
                "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                "rng": {"generator": gen.get_state(), "torch": torch.get_rng_state()},
                "history": history, "best_val": best_val, "stale_rounds": stale,
                "rest_direction": direction, "identity": identity, **extra}

    if epochs == 0 and dist.main:                # readout only: the init's network is the best model
        model.eval()
        save_checkpoint({**base, "state_dict": model.state_dict(), "epoch": 0,
                         "val_error": validation_error(model, data.graph, val_trajs, ds.layout, ds.dt)}, ckpt_path)
        print(f"train.epochs = 0: {tc.init}'s network kept as it is"
              + (f", stepped in the mesh's {len(frames)} mirror frames" if len(frames) > 1 else "")
              + ("; fitting its stress readout" if hops else ""))
    tb = _tensorboard(_sel(tc, "tensorboard", "auto"), out_dir / "tensorboard") if dist.main else None
    stopped = start_epoch >= epochs or (patience > 0 and stale >= patience)
    with _progress(disable=not dist.main) as progress:
        task = progress.add_task("train", total=epochs, completed=start_epoch, info="")
        epoch = start_epoch
        while not stopped and epoch < epochs:
            t0 = time.perf_counter() - (mid["seconds"] if mid else 0.0)
            items = list(pairs)
            if window:                                          # this epoch's tiling, from (seed, epoch) alone
                items = window_starts(train_trajs, window, torch.Generator().manual_seed(seed * 100_019 + epoch))
                items += [(len(train_trajs), 0)] * n_rest
            rolled = None                                       # refreshed every epoch (resumes exactly)
            drifting = (rollout_from > 0 and epoch + 1 >= rollout_from) or bool(rest_horizon)
            # the weights the epoch's drifted states come from (an interrupted epoch's, kept in its checkpoint)
            epoch_start = ((mid["epoch_start"] if mid else {k: v.clone() for k, v in model.state_dict().items()})
                           if drifting else None)
            if mid and drifting:
                weights_now = {k: v.clone() for k, v in model.state_dict().items()}
                model.load_state_dict(epoch_start)
            if rollout_from > 0 and epoch + 1 >= rollout_from:
                rolled = drifted_states(model, data.graph, train_trajs, ds.dt)
                items += [(i, s, 1) for i, s in pairs if s > 0]
            if rest_horizon:                                    # the model's own drift at rest, taken back
                rolled = (rolled or [t.z for t in train_trajs]) + drifted_states(model, data.graph, [rest], ds.dt)
                items += [(len(train_trajs), s, 1) for s in rest_steps]
            if mid and drifting:
                model.load_state_dict(weights_now)
            model.train()
            if mid:                         # an interrupted epoch goes on where its checkpoint left it
                perm, n_batches, (tot, dat, dgn, grown) = saves.resume(mid, last, epoch + 1)
                n_probes = int(mid["probes"])
            else:
                perm = torch.randperm(len(items), generator=gen, device="cpu").tolist()
                tot = dat = dgn = grown = 0.0
                n_batches = n_probes = 0
            mid = None
            n_use = len(perm) // dist.world * dist.world if dist.world > 1 else len(perm)
            mine = perm[dist.rank:n_use:dist.world]
            nb = -(-len(mine) // batch_size)
            # each item's mirror frame this epoch, from (seed, epoch) alone: a resumed epoch draws the same
            frame = (torch.randint(len(images), (len(items),), generator=torch.Generator().manual_seed(
                seed * 100_003 + epoch), device="cpu").tolist() if images is not None else None)
            saves.start()
            for b in range(n_batches * batch_size, len(mine), batch_size):
                chosen = mine[b:b + batch_size]
                mirrors = [images[frame[i]] for i in chosen] if frame is not None else None
                if window:
                    batch = make_window_batch(batch_trajs, [items[i] for i in chosen], data.graph, window, mirrors)
                    loss, dl, dg = window_loss(model, batch, ds.dt, column_weights, edge_scale, lam_d, lam_g, lam_grad,
                                               readout_fixed, lam_read)
                else:
                    batch = make_batch(batch_trajs, [items[i] for i in chosen], data.graph, rolled, mirrors)
                    loss, dl, dg = step_loss(model, batch, ds.dt, noise, gen, lam_d, lam_g, lam_grad)
                if lam_s > 0 and n_batches % probe_every == 0:   # a disturbance at rest must not grow
                    growth, direction = rest_growth(model, rest, data.graph, ds.dt, direction, probe_sizes)
                    loss = loss + lam_s * torch.relu(growth - 1.0).pow(2).sum()
                    grown, n_probes = grown + float(growth.detach().max()), n_probes + 1
                opt.zero_grad(set_to_none=True)
                loss.backward()
                dist.average_gradients(model)
                opt.step()
                tot, dat, dgn, n_batches = tot + float(loss.detach()), dat + dl, dgn + dg, n_batches + 1
                if saves.due(n_batches < nb):
                    place = saves.place(perm, n_batches, [tot, dat, dgn, grown], probes=n_probes,
                                        epoch_start=epoch_start, seconds=time.perf_counter() - t0)
                    if dist.main:
                        save_checkpoint(resume_state(
                            epoch, history[-1].get("val_error", math.nan) if history else math.nan,
                            mid_epoch=place), last)
                        print(f"epoch {epoch + 1}: batch {n_batches} of {nb}, loss {tot / n_batches:.3e}; "
                              f"{last.name} written (train.checkpoint_minutes)", flush=True)
            tot, dat, dgn, grown = dist.mean([tot, dat, dgn, grown])     # over all processes' samples
            if not math.isfinite(tot):
                raise DataError(f"{data.path}: training diverged (non-finite loss at epoch {epoch + 1}); "
                                f"lower train.lr or check the dataset")
            row = {"epoch": epoch + 1, "lr": opt.param_groups[0]["lr"], "loss": tot / max(n_batches, 1),
                   "data_loss": dat / max(n_batches, 1), "degeneracy_loss": dgn / max(n_batches, 1)}
            if lam_s > 0:
                row["rest_growth"] = grown / max(n_probes, 1)
            sched.step()
            epoch += 1
            if epoch % val_every == 0 or epoch == epochs:
                model.eval()
                val = validation_error(model, data.graph, val_trajs, ds.layout, ds.dt, readout_fixed)
                row["val_error"] = val
                if val < best_val or best_val == math.inf:  # the first round always saves
                    best_val, stale = min(val, best_val), 0
                    if dist.main:
                        save_checkpoint({**base, "state_dict": model.state_dict(), "epoch": epoch,
                                         "val_error": val}, ckpt_path)
                else:
                    stale += 1
                stopped = patience > 0 and stale >= patience
            row["seconds"] = time.perf_counter() - t0
            history.append(row)
            if dist.main:
                save_checkpoint(resume_state(epoch, row.get("val_error", math.nan)), last)
                _write_metrics(out_dir / "metrics.csv", history)
                if tb is not None:
                    for key, value in row.items():
                        if key != "epoch" and math.isfinite(value):
                            tb.add_scalar(f"train/{key}", value, epoch)
                    tb.flush()
            progress.update(task, completed=epoch,
                            info=f"loss {row['loss']:.3e} val {row.get('val_error', float('nan')):.3e}")
            if stopped and dist.main:
                print(f"early stopping at epoch {epoch} (no improvement in {patience} validation rounds)")
    if tb is not None:
        tb.close()
    dist.barrier()
    dist.close()
    if dist.main:
        if not ckpt_path.exists():  # e.g. resumed a finished run whose best file was deleted
            raise DataError(f"{ckpt_path}: no best checkpoint written (delete {last} and retrain)")
        ckpt = load_checkpoint(ckpt_path)
        if hops:                         # the stress read off the best model's own positions
            from .stress_readout import fit_readout_to_rollouts, with_stress_readout

            readout, fit = fit_readout_to_rollouts(model_from_checkpoint(ckpt, ds), data, train_trajs, hops,
                                                   symmetric=mirror_readout, load_hops=load_hops, modes=modes,
                                                   folds=folds, ridge=ridge, relative=relative)
            ckpt = with_stress_readout(ckpt, readout, hops, load_hops)
            if "held_out_loads" in fit:
                ckpt["stress_readout_check"] = fit["held_out_loads"]
            # the checkpoint's validation error is that of the stress it now reports (metrics.csv keeps
            # the one each epoch was selected by: the network's own σ, or the init's readout's)
            selected = ckpt.get("val_error", math.nan)
            best = model_from_checkpoint(ckpt, ds)
            ckpt["val_error"] = validation_error(best, data.graph, val_trajs, ds.layout, ds.dt)
            save_checkpoint(ckpt, ckpt_path)
            print(f"stress readout: {fit['hops']} hops" + (f", loads within {load_hops}" if load_hops else "")
                  + (f", onto {fit['modes']} displacement modes" if fit["modes"] else "")
                  + ((", each snapshot weighed by 1 / |sigma|" + (f"^{fit['relative']:g}" if fit["relative"] != 1 else ""))
                     if fit["relative"] else "")
                  + f", {fit['classes']} neighbourhood shapes, {fit['weights']} "
                  f"weights ({fit['symmetries']} mesh symmetries), fitted to the model's {len(train_trajs)} training rollouts (relative L2 of sigma "
                  f"{fit['fit_error']:.4f}); validation error with it {ckpt['val_error']:.4e} "
                  f"(selected at {selected:.4e})")
            if "held_out_loads" in fit:
                print(held_out_sentence(fit["held_out_loads"]))
        else:
            best = model_from_checkpoint(ckpt, ds)
        mean = rollout_errors(best, data.graph, data.of("test"), ds.layout, ds.dt)[0]
        print_rrmse_table(f"test rollout RRMSE ({len(data.split['test'])} trajectories)", {"test": mean})
    return ckpt_path
