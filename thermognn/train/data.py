"""Dataset -> tensors for training: trajectory-wise split, normalisation statistics, batches.

All trajectories of a dataset share one mesh, so a sample is a snapshot pair (z[s], z[s+1]) with
the force f[s+1] that drives the step; a batch concatenates B snapshots into one disjoint graph
(``torch_geometric.data.Batch``, edge indices offset per graph).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from thermognn.core.errors import ConfigError, DataError
from thermognn.core.schema import Dataset
from thermognn.core.state import StateLayout

from .model import raw_edge_features


@dataclass
class Graph:
    """The mesh graph shared by all snapshots. ref_pos [N, 3] m, edge_index [2, E], node_type [N]."""

    ref_pos: Tensor
    edge_index: Tensor
    node_type: Tensor
    surface_faces: Tensor

    @property
    def n_nodes(self) -> int:
        return int(self.ref_pos.shape[0])

    def copies(self, count: int) -> "Graph":
        """``count`` disjoint copies of the mesh as one graph, laid out as
        ``torch_geometric.data.Batch.from_data_list`` would: copy b's node indices offset by b*N.
        ref_pos [count*N, 3], edge_index [2, count*E], node_type [count*N], surface_faces [count*F, 3]."""
        offsets = (torch.arange(count) * self.n_nodes).view(count, 1, 1)                       # [count, 1, 1]
        edge_index = (self.edge_index.unsqueeze(0) + offsets).permute(1, 0, 2).reshape(2, -1)  # [2, count*E]
        faces = (self.surface_faces.unsqueeze(0) + offsets.to(self.surface_faces.dtype)).reshape(-1, self.surface_faces.shape[-1])
        return Graph(ref_pos=self.ref_pos.repeat(count, 1), edge_index=edge_index,
                     node_type=self.node_type.repeat(count), surface_faces=faces)


@dataclass
class TrajectoryTensors:
    """One trajectory as tensors: z [S, N, D], force [S, N, 3], time [S]."""

    name: str
    z: Tensor
    force: Tensor
    time: Tensor


@dataclass
class LoadedData:
    """Everything training needs from one dataset."""

    path: Path
    dataset: Dataset
    graph: Graph
    layout: StateLayout
    dt: float
    split: dict[str, list[str]]
    trajectories: dict[str, TrajectoryTensors] = field(default_factory=dict)
    state_dtype: torch.dtype = torch.float32          # of the trajectories' states and loads

    def of(self, part: str) -> list[TrajectoryTensors]:
        return [self.trajectories[n] for n in self.split[part]]

    def reference_positions(self) -> np.ndarray:
        """The mesh's reference positions X [N, 3] [m] as the states store them (rounded to
        ``state_dtype``; float64 array), so that q − X is zero at rest."""
        return torch.as_tensor(self.dataset.mesh.nodes, dtype=self.state_dtype).double().cpu().numpy()

    def read(self, name: str) -> TrajectoryTensors:
        """Trajectory ``name`` as tensors (read once, then kept in ``trajectories``)."""
        if name not in self.trajectories:
            t = self.dataset.read(name)
            if t.z.shape[0] < 2:
                raise DataError(f"{self.dataset.path}: trajectory '{name}' has {t.z.shape[0]} states, need at least 2")
            self.trajectories[name] = TrajectoryTensors(name, torch.as_tensor(t.z, dtype=self.state_dtype),
                                                        torch.as_tensor(t.force, dtype=self.state_dtype),
                                                        torch.as_tensor(t.time, dtype=torch.float64))
        return self.trajectories[name]


def fingerprint(ds: Dataset) -> dict:
    """What a checkpoint must agree on with a dataset: sizes and the state layout."""
    return {"n_nodes": int(ds.mesh.nodes.shape[0]), "dim": int(ds.layout.dim),
            "n_edges": int(ds.mesh.edges().shape[1]), "state_layout": ds.layout.to_json()}


def check_fingerprint(expected: dict, ds: Dataset, ckpt_path, hint: str = "") -> None:
    """DataError (one line, naming both files) when a dataset does not match a checkpoint."""
    got = fingerprint(ds)
    for key in ("n_nodes", "dim", "n_edges", "state_layout"):
        if expected.get(key) != got[key]:
            raise DataError(f"{ckpt_path} does not match dataset {ds.path}: {key} {expected.get(key)} "
                            f"in the checkpoint, {got[key]} in the dataset" + (f" ({hint})" if hint else ""))


def split_names(ds: Dataset, fractions, seed: int,
                keep: dict[str, list[str]] | None = None) -> dict[str, list[str]]:
    """Trajectory-wise train/val/test split of the 'ok' trajectories.

    A fixed split stored in the dataset (``Dataset.split``) wins; otherwise a seeded permutation
    of the split groups (``Dataset.split_groups``; a trajectory without one is its own group) with
    the fractions (train, val, test) counted in groups: the cases ``generate`` presses at one point
    with several magnitudes land in the same part, so no validation or test trajectory repeats a
    training point; without shared groups this is a permutation of the trajectories. With fewer
    than 3 groups all three parts are the same list (nothing to hold out).

    ``keep`` (a fine-tune's ``train.init`` checkpoint's split): every trajectory it names keeps
    its part, and so does the rest of its split group; only the groups it does not touch (the
    cases a grown dataset added) are split, among themselves, as above. So a model fine-tuned on a
    grown dataset never trains on a case its init held out, and is tested on those same cases
    plus its share of the new ones."""
    ok = ds.ok_names
    if not ok:
        raise DataError(f"{ds.path}: no trajectory with status 'ok'")
    fixed = getattr(ds, "split", None)
    if fixed:
        okset = set(ok)
        parts = {k: [n for n in fixed.get(k, []) if n in okset] for k in ("train", "val", "test")}
        if parts["train"]:
            for k in ("val", "test"):
                parts[k] = parts[k] or parts["train"]
            return parts
    fr = [float(x) for x in fractions]
    if len(fr) != 3 or min(fr) < 0 or sum(fr) <= 0:
        raise DataError(f"train.split = {fractions}: expected three non-negative fractions")
    groups = _split_groups(ok, ds.split_groups)
    kept = _kept_part(groups, keep) if keep else []
    if kept:
        return _grown_split(groups, kept, fr, seed, ok)
    n = len(groups)
    if n < 3:
        return {"train": list(ok), "val": list(ok), "test": list(ok)}
    total = sum(fr)
    n_val = max(1, int(round(fr[1] / total * n)))
    n_test = max(1, int(round(fr[2] / total * n)))
    n_train = max(1, n - n_val - n_test)
    perm = np.random.default_rng(seed).permutation(n)
    bounds = {"train": (0, n_train), "val": (n_train, n_train + n_val),
              "test": (n_train + n_val, n_train + n_val + n_test)}
    return {part: sorted((name for i in perm[a:b] for name in groups[i]), key=ok.index)
            for part, (a, b) in bounds.items()}


def _kept_part(groups: list[list[str]], keep: dict[str, list[str]]) -> list[str | None]:
    """Per group, the part of ``keep`` that names one of its trajectories (train first), or None;
    an empty list where ``keep`` keeps no training trajectory of this dataset (nothing to keep)."""
    where = {n: k for k in ("test", "val", "train") for n in keep.get(k, [])}   # train wins ties
    parts = [next((where[n] for n in g if where.get(n) == "train"),
                  next((where[n] for n in g if n in where), None)) for g in groups]
    return parts if "train" in parts else []


def _grown_split(groups: list[list[str]], kept: list[str | None], fr: list[float], seed: int,
                 ok: list[str]) -> dict[str, list[str]]:
    """``split_names`` with ``keep``: the kept groups in their parts (``kept``, ``_kept_part``'s),
    the new ones split by ``fr`` (rounded; no minimum of one, so a few new cases may all go to
    training)."""
    new = [i for i, part in enumerate(kept) if part is None]
    n_val = int(round(fr[1] / sum(fr) * len(new)))
    n_test = int(round(fr[2] / sum(fr) * len(new)))
    perm = [new[i] for i in np.random.default_rng(seed).permutation(len(new))]
    part_of = dict(enumerate(kept))
    part_of.update({i: "train" for i in perm[:len(new) - n_val - n_test]})
    part_of.update({i: "val" for i in perm[len(new) - n_val - n_test:len(new) - n_test]})
    part_of.update({i: "test" for i in perm[len(new) - n_test:]})
    out = {part: sorted((name for i, g in enumerate(groups) if part_of[i] == part for name in g), key=ok.index)
           for part in ("train", "val", "test")}
    for k in ("val", "test"):                   # as split_names: an empty part is the training one
        out[k] = out[k] or out["train"]
    return out


def _split_groups(names: list[str], split_groups: dict[str, str]) -> list[list[str]]:
    """``names`` grouped by their split group, in order of first appearance; a trajectory
    without one is a group of its own."""
    groups: dict[tuple[str, str], list[str]] = {}
    for name in names:
        group = split_groups.get(name)
        groups.setdefault(("group", group) if group else ("name", name), []).append(name)
    return list(groups.values())


def spread(names: list, k: int) -> list:
    """At most k of ``names`` (names or trajectories), evenly spaced over the list (its first and
    last included), in order: a sample of the training trajectories that covers every load level
    of a dataset generated with several magnitudes (``generate`` lists the cases of one magnitude
    after another)."""
    if k <= 0 or not names:
        return []
    if k >= len(names):
        return list(names)
    return [names[i] for i in sorted({int(round(x)) for x in np.linspace(0, len(names) - 1, k)})]


def load_graph(ds: Dataset, dtype: torch.dtype) -> Graph:
    mesh = ds.mesh
    faces = mesh.boundary_faces() if len(mesh.tets) else np.zeros((0, 3), np.int64)
    return Graph(ref_pos=torch.as_tensor(mesh.nodes, dtype=dtype),
                 edge_index=torch.as_tensor(mesh.edges(), dtype=torch.long),
                 node_type=torch.as_tensor(np.asarray(mesh.node_type, np.int64)),
                 surface_faces=torch.as_tensor(faces, dtype=torch.long).reshape(-1, 3))


def load_data(path, fractions, seed: int, dtype: torch.dtype = torch.float32,
              parts=("train", "val", "test"), state_dtype: torch.dtype | None = None,
              keep_split: dict[str, list[str]] | None = None) -> LoadedData:
    """Open the dataset, split it and read the trajectories of ``parts`` into tensors: the graph
    in ``dtype`` (the network's), the states and loads in ``state_dtype`` (default ``dtype``;
    float64 for a model that steps float64 states, ``model.prior=linear``: in float32 the
    positions of a 4 cm body are rounded by up to 2e-9 m, a displacement a gentle load does not
    dwarf). ``keep_split``: a fine-tune's init split to keep (``split_names``'s ``keep``)."""
    ds = Dataset(path)
    if ds.layout.names[0] != "q" or ds.layout.groups[0][1] != 3:
        raise DataError(f"{ds.path}: state_layout {ds.layout.to_json()} must start with q (3)")
    split = split_names(ds, fractions, seed, keep_split)
    data = LoadedData(path=Path(path), dataset=ds, graph=load_graph(ds, dtype), layout=ds.layout,
                      dt=ds.dt, split=split, state_dtype=state_dtype or dtype)
    for name in sorted({n for p in parts for n in split[p]}, key=ds.names.index):
        data.read(name)
    return data


def velocity_columns(layout: StateLayout) -> list[int]:
    return list(range(*layout.slice("v").indices(layout.dim))) if "v" in layout.names else []


def _safe_std(x: Tensor) -> Tensor:
    """Std with degenerate (constant) columns mapped to 1."""
    s = x.std(0, unbiased=False)
    return torch.where(s > 1e-12 * (1.0 + x.abs().mean(0)), s, torch.ones_like(s))


def _edge_stats(z: Tensor, graph: Graph, hparams: dict, chunk: int = 64) -> tuple[Tensor, Tensor]:
    """Mean and std [edge_feature_count] of the raw edge features over all snapshots z [S, N, D]
    (two passes over chunks of snapshots: exact, and memory bounded for large datasets)."""
    src, dst = graph.edge_index[0], graph.edge_index[1]
    X = graph.ref_pos.double()
    dx = X[dst] - X[src]                                                      # [E, 3]
    reference, velocity = bool(hparams["reference_edges"]), bool(hparams.get("velocity_edges", False))
    vc = int(hparams["velocity_columns"][0]) if velocity else 0

    def feats(zc: Tensor) -> Tensor:                                          # [c * E, F]
        dz = zc[:, dst] - zc[:, src]                                          # [c, E, D]
        dq = dz[..., :3].reshape(-1, 3)
        dv = dz[..., vc:vc + 3].reshape(-1, 3) if velocity else dq[:, :0]
        return raw_edge_features(dq, dx.repeat(zc.shape[0], 1), dv, reference, velocity)

    chunks = [z[i:i + chunk] for i in range(0, z.shape[0], chunk)]
    count = z.shape[0] * dx.shape[0]
    mean = sum(feats(c).sum(0) for c in chunks) / count
    var = sum((feats(c) - mean).pow(2).sum(0) for c in chunks) / count
    std = var.sqrt()
    return mean, torch.where(std > 1e-12 * (1.0 + mean.abs()), std, torch.ones_like(std))


def compute_stats(train: list[TrajectoryTensors], graph: Graph, dt: float,
                  hparams: dict) -> dict[str, Tensor]:
    """Per-column normalisation from the TRAINING trajectories only (float64, SI units).

    z_mean/z_std [D] over all snapshots and nodes, except that z_std of the positions q is the
    spread of the displacement q - X, the scale on which q moves (the network sees q only through
    edge differences, so this scale only sets how dE/dq and the GENERIC operators are balanced;
    the spread of the absolute positions would make the energy needlessly steep in q);
    edge_mean/edge_std over the edge features (``model.raw_edge_features``, as the model's
    ``hparams`` select them);
    f_mean/f_std [3] over the driving forces; dzdt_std [D] root mean square of (z[s+1]-z[s])/dt
    (scale only, no shift, so that a zero rate stays zero). A column that never changes (e.g. a
    stress component a plane load never excites) gets z_std = 1 and the typical (geometric mean)
    rate-to-state ratio of the others, so that it sits in the model's balanced coordinates
    (``TIGNN.balance``) like them instead of distorting the operators' scaling."""
    z = torch.cat([t.z for t in train]).double()                    # [sum S, N, D]
    f = torch.cat([t.force[1:] for t in train]).double()            # [sum (S-1), N, 3]
    dzdt = torch.cat([(t.z[1:] - t.z[:-1]).double() / dt for t in train])  # [sum (S-1), N, D]
    D = z.shape[-1]
    zf = z.reshape(-1, D)
    edge_mean, edge_std = _edge_stats(z, graph, hparams)
    rms = dzdt.reshape(-1, D).pow(2).mean(0).sqrt()
    z_std = _safe_std(zf)
    z_std[:3] = _safe_std((z[..., :3] - graph.ref_pos.double()).reshape(-1, 3))   # displacement scale [m]
    live = rms > 1e-30
    dzdt_std = torch.ones_like(rms)
    dzdt_std[live] = rms[live]
    if bool(live.any()):                                             # still columns: typical ratio
        ratio = torch.exp(torch.log(rms[live] / z_std[live]).mean())
        dzdt_std[~live] = ratio * z_std[~live]
    return {"z_mean": zf.mean(0), "z_std": z_std,
            "edge_mean": edge_mean, "edge_std": edge_std,
            "f_mean": torch.zeros(3, dtype=torch.float64),
            "f_std": _safe_std(torch.cat([f.reshape(-1, 3), -f.reshape(-1, 3)])),
            "dzdt_std": dzdt_std}


