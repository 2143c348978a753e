"""Import the public TIGNN viscoelastic-beam dataset (Hernández et al., IEEE TAI 2022).

Source: a folder of ``beam_K.pt`` files (K = 1..52), each a ``torch.save``d list of 20
``torch_geometric.data.Data`` snapshots with ``x`` = z_t (756, 12), ``y`` = z_{t+1}, ``f``
(756, 3) external nodal force, ``n`` (756, 2) one-hot node type (free, clamped) and
``edge_index`` (2, 3960). z = (q, v, Cauchy stress s11 s22 s33 s12 s13 s23).

The files are pickles, so they are loaded with ``torch.load(weights_only=True)`` and an
explicit allow-list of the two PyG classes they contain: no arbitrary code is ever run.

Mapping into schema v1 (thermognn/core/schema.py), 21 states per trajectory:
``z[0] = x_0``, ``z[s+1] = y_s``; snapshot s's force is the load at the end of its step,
so ``force[s+1] = f_s`` and ``force[0] = 0``. The mesh has graph edges but no tetrahedra.
The authors' reference split (seed 1) is stored in the root attribute ``split``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from thermognn.core.errors import DataError
from thermognn.core.io import versions_json
from thermognn.core.schema import NODE_CLAMPED, NODE_FREE, DatasetWriter, Mesh, Trajectory
from thermognn.core.state import state_layout

#: The published pretrained TIGNN model re-run on this machine (issue 4): the reference metric on the
#: reference test split (per-snapshot relative L2 error, clamped nodes imposed), its parameter count
#: and its step time (ms, 2 CPU threads).
PUBLISHED = {"q": 4.1e-3, "v": 1.7e-2, "sigma": 9.5e-2, "params": 268_000, "ms_per_step": 84.0}

DT = 1.0 / 20.0  # [s] (dataset README)
EFFECTS = ("elastic", "viscous", "inertia")
#: the dataset authors' split (seed 1); the other 41 trajectories are training
REFERENCE_SPLIT = {"val": [1, 2, 6, 16, 17], "test": [9, 10, 12, 13, 38, 44]}
N_NODES, N_STATE = 756, 12


def _load_snapshots(path: Path) -> list:
    """Load one ``beam_K.pt`` safely (weights_only + allow-list of PyG's Data and GlobalStorage)."""
    import pickle

    import torch
    from torch_geometric.data import Data
    from torch_geometric.data.storage import GlobalStorage

    try:
        with torch.serialization.safe_globals([Data, GlobalStorage]):
            snaps = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[0]
        raise DataError(f"{path}: refused to unpickle (not an allow-listed TIGNN snapshot list): {first}") from None
    except (OSError, RuntimeError, EOFError) as exc:
        raise DataError(f"{path}: not a readable torch file ({type(exc).__name__})") from None
    if not isinstance(snaps, list) or not snaps or not all(isinstance(s, Data) for s in snaps):
        raise DataError(f"{path}: expected a list of torch_geometric Data snapshots")
    for key in ("x", "y", "f", "n", "edge_index"):
        if getattr(snaps[0], key, None) is None:
            raise DataError(f"{path}: snapshot lacks '{key}'")
    if tuple(snaps[0].x.shape) != (N_NODES, N_STATE):
        raise DataError(f"{path}: x has shape {tuple(snaps[0].x.shape)}, expected ({N_NODES}, {N_STATE})")
    return snaps


def _trajectory(name: str, snaps: list) -> Trajectory:
    x0 = snaps[0].x.double().numpy()
    z = np.stack([x0] + [s.y.double().numpy() for s in snaps])  # (S+1, N, 12)
    force = np.zeros((len(snaps) + 1, N_NODES, 3))
    force[1:] = np.stack([s.f.double().numpy() for s in snaps])  # force[s+1] drives z[s] -> z[s+1]
    loaded = np.nonzero(np.abs(force).sum(axis=(0, 2)) > 0)[0]
    return Trajectory(name=name, time=np.arange(len(snaps) + 1) * DT, z=z, force=force,
                      load_nodes=loaded, load_point=z[0, loaded, :3].mean(axis=0) if loaded.size else np.zeros(3))


def import_tignn(source: str | Path, out: str | Path) -> Path:
    """Convert ``source/beam_K.pt`` into one thermognn HDF5 dataset at ``out`` (atomic, resumable)."""
    from rich.progress import Progress

    source, out = Path(source), Path(out)
    files = sorted(source.glob("beam_*.pt"), key=lambda p: int(re.findall(r"\d+", p.stem)[-1]))
    if not files:
        raise DataError(f"{source}: no beam_K.pt files found (expected the TIGNN beam dataset folder)")
    first = _load_snapshots(files[0])
    node_type = np.where(first[0].n[:, 1].numpy() > 0, NODE_CLAMPED, NODE_FREE).astype(np.int8)
    mesh = Mesh(nodes=first[0].x[:, :3].double().numpy(), tets=np.zeros((0, 4), np.int64),
                node_type=node_type, graph_edges=first[0].edge_index.numpy().astype(np.int64))
    names = [f"beam_{int(re.findall(r'[0-9]+', p.stem)[-1])}" for p in files]
    split = {"train": [n for n in names if int(n.split("_")[1]) not in
                       REFERENCE_SPLIT["val"] + REFERENCE_SPLIT["test"]],
             "val": [f"beam_{k}" for k in REFERENCE_SPLIT["val"]],
             "test": [f"beam_{k}" for k in REFERENCE_SPLIT["test"]]}
    config_yaml = f"scene:\n  name: tignn_beam\n  source: {source.resolve()}\n"
    writer = DatasetWriter(out, mesh, state_layout(EFFECTS), DT, config_yaml, versions_json(),
                           scene="tignn_beam", effects=EFFECTS)
    with writer, Progress(transient=True) as progress:
        writer.set_split(split)
        task = progress.add_task("importing TIGNN beam", total=len(files))
        for path, name in zip(files, names):
            if not writer.has(name):
                snaps = first if path == files[0] else _load_snapshots(path)
                if not np.array_equal(snaps[0].edge_index.numpy(), mesh.graph_edges):
                    raise DataError(f"{path}: edge_index differs from {files[0].name}'s (one mesh expected)")
                writer.write(_trajectory(name, snaps))
            progress.advance(task)
    return out
