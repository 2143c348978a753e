"""A damped spring network on a tet box, exported per the "Exported model" contract.

For tests, benchmarks and demos of the serve stage without a trained model: a real TorchScript
file with the contract's buffers and metadata, stepping z = (q, v, sigma) [N, 12] by
semi-implicit Euler. Imports torch (never used by the haptic process).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from thermognn.core.state import state_layout


def box_mesh(n: tuple[int, int, int], size: tuple[float, float, float]):
    """Structured box: nodes X [N, 3] (z = 0 bottom), edges [2, E] (tet edges of the 6-tet hex split
    plus all cube edges), boundary triangles [F, 3], node_type [N] (1 bottom, 2 top, 0 else)."""
    nx, ny, nz = n
    gx, gy, gz = (np.linspace(0.0, s, k) for s, k in zip(size, n))
    X = np.stack(np.meshgrid(gx - size[0] / 2, gy - size[1] / 2, gz, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    edges = set()
    faces = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            for k in range(nz - 1):
                c = [idx[i + a, j + b, k + d] for a in (0, 1) for b in (0, 1) for d in (0, 1)]
                for p in range(8):             # all pairs in the cell: edges, face and body diagonals
                    for q in range(p + 1, 8):
                        edges.add((min(c[p], c[q]), max(c[p], c[q])))
    def quads(a_idx):  # boundary quads of a 2D index grid -> 2 triangles each
        for u in range(a_idx.shape[0] - 1):
            for w in range(a_idx.shape[1] - 1):
                p0, p1, p2, p3 = a_idx[u, w], a_idx[u + 1, w], a_idx[u + 1, w + 1], a_idx[u, w + 1]
                faces.extend([(p0, p1, p2), (p0, p2, p3)])
    for sl in (idx[0], idx[-1], idx[:, 0], idx[:, -1], idx[:, :, 0], idx[:, :, -1]):
        quads(sl)
    node_type = np.zeros(len(X), dtype=np.int64)
    node_type[idx[:, :, -1].reshape(-1)] = 2
    node_type[idx[:, :, 0].reshape(-1)] = 1
    E = np.array(sorted(edges), dtype=np.int64).T
    edge_index = np.concatenate([E, E[::-1]], axis=1)      # both directions, as a graph would
    return X, edge_index, np.array(faces, dtype=np.int64), node_type


def build_spring_model(n=(5, 5, 3), size=(0.04, 0.04, 0.02), stiffness: float = 50.0, damping: float = 0.05,
                       mass: float = 0.002, dt: float = 1e-3, nan_after: int = -1):
    """Scripted damped spring network (torch.jit.ScriptModule) and its metadata dict.

    ``stiffness`` per spring [N/m], ``damping`` per node [N s/m], ``mass`` per node [kg], ``dt`` [s].
    ``nan_after`` >= 0 makes forward return NaN from that step on (fault-injection tests).
    """
    import torch

    X, edge_index, faces, node_type = box_mesh(n, size)
    layout = state_layout(["elastic", "inertia"])

    class SpringNetwork(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            Xt = torch.tensor(X, dtype=torch.float64)
            z0 = torch.zeros(len(X), layout.dim, dtype=torch.float64)
            z0[:, 0:3] = Xt
            ei = torch.tensor(edge_index)
            self.register_buffer("reference_positions", Xt)
            self.register_buffer("z0", z0)
            self.register_buffer("edge_index", ei)
            self.register_buffer("node_type", torch.tensor(node_type))
            self.register_buffer("surface_faces", torch.tensor(faces))
            self.register_buffer("dt", torch.tensor(dt, dtype=torch.float64))
            self.register_buffer("rest_length", (Xt[ei[1]] - Xt[ei[0]]).norm(dim=1))
            self.register_buffer("steps", torch.zeros((), dtype=torch.int64))
            self.k = stiffness
            self.c = damping
            self.m = mass
            self.nan_after = nan_after

        def spring_forces(self, q: torch.Tensor) -> torch.Tensor:
            src, dst = self.edge_index[0], self.edge_index[1]
            d = q[dst] - q[src]                                              # [E, 3]
            length = torch.linalg.vector_norm(d, dim=1, keepdim=True)                           # [E, 1]
            fe = self.k * (length - self.rest_length.unsqueeze(1)) * d / length  # on src, towards dst
            return torch.zeros_like(q).index_add(0, src, fe)                 # [N, 3]

        def forward(self, z: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
            q, v = z[:, 0:3], z[:, 3:6]
            a = (self.spring_forces(q) + f - self.c * v) / self.m
            v_new = v + self.dt * a
            q_new = q + self.dt * v_new
            clamped = (self.node_type == 1).unsqueeze(1)
            q_new = torch.where(clamped, self.reference_positions, q_new)
            v_new = torch.where(clamped, torch.zeros_like(v_new), v_new)
            out = torch.cat([q_new, v_new, torch.zeros_like(z[:, 6:12])], dim=1)
            self.steps += 1
            if self.nan_after >= 0 and int(self.steps) > self.nan_after:
                out = out * float("nan")
            return out

        @torch.jit.export
        def energy_entropy(self, z: torch.Tensor):
            q, v = z[:, 0:3], z[:, 3:6]
            d = q[self.edge_index[1]] - q[self.edge_index[0]]
            stretch = torch.linalg.vector_norm(d, dim=1) - self.rest_length
            energy = 0.25 * self.k * (stretch * stretch).sum() + 0.5 * self.m * (v * v).sum()
            return energy, torch.zeros_like(energy)

    module = torch.jit.script(SpringNetwork())
    meta = {"format": "thermognn-model/1", "scene": "toy_box", "effects": ["elastic", "inertia"],
            "state_layout": layout.to_json(), "dt": dt, "structure": "hamiltonian",
            "config": "", "versions": {"torch": torch.__version__}}
    return module, meta


def export_spring_model(path: str | Path, **kwargs) -> Path:
    """Build the spring network and save it as a TorchScript file with ``thermognn.json`` metadata."""
    import torch

    from thermognn.core.io import atomic_path

    module, meta = build_spring_model(**kwargs)
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.jit.save(module, str(tmp), _extra_files={"thermognn.json": json.dumps(meta)})
    return path