def samples(trajs: list[TrajectoryTensors], start_repeats: int | str = 1) -> list[tuple[int, int]]:
    """(trajectory index, step s) for every transition z[s] -> z[s+1]; each trajectory's first
    transition ``start_repeats`` times. The start (a body at rest in its reference shape, or
    already moving) is one sample in a trajectory's length but the error made there is carried
    through the whole rollout (``train.start_repeats``)."""
    try:
        k = int(start_repeats)
    except (TypeError, ValueError):
        k = 0
    if k < 1:
        raise ConfigError(f"train.start_repeats = {start_repeats!r}, expected an integer >= 1")
    every = [(i, s) for i, t in enumerate(trajs) for s in range(t.z.shape[0] - 1)]
    return every + [(i, 0) for i, t in enumerate(trajs) if t.z.shape[0] > 1] * (k - 1)


def rest_trajectory(trajs: list[TrajectoryTensors], effects, velocity_cols: list[int],
                    key: str = "train.rest_samples", steps: int = 1) -> TrajectoryTensors:
    """The unloaded body at rest, held for ``steps`` steps: z[0] repeated under zero force
    [steps + 1, N, D] (``train.rest_rollout`` rolls the model out along it).

    Taken from the data: every trajectory must start from one common state with zero velocity
    and zero load (the reference configuration). Without this sample nothing in a loaded
    dataset says that an unloaded body stays put, and a model whose kinematics are exact
    integrates a small bias at rest into a drift. Not for scenes with gravity, whose reference
    configuration is not an equilibrium."""
    if "gravity" in effects:
        raise ConfigError(f"{key}: the scene has gravity, so its reference state is not at rest; "
                          f"set {key}=0")
    z0 = trajs[0].z[0]
    for t in trajs:
        if t.force[0].abs().max() > 0 or (velocity_cols and t.z[0][:, velocity_cols].abs().max() > 0):
            raise ConfigError(f"{key}: trajectory {t.name} does not start at rest (unloaded, zero "
                              f"velocity); set {key}=0")
        if not torch.allclose(t.z[0], z0, rtol=1e-6, atol=1e-9 * float(z0.abs().max().clamp(min=1.0))):
            raise ConfigError(f"{key}: trajectory {t.name} starts from another state than "
                              f"{trajs[0].name}; set {key}=0")
    dt = trajs[0].time[1] - trajs[0].time[0]
    return TrajectoryTensors(name="rest", z=z0.expand(steps + 1, *z0.shape).clone(),
                             force=torch.zeros(steps + 1, *trajs[0].force.shape[1:], dtype=trajs[0].force.dtype),
                             time=trajs[0].time[0] + dt * torch.arange(steps + 1, dtype=trajs[0].time.dtype))


