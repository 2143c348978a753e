"""The exported (TorchScript) module: the trained TIGNN plus its mesh as buffers.

Contract (docs/stages.md, "Exported model"), in the model's dtype::

    forward(z [N, D], f [N, 3]) -> z_next [N, D]     one step, SI units, clamped nodes imposed
    energy_entropy(z [N, D]) -> (E, S)               learned energy and entropy (0-dim; S = 0
                                                     for Hamiltonian models), at zero load
    buffers: reference_positions [N, 3], z0 [N, D], edge_index [2, E] int64,
             node_type [N] int64, surface_faces [F, 3] int64, dt (0-dim) [s]

Never call it under ``torch.no_grad()``: dE/dz and dS/dz come from autograd.
"""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor, nn

from thermognn.train.model import TIGNN


class ExportedTIGNN(nn.Module):
    def __init__(self, core: TIGNN, reference_positions: Tensor, z0: Tensor, edge_index: Tensor,
                 node_type: Tensor, surface_faces: Tensor, dt: float) -> None:
        super().__init__()
        dtype = core.z_mean.dtype
        self.core = core
        self.register_buffer("reference_positions", reference_positions.to(dtype).contiguous())
        self.register_buffer("z0", z0.to(dtype).contiguous())
        self.register_buffer("edge_index", edge_index.to(torch.int64).contiguous())
        self.register_buffer("node_type", node_type.to(torch.int64).contiguous())
        self.register_buffer("surface_faces", surface_faces.to(torch.int64).reshape(-1, 3).contiguous())
        self.register_buffer("dt", torch.tensor(float(dt), dtype=dtype))

    def forward(self, z: Tensor, f: Tensor) -> Tensor:
        """One time step z_n -> z_{n+1} [N, D] driven by the nodal force f [N, 3] [N] at t_{n+1}."""
        return self.core.step(z, f, self.edge_index, self.node_type, self.reference_positions, self.dt)

    @torch.jit.export
    def energy_entropy(self, z: Tensor) -> Tuple[Tensor, Tensor]:
        """Learned total energy E and entropy S of the state z [N, D] (0-dim tensors), at zero load."""
        f = torch.zeros(z.shape[0], 3, dtype=z.dtype, device=z.device)
        energy, entropy = self.core.energy_entropy(z, self.edge_index, self.node_type, self.reference_positions, f)
        return energy.detach(), entropy.detach()
