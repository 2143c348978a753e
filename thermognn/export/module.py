"""The exported (TorchScript) module: the trained TIGNN plus its mesh as buffers.

Contract (docs/stages.md, "Exported model"), in the model's dtype::

    forward(z [N, D], f [N, 3]) -> z_next [N, D]     one step, SI units, clamped nodes imposed
    energy_entropy(z [N, D]) -> (E, S)               learned energy and entropy (0-dim; S = 0
                                                     for Hamiltonian models), at zero load (a
                                                     prior model: the body's energy, S = 0)
    buffers: reference_positions [N, 3], z0 [N, D], edge_index [2, E] int64,
             node_type [N] int64, surface_faces [F, 3] int64, dt (0-dim) [s]

    begin(z [N, D], f [N, 3]) -> the state ``forward`` steps (here z itself)
    report(z [N, D]) -> z as reported: with ``model.stress_readout`` the stress read off the
                        positions (the stepped state keeps the network's σ); else z

A model trained with ``model.prior=linear`` exports as :class:`ExportedLinearPrior`: the same
contract on its *carried* state [N, D + 6 (+ 9 T)], the physical state with Newmark's acceleration a
[m/s²] and the last internal-force remainder G [N] appended, and with ``model.prior_relax`` the
prior's Prony internal variables, 9 columns per term T (``thermognn.train.hybrid``; the
metadata's state_layout lists them as groups ``a``, ``G``, ``prony_force_i``, ``prony_stress_i``, or for the
corotated prior its per-cell variables ``prony_cells_i``), in float64; ``z0`` is already
carried, and ``begin`` makes a carried state from a physical one.

Never call it under ``torch.no_grad()``: dE/dz and dS/dz come from autograd.
"""

from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch import Tensor, nn

from thermognn.train.hybrid import LinearPriorModel
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
    def begin(self, z: Tensor, f: Tensor) -> Tensor:
        """The state ``forward`` steps, from a physical state z [N, D] under the load f [N, 3]:
        z with the clamped nodes imposed."""
        return self.core.impose(z, self.node_type, self.reference_positions)

    @torch.jit.export
    def energy_entropy(self, z: Tensor) -> Tuple[Tensor, Tensor]:
        """Learned total energy E and entropy S of the state z [N, D] (0-dim tensors), at zero load."""
        f = torch.zeros(z.shape[0], 3, dtype=z.dtype, device=z.device)
        energy, entropy = self.core.energy_entropy(z, self.edge_index, self.node_type, self.reference_positions, f)
        return energy.detach(), entropy.detach()

    @torch.jit.export
    def report(self, z: Tensor, f: Optional[Tensor] = None) -> Tensor:
        """The state z [N, D] as the model reports it: with ``model.stress_readout`` its stress read
        off the positions (and, with ``model.stress_readout_load``, the applied load f [N, 3] (N) of
        that state; None: unloaded), the state ``forward`` steps keeping the network's own σ; else z."""
        return self.core.report(z, self.reference_positions, f)


class ExportedLinearPrior(nn.Module):
    """The linearised FE Newmark step with the network's remainders (``model.prior=linear``),
    stepping the carried state [N, D + 6 (+ 9 T)] in float64 (module docstring)."""

    def __init__(self, core: LinearPriorModel, z0: Tensor, edge_index: Tensor, node_type: Tensor,
                 surface_faces: Tensor, dt: float) -> None:
        super().__init__()
        self.core = core
        X = core.reference_positions
        self.register_buffer("reference_positions", X.to(torch.float64).contiguous())          # [N, 3] m
        self.register_buffer("network_positions", X.to(core.net.z_mean.dtype).contiguous())   # the network's dtype
        self.register_buffer("edge_index", edge_index.to(torch.int64).contiguous())
        self.register_buffer("node_type", node_type.to(torch.int64).contiguous())
        self.register_buffer("surface_faces", surface_faces.to(torch.int64).reshape(-1, 3).contiguous())
        self.register_buffer("dt", torch.tensor(float(dt), dtype=torch.float64))
        with torch.enable_grad():
            carried = self.begin(z0.to(torch.float64), torch.zeros_like(X, dtype=torch.float64))
        self.register_buffer("z0", carried.detach().contiguous())                             # [N, D + 6 (+ 9 T)]

    def forward(self, z: Tensor, f: Tensor) -> Tensor:
        """One time step of the carried state z [N, D + 6 (+ 9 T)] driven by the nodal force f [N, 3] [N]
        at t_{n+1}."""
        return self.core.step(z.to(torch.float64), f.to(torch.float64), self.edge_index, self.node_type,
                              self.network_positions, self.dt)

    @torch.jit.export
    def begin(self, z: Tensor, f: Tensor) -> Tensor:
        """The carried state [N, D + 6 (+ 9 T)] of a physical state z [N, D] under the load f [N, 3]:
        Newmark's acceleration from the balance of forces there, G from the network."""
        return self.core.carry(z.to(torch.float64), f.to(torch.float64), self.edge_index, self.node_type,
                               self.network_positions)

    @torch.jit.export
    def energy_entropy(self, z: Tensor) -> Tuple[Tensor, Tensor]:
        """The body's energy E [J] of the (carried) state z [N, D(+...)], and S = 0 (0-dim; the
        network's remainders learn no energy): the linearised solid's elastic and kinetic energy
        u K u / 2 + v M v / 2, or a law prior's ½ vᵀ M v + Σ_e V_e (Ψ_vol + g∞ Ψ_iso) − f_body · u
        (``prior.body_energy``)."""
        P = self.core.prior
        x = z.to(torch.float64).unsqueeze(0)
        u = P.gather(x[:, :, 0:3] - self.reference_positions.unsqueeze(0))
        v = P.gather(x[:, :, 3:6])
        energy = P.body_energy(u, v).sum()
        return energy.detach(), torch.zeros_like(energy)

    @torch.jit.export
    def report(self, z: Tensor, f: Optional[Tensor] = None) -> Tensor:
        """The state as the model reports it: z itself (the prior's stress is the state's; f unused)."""
        return z