def rest_samples(setting, trajs: list[TrajectoryTensors], effects,
                 velocity_cols: list[int]) -> tuple[int, TrajectoryTensors | None]:
    """``train.rest_samples``: how many rest transitions per epoch, and the rest trajectory.
    ``auto``: one per training trajectory where the data start from one unloaded rest state
    (without gravity), else none; an integer: that many (refused where there is no rest state)."""
    if str(setting).lower() == "auto":
        try:
            return len(trajs), rest_trajectory(trajs, effects, velocity_cols)
        except ConfigError:
            return 0, None
    try:
        n = int(setting)
    except (TypeError, ValueError):
        n = -1
    if n < 0:
        raise ConfigError(f"train.rest_samples = {setting!r}, expected auto or an integer >= 0")
    return n, (rest_trajectory(trajs, effects, velocity_cols) if n else None)


def rest_rollout_steps(setting, n_rest: int) -> tuple[int, list[int]]:
    """``train.rest_rollout`` H: how long the model's own rollout leaves the unloaded body alone
    each epoch, and which of its states s (``n_rest`` of them, evenly spread over 1 .. H - 1) are
    trained back toward rest. 0 is off; otherwise H >= 2, and rest samples are needed."""
    try:
        h = int(setting)
    except (TypeError, ValueError):
        h = -1
    if h == 0:
        return 0, []
    if h < 2:
        raise ConfigError(f"train.rest_rollout = {setting!r}, expected 0 (off) or an integer >= 2 (steps)")
    if n_rest < 1:
        raise ConfigError(f"train.rest_rollout = {h} needs the rest state: train.rest_samples is 0 here "
                          f"(the data do not all start from one unloaded rest state, or it was set to 0)")
    return h, [h - 1 - (k * (h - 2)) // max(n_rest - 1, 1) for k in range(n_rest)]


@dataclass(frozen=True)
class StateImage:
    """One symmetry g = (R, p) of the mesh (``stress_readout.mesh_symmetries``: X[p[i]] = c + R (X[i] - c))
    acting on the states and loads: the same motion seen in the mirror, node p[i] doing what node i
    did. For an isotropic solid whose supports and (with ``gravity``) body force the mirror keeps,
    the image of a trajectory is a trajectory of the same physics (``train.symmetry_augment``).

    source [N] (node k of the image is node source[k] = p⁻¹[k] of the original),
    matrix [D, D] (block-diagonal: R on q and v, voigt(R σ Rᵀ) on every stress group),
    shift [D] ((I - R) c on q [m], 0 elsewhere), rotation [3, 3] (R, for the loads)."""

    source: Tensor
    matrix: Tensor
    shift: Tensor
    rotation: Tensor

    def states(self, z: Tensor) -> Tensor:
        """z [..., N, D] -> its image [..., N, D]: q' = c + R (q - c), v' = R v, σ' = R σ Rᵀ
        (worked in float64, returned in z's dtype, on z's device)."""
        m = self.matrix.to(z.device)
        return (z[..., self.source.to(z.device), :].to(m.dtype) @ m.T + self.shift.to(z.device)).to(z.dtype)

    def loads(self, f: Tensor) -> Tensor:
        """Nodal loads f [..., N, 3] [N] -> their image R f, moved with their nodes."""
        r = self.rotation.to(f.device)
        return (f[..., self.source.to(f.device), :].to(r.dtype) @ r.T).to(f.dtype)


#: state groups a mirror acts on as vectors, and as symmetric tensors (Voigt); others are refused
_VECTOR_GROUPS, _TENSOR_PREFIXES = ("q", "v"), ("sigma", "xi")


def state_images(graph: Graph, layout: StateLayout, gravity=None, dtype: torch.dtype = torch.float64,
                 key: str = "train.symmetry_augment") -> list[StateImage]:
    """The mesh's symmetries (identity first) as ``StateImage``s on states of ``layout``; with a
    ``gravity`` vector [m/s²] only those that keep it. Raises ConfigError for a state group it cannot
    mirror (names ``key``)."""
    from .stress_readout import mesh_symmetries, stress_action, symmetry_centre

    X = graph.ref_pos.double().cpu().numpy()
    c = symmetry_centre(X)                                               # [3] m
    symmetries = mesh_symmetries(X, graph.edge_index.cpu().numpy(), graph.node_type.cpu().numpy())
    if gravity is not None:
        g = np.asarray(gravity, dtype=np.float64)
        symmetries = [(R, p) for R, p in symmetries if np.allclose(R @ g, g)]
    images = []
    for R, p in symmetries:
        A, b, start = np.zeros((layout.dim, layout.dim)), np.zeros(layout.dim), 0
        for name, width in layout.groups:
            block = slice(start, start + width)
            if name in _VECTOR_GROUPS and width == 3:
                A[block, block] = R
                if name == "q":
                    b[block] = c - R @ c
            elif name.startswith(_TENSOR_PREFIXES) and width == 6:
                A[block, block] = stress_action(R)
            else:
                raise ConfigError(f"{key}: state variable '{name}' ({width} columns) has no known mirror image; "
                                  f"expected q, v (3) or stresses sigma, xi* (6)")
            start += width
        images.append(StateImage(source=torch.as_tensor(np.argsort(p)),
                                 matrix=torch.as_tensor(A, dtype=dtype), shift=torch.as_tensor(b, dtype=dtype),
                                 rotation=torch.as_tensor(R, dtype=dtype)))
    return images


def make_batch(trajs: list[TrajectoryTensors], items: list[tuple[int, ...]], graph: Graph,
               rolled: list[Tensor] | None = None, frames: list[StateImage] | None = None):
    """Concatenate snapshot pairs into one disjoint graph (a ``torch_geometric.data.Data``, laid
    out as ``Batch.from_data_list`` would, built directly since all snapshots share one mesh).

    An item (i, s) pairs z[s] with z[s+1] of trajectory i; an item (i, s, 1) starts instead from
    ``rolled[i][s]`` [N, D], the model's own rollout of that trajectory, still aiming at the true
    z[s+1] (training on its own drift, ``train.rollout_pairs``).

    With ``frames`` (one ``StateImage`` per item, ``train.symmetry_augment``) each pair is seen in
    its item's mirror of the mesh.

    Fields: z [B*N, D], z_next [B*N, D], f [B*N, 3], pos [B*N, 3] (reference X),
    node_type [B*N], edge_index [2, B*E] (graph b's indices offset by b*N), batch [B*N]."""
    from torch_geometric.data import Data

    B, N = len(items), graph.n_nodes
    z = torch.stack([(rolled[it[0]] if len(it) > 2 and it[2] else trajs[it[0]].z)[it[1]] for it in items])  # [B, N, D]
    z_next = torch.stack([trajs[it[0]].z[it[1] + 1] for it in items])                                       # [B, N, D]
    f = torch.stack([trajs[it[0]].force[it[1] + 1] for it in items])                                        # [B, N, 3]
    if frames is not None:
        z = torch.stack([g.states(z[b]) for b, g in enumerate(frames)])
        z_next = torch.stack([g.states(z_next[b]) for b, g in enumerate(frames)])
        f = torch.stack([g.loads(f[b]) for b, g in enumerate(frames)])
    z, z_next, f = z.reshape(B * N, -1), z_next.reshape(B * N, -1), f.reshape(B * N, 3)
    batched = graph.copies(B)
    return Data(z=z, z_next=z_next, f=f, pos=batched.ref_pos, node_type=batched.node_type,
                edge_index=batched.edge_index, batch=torch.arange(B).repeat_interleave(N), num_nodes=B * N)


def window_starts(trajs: list[TrajectoryTensors], window: int, generator: torch.Generator) -> list[tuple[int, int]]:
    """``train.window_steps``: (trajectory index, first step s) of the windows z[s] -> z[s + window],
    ceil(steps / window) per trajectory, from an offset o in [0, window) drawn from ``generator``:
    s_j = min(o + j window, steps - window), so every epoch covers the trajectory from o to its end
    (the last window overlapping its neighbour) and every step starts a window in some epoch."""
    items = []
    for i, t in enumerate(trajs):
        steps = t.z.shape[0] - 1
        offset = int(torch.randint(window, (1,), generator=generator, device="cpu"))   # a CPU generator, whatever train.device
        starts = sorted({min(offset + j * window, steps - window) for j in range(-(-steps // window))})
        items += [(i, s) for s in starts]
    return items


def make_window_batch(trajs: list[TrajectoryTensors], items: list[tuple[int, int]], graph: Graph, window: int,
                      frames: list[StateImage] | None = None):
    """Windows z[s .. s + window] of the items (i, s), stacked as one disjoint graph per time
    (``make_batch``'s layout), each seen in its item's mirror with ``frames``.

    Fields: z [window+1, B*N, D] (true states), f [window+1, B*N, 3] (f[k] drives z[k-1] -> z[k]),
    pos [B*N, 3], node_type [B*N], edge_index [2, B*E], batch [B*N]."""
    from torch_geometric.data import Data

    B, N = len(items), graph.n_nodes
    z = torch.stack([trajs[i].z[s: s + window + 1] for i, s in items])              # [B, W+1, N, D]
    f = torch.stack([trajs[i].force[s: s + window + 1] for i, s in items])          # [B, W+1, N, 3]
    if frames is not None:
        z = torch.stack([g.states(z[b]) for b, g in enumerate(frames)])
        f = torch.stack([g.loads(f[b]) for b, g in enumerate(frames)])
    z = z.transpose(0, 1).reshape(window + 1, B * N, -1)                           # [W+1, B*N, D]
    f = f.transpose(0, 1).reshape(window + 1, B * N, 3)                            # [W+1, B*N, 3]
    batched = graph.copies(B)
    return Data(z=z, f=f, pos=batched.ref_pos, node_type=batched.node_type, edge_index=batched.edge_index,
                batch=torch.arange(B).repeat_interleave(N), num_nodes=B * N)
