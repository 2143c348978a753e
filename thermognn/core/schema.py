"""The HDF5 dataset that ``generate`` writes and ``train`` reads (schema version 1).

Layout (units SI)::

    /                       attrs: schema_version (int), scene (str), config (YAML str),
                                   versions (JSON str), state_layout (JSON str), dt [s],
                                   effects (JSON list), config_hash (str), resume_hash
                                   (str: the hash of what decides the trajectories, which a
                                   re-run must match to resume; defaults to config_hash's),
                                   split (optional JSON {"train": [names], "val": [...], "test": [...]}:
                                   a fixed reference split that training must use),
                                   time_resolution (optional JSON: how well dt resolves the
                                   solid's vibration modes, from ``generate``; see
                                   thermognn/generate/modes.py ``diagnose``),
                                   substeps (optional int: FE steps per stored step, each
                                   dt / substeps, the loads linear between the stored ones;
                                   absent: 1), time_convergence (optional JSON: how far the
                                   data are from the FE at twice the substeps, from
                                   ``generate``; thermognn/generate/pipeline.py)
    /mesh/nodes             (N, 3) float64  reference positions X [m]
    /mesh/tets              (T, 4) int64    tetrahedra (node indices)
    /mesh/node_type         (N,)   int8     0 free, 1 clamped (Dirichlet), 2 loadable surface
    /mesh/edges             (2, E) int64    optional: graph edges (both directions); when absent
                                            they are the tetrahedra's edges (imported datasets
                                            such as the TIGNN beam have edges but no tets)
    /linear/                optional (``generate``): the solid linearised at rest over its n free
                            DOFs (node-blocked, 3 i + c), scipy CSR matrices stored as
                            <name>/data, <name>/indices, <name>/indptr with attrs shape:
        stiffness           (n, n)   K [N/m]          mass (n, n) M [kg]
        stress              (6N, n)  Σ [Pa/m] nodal Cauchy stress of a displacement (optional)
        free                (3N,)    bool             the DOFs K and M act on
        body_force          (n,)     [N]              gravity load (optional)
        stiffness_iso       (n, n)   K_iso [N/m]      viscous solids: the isochoric parts of K
        stress_iso          (6N, n)  Σ_iso [Pa/m]     and Σ, which the Prony series relaxes
                            attrs: rayleigh (αM [1/s], βK [s]), integrator, beta, gamma,
                            prony (JSON [[ḡ_i, τ_i [s]], ...]; viscous solids),
                            shear_modulus, bulk_modulus (μ0, K0 [Pa] at rest; optional, since
                            session 42: the corotated baseline, ``thermognn.core.corotated``)
                            (``thermognn.core.linear.LinearSolid``: the physics baseline)
    /trajectories/<name>/   attrs: status ('ok' | 'failed'), reason (str), load_point (3,) [m],
                                   split_group (optional str: trajectories sharing one land in
                                   the same split part; ``generate``: the point pressed)
        time                (S,)        float64  [s]
        z                   (S, N, D)   float64  state per node, columns as in state_layout
        force               (S, N, 3)   float64  external nodal force [N]
        load_nodes          (K,)        int64    nodes the load acts on

Time convention: ``force[s]`` is the external load at ``time[s]``; the step
``z[s] -> z[s+1]`` is driven by ``force[s+1]`` (the load an implicit FE step solves with).

A failed trajectory keeps the steps that converged (no NaN is ever written) and says why.
Writing goes to ``<path>.partial`` and is renamed at the end; re-running resumes from
the trajectories already in the partial file when its resume_hash matches (``generate``: the
same scene, whatever its number of load cases, which is how a finished dataset grows).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import DataError
from .linear import LinearSolid
from .state import StateLayout

SCHEMA_VERSION = 1
NODE_FREE, NODE_CLAMPED, NODE_SURFACE = 0, 1, 2


@dataclass
class Mesh:
    """Tetrahedral mesh with node types. nodes (N,3) [m], tets (T,4), node_type (N,)."""

    nodes: np.ndarray
    tets: np.ndarray
    node_type: np.ndarray
    graph_edges: np.ndarray | None = None

    def edges(self) -> np.ndarray:
        """Graph edges, both directions: (2, E) int64 (stored ones, else the tets' edges)."""
        if self.graph_edges is not None:
            return np.asarray(self.graph_edges, dtype=np.int64)
        t = self.tets
        pairs = np.concatenate([t[:, [i, j]] for i in range(4) for j in range(i + 1, 4)])
        pairs = np.sort(pairs, axis=1)
        pairs = np.unique(pairs, axis=0)
        return np.concatenate([pairs.T, pairs[:, ::-1].T], axis=1).astype(np.int64)

    def boundary_faces(self) -> np.ndarray:
        """Triangles on the boundary (faces belonging to one tet only): (F, 3) int64."""
        t = self.tets
        faces = np.concatenate([t[:, [0, 1, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 3]], t[:, [1, 2, 3]]])
        key = np.sort(faces, axis=1)
        _, idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
        return faces[idx[counts == 1]].astype(np.int64)


@dataclass
class Trajectory:
    """One simulated load case. time (S,), z (S,N,D), force (S,N,3), load_nodes (K,)."""

    name: str
    time: np.ndarray
    z: np.ndarray
    force: np.ndarray
    load_nodes: np.ndarray
    load_point: np.ndarray = field(default_factory=lambda: np.zeros(3))
    status: str = "ok"
    reason: str = ""
    #: trajectories with the same non-empty group land in the same train/val/test part
    #: (``generate``: ``point_<i>``, the load point pressed, whatever the magnitude)
    split_group: str = ""
    #: what the FE solve of it cost (``generate``): wall time [s] (nan: not recorded), Newton
    #: iterations and step cuts in all, the price of the data a learned model is measured against
    fe_seconds: float = float("nan")
    fe_iterations: int = 0
    fe_cuts: int = 0


def config_hash(config_yaml: str) -> str:
    return hashlib.sha256(config_yaml.encode()).hexdigest()[:16]


class DatasetWriter:
    """Write a dataset atomically and resumably.

    >>> with DatasetWriter(path, mesh, layout, dt, config_yaml, versions_json, scene, effects) as w:
    ...     for name in names:
    ...         if not w.has(name):
    ...             w.write(trajectory)
    ... # on clean exit the partial file is renamed onto ``path``
    """

    def __init__(self, path, mesh: Mesh, layout: StateLayout, dt: float, config_yaml: str,
                 versions_json: str, scene: str, effects, resume_key: str | None = None) -> None:
        """``resume_key``: the text that decides the trajectories (default ``config_yaml``); a
        partial file written with another is discarded, one with the same is resumed."""
        import h5py

        self.path = Path(path)
        self.partial = self.path.with_name(self.path.name + ".partial")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        chash = config_hash(config_yaml)
        rhash = config_hash(config_yaml if resume_key is None else resume_key)
        if self.partial.exists():
            try:
                with h5py.File(self.partial, "r") as f:
                    stale = f.attrs.get("resume_hash", f.attrs.get("config_hash")) != rhash
            except OSError:
                stale = True
            if stale:
                self.partial.unlink()
        fresh = not self.partial.exists()
        self._f = h5py.File(self.partial, "a")
        a = self._f.attrs
        a["config"] = config_yaml          # resumed too: the file describes the run that finishes it
        a["config_hash"] = chash
        a["resume_hash"] = rhash
        if fresh:
            a["versions"] = versions_json       # of the run that started it
            a["schema_version"] = SCHEMA_VERSION
            a["scene"] = scene
            a["state_layout"] = layout.to_json()
            a["effects"] = json.dumps(list(effects))
            a["dt"] = float(dt)
            g = self._f.create_group("mesh")
            g.create_dataset("nodes", data=np.asarray(mesh.nodes, dtype=np.float64))
            g.create_dataset("tets", data=np.asarray(mesh.tets, dtype=np.int64))
            g.create_dataset("node_type", data=np.asarray(mesh.node_type, dtype=np.int8))
            if mesh.graph_edges is not None:
                g.create_dataset("edges", data=np.asarray(mesh.graph_edges, dtype=np.int64))
            self._f.create_group("trajectories")
            self._f.flush()
        self.layout = layout

    def set_split(self, split: dict[str, list[str]]) -> None:
        """Fix the train/val/test split (trajectory names), e.g. a published reference split."""
        self._f.attrs["split"] = json.dumps({k: list(v) for k, v in split.items()})

    def set_linear(self, linear: LinearSolid) -> None:
        """Store the solid linearised at rest (group ``/linear``, module docstring); replaces an
        earlier one (a resumed run); finalised with the file."""
        if "linear" in self._f:
            del self._f["linear"]
        g = self._f.create_group("linear")
        for name in ("stiffness", "mass", "stress", "stiffness_iso", "stress_iso"):
            matrix = getattr(linear, name)
            if matrix is not None:
                _write_csr(g, name, matrix)
        g.create_dataset("free", data=np.asarray(linear.free, dtype=bool))
        if linear.body_force is not None:
            g.create_dataset("body_force", data=np.asarray(linear.body_force, dtype=np.float64))
        g.attrs.update({"rayleigh": np.asarray(linear.rayleigh, dtype=np.float64), "integrator": linear.integrator,
                        "beta": float(linear.beta), "gamma": float(linear.gamma)})
        if linear.prony:
            g.attrs["prony"] = json.dumps([[float(a), float(b)] for a, b in linear.prony])
        for name in ("shear_modulus", "bulk_modulus"):
            if getattr(linear, name) is not None:
                g.attrs[name] = float(getattr(linear, name))

    def set_time_resolution(self, report: dict) -> None:
        """Store generate's time-resolution diagnostic (JSON) on the root; finalised with the file."""
        self._f.attrs["time_resolution"] = json.dumps(report)

    def set_substeps(self, substeps: int) -> None:
        """Store how many FE steps the FE took per stored step (``scene.time.substeps``)."""
        self._f.attrs["substeps"] = int(substeps)

    def set_time_convergence(self, report: dict) -> None:
        """Store generate's time-convergence check (JSON) on the root; finalised with the file."""
        self._f.attrs["time_convergence"] = json.dumps(report)

    def has(self, name: str) -> bool:
        return name in self._f["trajectories"]

    def ok_trajectories(self):
        """Yield the trajectories written so far with status 'ok' (read back, in natural order)."""
        grp = self._f["trajectories"]
        for name in sorted(grp.keys(), key=_natural_key):
            if str(grp[name].attrs.get("status", "ok")) == "ok":
                yield _trajectory_from_group(grp[name], name)

    def write(self, traj: Trajectory) -> None:
        """Write one trajectory (flushed at once, so an interruption keeps it)."""
        if not np.all(np.isfinite(traj.z)) or not np.all(np.isfinite(traj.force)):
            raise ValueError(f"trajectory {traj.name}: non-finite values must not be written")
        if traj.z.ndim != 3 or traj.z.shape[2] != self.layout.dim:
            raise ValueError(f"trajectory {traj.name}: z shape {traj.z.shape}, expected (S, N, {self.layout.dim})")
        grp = self._f["trajectories"]
        if traj.name in grp:
            del grp[traj.name]
        g = grp.create_group(traj.name)
        g.create_dataset("time", data=np.asarray(traj.time, np.float64))
        g.create_dataset("z", data=np.asarray(traj.z, np.float64), compression="gzip", compression_opts=1)
        g.create_dataset("force", data=np.asarray(traj.force, np.float64), compression="gzip",
                         compression_opts=1)
        g.create_dataset("load_nodes", data=np.asarray(traj.load_nodes, np.int64))
        g.attrs["status"] = traj.status
        g.attrs["reason"] = traj.reason
        g.attrs["load_point"] = np.asarray(traj.load_point, np.float64)
        if traj.split_group:
            g.attrs["split_group"] = traj.split_group
        if np.isfinite(traj.fe_seconds):
            g.attrs["fe_seconds"] = float(traj.fe_seconds)
            g.attrs["fe_iterations"] = int(traj.fe_iterations)
            g.attrs["fe_cuts"] = int(traj.fe_cuts)
        self._f.flush()

    def close(self, finalize: bool) -> None:
        self._f.close()
        if finalize:
            os.replace(self.partial, self.path)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(finalize=exc_type is None)


class Dataset:
    """Read-only view of a thermognn HDF5 dataset; validates the schema on open."""

    def __init__(self, path) -> None:
        import h5py

        self.path = Path(path)
        if not self.path.exists():
            raise DataError(f"{self.path}: dataset not found (run `thermognn generate` first)")
        try:
            f = h5py.File(self.path, "r")
        except OSError as exc:
            raise DataError(f"{self.path}: not a readable HDF5 file ({exc.__class__.__name__})") from None
        with f:
            attrs = dict(f.attrs)
            for key in ("schema_version", "state_layout", "dt", "config"):
                if key not in attrs:
                    raise DataError(f"{self.path}: missing root attribute '{key}' (not a thermognn dataset?)")
            if int(attrs["schema_version"]) != SCHEMA_VERSION:
                raise DataError(f"{self.path}: schema_version {attrs['schema_version']}, expected {SCHEMA_VERSION}")
            for key in ("mesh/nodes", "mesh/tets", "mesh/node_type", "trajectories"):
                if key not in f:
                    raise DataError(f"{self.path}: missing '{key}'")
            self.mesh = Mesh(f["mesh/nodes"][()], f["mesh/tets"][()], f["mesh/node_type"][()],
                             f["mesh/edges"][()] if "mesh/edges" in f else None)
            self.names = sorted(f["trajectories"].keys(), key=_natural_key)
            self.status = {n: str(f["trajectories"][n].attrs.get("status", "ok")) for n in self.names}
            #: each trajectory's split group where the file records one (``Trajectory.split_group``)
            self.split_groups = {n: str(f["trajectories"][n].attrs["split_group"]) for n in self.names
                                 if f["trajectories"][n].attrs.get("split_group", "")}
            #: each trajectory's load point [m], (3,), where the file records one (``Trajectory.load_point``)
            self.load_points = {n: np.asarray(f["trajectories"][n].attrs["load_point"], np.float64)
                                for n in self.names if "load_point" in f["trajectories"][n].attrs}
        self.layout = StateLayout.from_json(str(attrs["state_layout"]))
        self.dt = float(attrs["dt"])
        self.config_yaml = str(attrs["config"])
        self.scene = str(attrs.get("scene", ""))
        self.effects = tuple(json.loads(str(attrs.get("effects", '["elastic"]'))))
        self.versions = str(attrs.get("versions", "{}"))
        #: fixed split {"train": [...], "val": [...], "test": [...]} or None (then split at random)
        self.split = json.loads(str(attrs["split"])) if "split" in attrs else None
        #: generate's time-resolution diagnostic (dict), None in files written before it existed
        self.time_resolution = (json.loads(str(attrs["time_resolution"])) if "time_resolution" in attrs
                                else None)
        #: FE steps per stored step (``scene.time.substeps``; 1 in files written before it existed)
        self.substeps = int(attrs.get("substeps", 1))
        #: generate's time-convergence check (dict), None where it was not run
        self.time_convergence = (json.loads(str(attrs["time_convergence"])) if "time_convergence" in attrs
                                 else None)

    def linear_solid(self) -> LinearSolid | None:
        """The solid linearised at rest (``/linear``), or None in files written before it existed
        (or by an importer, which has no FE model). DataError if the group is incomplete. Read
        once: every call returns the same object, so its callers (a prior model, evaluate's
        baseline and gentle-load check) share its LU factorisations; treat it as read-only."""
        if not hasattr(self, "_linear"):
            self._linear = self._read_linear()
        return self._linear

    def _read_linear(self) -> LinearSolid | None:
        import h5py

        with h5py.File(self.path, "r") as f:
            if "linear" not in f:
                return None
            g = f["linear"]
            try:
                free = g["free"][()].astype(bool)
                linear = LinearSolid(
                    stiffness=_read_csr(g, "stiffness"), mass=_read_csr(g, "mass"), free=free,
                    stress=_read_csr(g, "stress") if "stress" in g else None,
                    rayleigh=tuple(float(r) for r in g.attrs["rayleigh"]), integrator=str(g.attrs["integrator"]),
                    beta=float(g.attrs["beta"]), gamma=float(g.attrs["gamma"]),
                    body_force=g["body_force"][()] if "body_force" in g else None,
                    prony=tuple((float(a), float(b)) for a, b in json.loads(str(g.attrs.get("prony", "[]")))),
                    stiffness_iso=_read_csr(g, "stiffness_iso") if "stiffness_iso" in g else None,
                    stress_iso=_read_csr(g, "stress_iso") if "stress_iso" in g else None,
                    **{k: float(g.attrs[k]) for k in ("shear_modulus", "bulk_modulus") if k in g.attrs})
            except KeyError as exc:
                raise DataError(f"{self.path}: /linear lacks {exc}") from None
        n = int(free.sum())
        if linear.stiffness.shape != (n, n) or free.shape != (3 * len(self.mesh.nodes),):
            raise DataError(f"{self.path}: /linear stiffness {linear.stiffness.shape} does not fit "
                            f"{n} free DOFs of {len(self.mesh.nodes)} nodes")
        return linear

    @property
    def ok_names(self) -> list[str]:
        return [n for n in self.names if self.status[n] == "ok"]

    @property
    def material(self) -> dict:
        """``scene.material`` of the config the dataset was generated with (the law, its parameters
        and Prony terms), {} where it has none (imported datasets)."""
        import yaml

        try:
            scene = (yaml.safe_load(self.config_yaml or "") or {}).get("scene") or {}
            material = scene.get("material") or {}
        except (yaml.YAMLError, AttributeError):
            return {}
        return material if isinstance(material, dict) else {}

    def fe_cost(self, names: list[str]) -> dict | None:
        """What ``generate``'s FE solve of the trajectories ``names`` cost, as it recorded it (on
        the machine that generated them): {"ms_per_step": wall time a step [ms], "iterations_per_step":
        Newton iterations a step, "cuts": step cuts in all, "steps"}; None where any of them has no
        record (datasets from before session 49, imported ones)."""
        import h5py

        seconds, iterations, cuts, steps = 0.0, 0, 0, 0
        with h5py.File(self.path, "r") as f:
            for name in names:
                g = f["trajectories"][name]
                if "fe_seconds" not in g.attrs:
                    return None
                seconds += float(g.attrs["fe_seconds"])
                iterations += int(g.attrs["fe_iterations"])
                cuts += int(g.attrs["fe_cuts"])
                steps += int(g["time"].shape[0]) - 1
        if not steps:
            return None
        return {"ms_per_step": 1e3 * seconds / steps, "iterations_per_step": iterations / steps, "cuts": cuts,
                "steps": steps}

    def read(self, name: str) -> Trajectory:
        import h5py

        with h5py.File(self.path, "r") as f:
            if name not in f["trajectories"]:
                raise DataError(f"{self.path}: no trajectory '{name}'")
            try:
                traj = _trajectory_from_group(f["trajectories"][name], name)
            except KeyError as exc:
                raise DataError(f"{self.path}: trajectory '{name}' lacks {exc}") from None
        n = self.mesh.nodes.shape[0]
        if traj.z.shape[1:] != (n, self.layout.dim):
            raise DataError(f"{self.path}: trajectory '{name}' z has shape {traj.z.shape}, "
                            f"expected (S, {n}, {self.layout.dim})")
        return traj


def _write_csr(group, name: str, matrix) -> None:
    """A dense or scipy.sparse matrix as CSR arrays data / indices / indptr (gzip) + attrs shape."""
    import scipy.sparse as sp

    A = sp.csr_matrix(matrix)
    g = group.create_group(name)
    g.attrs["shape"] = np.asarray(A.shape, dtype=np.int64)
    for key in ("data", "indices", "indptr"):
        g.create_dataset(key, data=getattr(A, key), compression="gzip")


def _read_csr(group, name: str):
    import scipy.sparse as sp

    g = group[name]
    return sp.csr_matrix((g["data"][()], g["indices"][()], g["indptr"][()]), shape=tuple(g.attrs["shape"]))


def _trajectory_from_group(g, name: str) -> Trajectory:
    """A trajectory from its HDF5 group (KeyError when a dataset is missing)."""
    return Trajectory(name=name, time=g["time"][()], z=g["z"][()], force=g["force"][()],
                      load_nodes=g["load_nodes"][()],
                      load_point=np.asarray(g.attrs.get("load_point", np.zeros(3))),
                      status=str(g.attrs.get("status", "ok")),
                      reason=str(g.attrs.get("reason", "")),
                      split_group=str(g.attrs.get("split_group", "")),
                      fe_seconds=float(g.attrs.get("fe_seconds", float("nan"))),
                      fe_iterations=int(g.attrs.get("fe_iterations", 0)),
                      fe_cuts=int(g.attrs.get("fe_cuts", 0)))


def _natural_key(s: str):
    import re
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]
