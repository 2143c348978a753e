"""Thermodynamics-informed graph network (TIGNN): encode-process-decode with a GENERIC decoder.

Notation (per node i of a graph with N nodes, state dimension D, E directed edges)::

    z   [N, D]   state (q, v, sigma, ...) in SI units; zn = (z - z_mean) / z_std (normalised)
    f   [N, 3]   external nodal force [N]
    edge features  [E, 4..16]    q_i - q_j, |q_i - q_j| (+ reference and relative-displacement
                                 terms, + v_i - v_j and the stretch rate: ``raw_edge_features``)
    node features  [N, D-3+3+3]  zn without q (v, sigma, ...), node type one-hot, normalised force

Positions enter only as differences along edges (Galilean invariance); with inertia the edges also
carry v_i - v_j and the stretch rate (``velocity_edges``). The decoder gives per node ``l``
(D x D), ``m`` (D x D), E_i and S_i; with L = l - l^T (skew), M = m m^T (PSD), E = sum_i E_i,
S = sum_i S_i and the gradients taken by autograd with respect to zn::

    r = L dE/dw + M dS/dw (+ W fn, the port term)                 GENERIC
    r = L dE/dw           (+ W fn)                                 Hamiltonian
    dz/dt  = r * dzdt_std,  r = (dw/dt) / c   [SI units per second]

With ``edge_operators`` an edge decoder also gives A_e (D x D) per directed edge j -> i and the
Poisson operator is diag(L_i) + A - A^T (``poisson_apply``; still skew, the graph-coupled L of
TIGNN): node i's rate then depends on its neighbours' dE/dw directly.

The operators act in the balanced coordinates w = zn / c = (z - z_mean) / sqrt(z_std * dzdt_std),
c = sqrt(dzdt_std / z_std) [D] (per column, 1/sqrt(s)): each column scaled by the geometric mean of its state and
rate scales, so that L and M need no entries spanning the columns' very different time scales.
In w the operators are exactly skew (L) and PSD (M), so the *physical* dynamics conserve the
learned E (dE/dt = dE/dz . dz/dt = dE/dw . L dE/dw = 0 without the port) and produce entropy
(dS/dt = dS/dw . M dS/dw >= 0 where L dS/dw = 0), while r stays O(1) per column for the loss.
(Applying L to dE/dzn and rescaling each column by dzdt_std would break both identities.)
Checkpoints from before this form load with ``balanced=False`` (c = 1).

Integrators (``integrator``), with q = X, v = 0 imposed on clamped nodes after every update::

    euler      z_{n+1} = z_n + dt dz/dt(z_n)                        1 network call per step
    midpoint   z_{n+1} = z_n + dt dz/dt((z_n + z_{n+1}) / 2)        implicit, solved by
               ``implicit_iterations`` fixed-point sweeps from the Euler predictor
               (1 + iterations calls); second order, and E changes only by the port's work
               up to O(dt^3) per step (Euler: O(dt^2)). Trained the same way: the rate is
               evaluated at the midpoint of the two known snapshots (no extra cost).

With ``exact_kinematics`` either integrator then takes the positions from the velocities,
q_{n+1} = q_n + dt (v_n + v_{n+1}) / 2 (``advance``): dq/dt = v is an identity, and a learned
dq/dt a few per cent off drags every other variable along (TIGNN beam: q error 12x lower).

Everything here is TorchScript-able (``torch.jit.script``): message passing is written with
``index_select``/``index_add`` rather than PyG's MessagePassing. The module must never run under
``torch.no_grad()``: dE/dz and dS/dz come from ``torch.autograd.grad``.
"""

from __future__ import annotations

import inspect
import re
from typing import Any, Dict, List, Optional, Tuple

import torch
from torch import Tensor, nn

from ..core.errors import ConfigError
from .stress_readout import StressReadout

NODE_TYPES = 3  # free, clamped, loadable surface
CLAMPED = 1
AGGREGATIONS = ("sum", "mean")
INTEGRATORS = ("euler", "midpoint")


class MLP(nn.Module):
    """``layers`` hidden SiLU layers of width ``hidden`` (smooth: the model is differentiated twice),
    then a linear output, optionally followed by LayerNorm. [*, n_in] -> [*, n_out]."""

    def __init__(self, n_in: int, hidden: int, n_out: int, layers: int, layer_norm: bool) -> None:
        super().__init__()
        mods: List[nn.Module] = []
        d = n_in
        for _ in range(layers):
            mods += [nn.Linear(d, hidden), nn.SiLU()]
            d = hidden
        mods.append(nn.Linear(d, n_out))
        if layer_norm:
            mods.append(nn.LayerNorm(n_out))
        self.net = nn.Sequential(*mods)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class ProcessorBlock(nn.Module):
    """One residual MeshGraphNet block: edge update from (e_ij, h_i, h_j), node update from
    (h_i, aggregated incoming edges). h [N, H], e [E, H], edge_index [2, E] (row 0 source j,
    row 1 target i).

    The edge MLP's first linear layer W [e, h_i, h_j] = W_e e + (W_i h)_i + (W_j h)_j is applied to
    the nodes before gathering (N H^2 instead of 2 E H^2 multiply-adds; identical function)."""

    def __init__(self, hidden: int, layers: int, mean_aggregation: bool) -> None:
        super().__init__()
        if layers < 1:
            raise ValueError(f"mlp_layers = {layers}, expected >= 1")
        self.edge_in = nn.Linear(hidden, hidden)
        self.edge_in_target = nn.Linear(hidden, hidden, bias=False)
        self.edge_in_source = nn.Linear(hidden, hidden, bias=False)
        self.edge_mlp = MLP(hidden, hidden, hidden, layers - 1, True)
        self.node_mlp = MLP(2 * hidden, hidden, hidden, layers, True)
        self.mean_aggregation = mean_aggregation

    def forward(self, h: Tensor, e: Tensor, edge_index: Tensor, inv_degree: Tensor) -> Tuple[Tensor, Tensor]:
        src, dst = edge_index[0], edge_index[1]
        first = (self.edge_in(e) + self.edge_in_target(h).index_select(0, dst)
                 + self.edge_in_source(h).index_select(0, src))                      # [E, H]
        e = e + self.edge_mlp(torch.nn.functional.silu(first))
        agg = torch.zeros(h.shape[0], e.shape[1], dtype=e.dtype, device=e.device).index_add(0, dst, e)
        if self.mean_aggregation:
            agg = agg * inv_degree  # [N, H] * [N, 1]
        h = h + self.node_mlp(torch.cat([h, agg], dim=1))
        return h, e


def edge_feature_count(reference_edges: bool, velocity_edges: bool) -> int:
    """Width of ``raw_edge_features``: 4, +8 with reference edges, +4 with velocity edges."""
    return 4 + (8 if reference_edges else 0) + (4 if velocity_edges else 0)


def raw_edge_features(dq: Tensor, dx: Tensor, dv: Tensor, reference_edges: bool, velocity_edges: bool) -> Tensor:
    """Edge features before normalisation, from q_i - q_j and X_i - X_j (both [E, 3], metres) and
    v_i - v_j ([E, 3], m/s): [dq, |dq|] (4); with ``reference_edges`` also
    [dX, |dX|, dq - dX, |dq| - |dX|] (+8); with ``velocity_edges`` also [dv, dv . dq / |dq|] (+4).

    The relative displacement dq - dX = u_i - u_j and the stretch |dq| - |dX| carry the strain,
    which for small deformations is a tiny perturbation of dq: normalised on their own (training
    statistics) they reach the network at full scale. Likewise the relative velocity dv and the
    edge's stretch rate d|dq|/dt = dv . dq / |dq| carry the strain *rate* (which drives the stress
    rate and the viscous dissipation); as node inputs the velocities differ between neighbours by
    a tiny fraction of their spread. All are Galilean invariant."""
    len_q = torch.sqrt(dq.pow(2).sum(1, keepdim=True) + 1e-30)  # [E, 1]
    feats = [dq, len_q]
    if reference_edges:
        len_x = torch.sqrt(dx.pow(2).sum(1, keepdim=True))
        feats += [dx, len_x, dq - dx, len_q - len_x]
    if velocity_edges:
        feats += [dv, (dv * dq).sum(1, keepdim=True) / len_q]
    return torch.cat(feats, 1)  # [E, edge_feature_count]


def skew(l: Tensor) -> Tensor:
    """L = l - l^T for a batch of matrices [N, D, D]."""
    return l - l.transpose(1, 2)


def psd(m: Tensor) -> Tensor:
    """M = m m^T for a batch of matrices [N, D, D]."""
    return torch.bmm(m, m.transpose(1, 2))


def poisson_apply(L: Tensor, A: Tensor, edge_index: Tensor, g: Tensor) -> Tensor:
    """The Poisson operator applied to a gradient g [N, D]: node blocks L [N, D, D] (skew) plus the
    graph coupling A [E, D, D] of the directed edges j -> i (``edge_index`` rows source j, target
    i) and its adjoint, (L g)_i + sum_{e: j->i} A_e g_j - sum_{e: i->k} A_e^T g_k. The whole
    operator is skew (g . L g = 0 for every g): the TIGNN form in which neighbours' gradients
    (e.g. their velocities through dE/dv) drive a node's rates, as the divergence and gradient
    operators of continuum mechanics do. A = [0, D, D]: node blocks only. [N, D]"""
    out = torch.bmm(L, g.unsqueeze(-1)).squeeze(-1)
    if A.shape[0] > 0:
        src, dst = edge_index[0], edge_index[1]
        out = out.index_add(0, dst, torch.bmm(A, g.index_select(0, src).unsqueeze(-1)).squeeze(-1))
        out = out.index_add(0, src, -torch.bmm(A.transpose(1, 2), g.index_select(0, dst).unsqueeze(-1)).squeeze(-1))
    return out


def degeneracy_loss(L: Tensor, M: Tensor, grad_E: Tensor, grad_S: Tensor, A: Tensor, edge_index: Tensor) -> Tensor:
    """Mean over nodes of ||L dS/dz||^2 + ||M dE/dz||^2. L (node blocks), M [N, D, D]; gradients
    [N, D]; the Poisson operator's edge coupling A [E, D, D] on ``edge_index`` (``poisson_apply``;
    A = [0, D, D]: node blocks only)."""
    l_ds = poisson_apply(L, A, edge_index, grad_S)
    m_de = torch.bmm(M, grad_E.unsqueeze(-1)).squeeze(-1)
    return (l_ds.pow(2).sum(1) + m_de.pow(2).sum(1)).mean()


class TIGNN(nn.Module):
    """The learned integrator. Normalisation statistics are buffers (set by ``set_stats``)."""

    def __init__(self, dim: int, velocity_columns: List[int], hidden: int = 64, mlp_layers: int = 2,
                 message_passing: int = 4, shared_weights: bool = False, aggregation: str = "sum",
                 hamiltonian: bool = False, port: bool = True, reference_edges: bool = True,
                 balanced: bool = False, integrator: str = "euler", implicit_iterations: int = 3,
                 velocity_edges: bool = False, edge_operators: bool = False,
                 exact_kinematics: bool = False, stress_readout: Optional[Dict[str, Any]] = None,
                 mirror_frames: Optional[Dict[str, int]] = None) -> None:
        super().__init__()
        if aggregation not in AGGREGATIONS:
            raise ValueError(f"aggregation '{aggregation}', expected sum or mean")
        if integrator not in INTEGRATORS:
            raise ValueError(f"integrator '{integrator}', expected euler or midpoint")
        self.balanced = balanced
        self.integrator = integrator
        self.implicit_iterations = int(implicit_iterations)
        self.dim = dim
        self.hamiltonian = hamiltonian
        self.use_port = port
        self.reference_edges = reference_edges
        if velocity_edges and len(velocity_columns) != 3:
            raise ValueError("velocity_edges needs the velocity v in the state (a scene with inertia)")
        self.velocity_edges = velocity_edges
        if exact_kinematics and len(velocity_columns) != 3:
            raise ValueError("exact kinematics needs the velocity v in the state (a scene with inertia)")
        self.exact_kinematics = exact_kinematics
        self.v_col = int(velocity_columns[0]) if velocity_columns else 0  # first column of v
        n_edge = edge_feature_count(reference_edges, velocity_edges)
        n_node = (dim - 3) + NODE_TYPES + 3
        self.node_encoder = MLP(n_node, hidden, hidden, mlp_layers, True)
        self.edge_encoder = MLP(n_edge, hidden, hidden, mlp_layers, True)
        n_blocks = 1 if shared_weights else message_passing
        self.repeats = message_passing if shared_weights else 1
        self.blocks = nn.ModuleList([ProcessorBlock(hidden, mlp_layers, aggregation == "mean")
                                     for _ in range(n_blocks)])
        # decoder outputs: l (D*D), E (1) [, m (D*D), S (1)]
        self.n_out = dim * dim + 1 if hamiltonian else 2 * (dim * dim + 1)
        self.decoder = MLP(hidden, hidden, self.n_out, mlp_layers, False)
        # graph-coupled Poisson blocks A_e (D*D per directed edge), one decoder or none
        self.edge_operators = edge_operators
        self.edge_decoders = nn.ModuleList([MLP(hidden, hidden, dim * dim, mlp_layers, False)]
                                           if edge_operators else [])
        self.port = nn.Linear(3, dim, bias=False)
        # normalisation (identity until set_stats)
        self.register_buffer("z_mean", torch.zeros(dim))
        self.register_buffer("z_std", torch.ones(dim))
        self.register_buffer("edge_mean", torch.zeros(n_edge))
        self.register_buffer("edge_std", torch.ones(n_edge))
        self.register_buffer("f_mean", torch.zeros(3))
        self.register_buffer("f_std", torch.ones(3))
        self.register_buffer("dzdt_std", torch.ones(dim))
        # columns imposed on clamped nodes: q (0..2) and v
        imposed = torch.zeros(dim, dtype=torch.bool)
        imposed[:3] = True
        for c in velocity_columns:
            imposed[c] = True
        self.register_buffer("imposed_columns", imposed)
        # the stress a rollout reports, read off the positions (``model.stress_readout``; fitted
        # after training by ``fit_readout_to_rollouts``, loaded with the checkpoint): shape from the spec
        spec = stress_readout or {"nodes": 0, "width": 0, "classes": 0, "columns": []}
        self.use_readout = stress_readout is not None
        self.readout = StressReadout(int(spec["nodes"]), int(spec["width"]), int(spec["classes"]),
                                     [int(c) for c in spec["columns"]], int(spec.get("independent", 0)),
                                     int(spec.get("load_width", 0)), int(spec.get("modes", 0)),
                                     int(spec.get("mode_values", 0)))
        columns = [int(c) for c in spec["columns"]] or [0]
        self.readout_first, self.readout_end = columns[0], columns[-1] + 1     # contiguous stress columns
        # the mesh's mirror frames a step is averaged over (``model.mirror_average``; ``set_frames``):
        # G frames of an N-node mesh, empty (and not saved) without
        frames = mirror_frames or {"frames": 0, "nodes": 0}
        G, N = int(frames["frames"]), int(frames["nodes"])
        self.n_frames = G
        keep = G > 0                                          # old checkpoints have no such buffers
        self.register_buffer("frame_source", torch.zeros(G, N, dtype=torch.long), persistent=keep)
        self.register_buffer("frame_back", torch.zeros(G, N, dtype=torch.long), persistent=keep)
        self.register_buffer("frame_matrix", torch.zeros(G, dim, dim), persistent=keep)
        self.register_buffer("frame_inverse", torch.zeros(G, dim, dim), persistent=keep)
        self.register_buffer("frame_shift", torch.zeros(G, dim), persistent=keep)

    def set_frames(self, images: List[Any]) -> None:
        """Fill the mirror frames from the mesh's symmetries (``data.state_images``: ``StateImage``s,
        the identity first), as many as ``mirror_frames`` declared."""
        if len(images) != self.n_frames:
            raise ValueError(f"set_frames: {len(images)} frames for a model built for {self.n_frames}")
        for k, im in enumerate(images):
            self.frame_source[k].copy_(im.source)
            self.frame_back[k].copy_(torch.argsort(im.source))
            self.frame_matrix[k].copy_(im.matrix)
            self.frame_inverse[k].copy_(torch.linalg.inv(im.matrix.double()))
            self.frame_shift[k].copy_(im.shift)

    def set_stats(self, stats: Dict[str, Tensor]) -> None:
        """Copy normalisation statistics (keys as the buffers: z_mean, z_std, ...) into the buffers."""
        for k, v in stats.items():
            getattr(self, k).copy_(torch.as_tensor(v, dtype=getattr(self, k).dtype))

    # --- features -------------------------------------------------------------------------
    def edge_features(self, z: Tensor, ref_pos: Tensor, edge_index: Tensor) -> Tensor:
        """Normalised edge features [E, edge_feature_count] from the state z [N, D] in SI units
        (positions q, velocities v) and the reference positions X [N, 3]."""
        src, dst = edge_index[0], edge_index[1]
        dz = z.index_select(0, dst) - z.index_select(0, src)  # [E, D], z_i - z_j
        dx = ref_pos.index_select(0, dst) - ref_pos.index_select(0, src)
        dv = dz[:, self.v_col: self.v_col + 3] if self.velocity_edges else dz[:, :0]
        raw = raw_edge_features(dz[:, :3], dx, dv, self.reference_edges, self.velocity_edges)
        return (raw - self.edge_mean) / self.edge_std

    def inv_degree(self, n: int, edge_index: Tensor, like: Tensor) -> Tensor:
        deg = torch.zeros(n, 1, dtype=like.dtype, device=like.device)
        deg = deg.index_add(0, edge_index[1], torch.ones(edge_index.shape[1], 1, dtype=like.dtype,
                                                         device=like.device))
        return 1.0 / deg.clamp(min=1.0)

    # --- network --------------------------------------------------------------------------
    def decode(self, zn: Tensor, fn: Tensor, edge_index: Tensor, node_type: Tensor,
               ref_pos: Tensor) -> Tuple[Tensor, Tensor]:
        """Raw decoder outputs for normalised state zn [N, D] and force fn [N, 3]: per node
        [N, n_out] (l, E [, m, S]) and per directed edge [E, D*D] (the Poisson coupling blocks A_e;
        [E, 0] without ``edge_operators``)."""
        z = zn * self.z_std + self.z_mean  # back in SI units (positions only enter as differences)
        onehot = torch.nn.functional.one_hot(node_type, 3).to(zn.dtype)
        h = self.node_encoder(torch.cat([zn[:, 3:], onehot, fn], 1))
        e = self.edge_encoder(self.edge_features(z, ref_pos, edge_index))
        inv_deg = self.inv_degree(zn.shape[0], edge_index, zn)
        for _ in range(self.repeats):
            for block in self.blocks:
                h, e = block(h, e, edge_index, inv_deg)
        coupling = e[:, :0]
        for edge_decoder in self.edge_decoders:
            coupling = edge_decoder(e)                                          # [E, D*D]
        return self.decoder(h), coupling

    def balance(self) -> Tensor:
        """c = sqrt(dzdt_std / z_std) [D] [1/sqrt(s)]: w = zn / c are the coordinates in which L and M
        act (ones for ``balanced=False``)."""
        if self.balanced:
            return torch.sqrt(self.dzdt_std / self.z_std)
        return torch.ones_like(self.z_std)

    @torch.jit.export
    def imposed_entries(self, node_type: Tensor) -> Tensor:
        """[N, D] bool: the state entries imposed rather than predicted (q, v of clamped nodes)."""
        return (node_type == 1).unsqueeze(1) & self.imposed_columns.unsqueeze(0)

    def free_entries(self, node_type: Tensor, like: Tensor) -> Tensor:
        """[N, D] 1.0 where the state entry evolves, 0.0 where it is imposed. L and M act on the free
        entries only (P L P stays skew, P M P PSD), so the constrained dynamics keep the energy
        and entropy identities and the imposed entries have zero rate."""
        return (~self.imposed_entries(node_type)).to(like.dtype)

    @torch.jit.export
    def rates(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
              create_graph: bool, through_state: bool = False) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """GENERIC rates. Returns (r [N, D] with dz/dt = r * dzdt_std, L [N, D, D], M [N, D, D],
        dE/dw [N, D], dS/dw [N, D], degeneracy loss (0-dim)), w the balanced coordinates (module
        docstring). M and dS/dw are zero for Hamiltonian models. With ``edge_operators`` L is the
        node (diagonal) part of the Poisson operator; the edge coupling (``poisson_apply``) acts
        besides it and enters the rates and the degeneracy loss. With ``through_state`` (and
        ``create_graph``) the rates stay differentiable in a z that carries a graph, e.g. the
        model's own previous step in a training window (``train.window_steps``); else z is cut off."""
        D = self.dim
        zn = (z - self.z_mean) / self.z_std
        if not (through_state and create_graph and zn.requires_grad):
            zn = zn.detach().requires_grad_(True)
        fn = (f - self.f_mean) / self.f_std
        out, coupling = self.decode(zn, fn, edge_index, node_type, ref_pos)
        n = zn.shape[0]
        c = self.balance()                                     # [D]; d/dw = c * d/dzn
        free = self.free_entries(node_type, zn)                # [N, D]; 0 where q, v are imposed
        L = skew(out[:, : D * D].reshape(n, D, D))
        A = coupling.reshape(coupling.shape[0], D, D) if self.edge_operators else L[:0]  # [E, D, D]
        energy = out[:, D * D].sum()
        if self.hamiltonian:
            grads = torch.autograd.grad([energy], [zn], create_graph=create_graph)
            g_e_opt = grads[0]
            assert g_e_opt is not None
            g_e = g_e_opt * c * free
            g_s = torch.zeros_like(g_e)
            M = torch.zeros_like(L)
            dwdt = poisson_apply(L, A, edge_index, g_e)
            deg = torch.zeros((), dtype=z.dtype, device=z.device)
        else:
            k = D * D + 1
            M = psd(out[:, k: k + D * D].reshape(n, D, D))
            entropy = out[:, k + D * D].sum()
            g_e_opt = torch.autograd.grad([energy], [zn], create_graph=create_graph, retain_graph=True)[0]
            g_s_opt = torch.autograd.grad([entropy], [zn], create_graph=create_graph)[0]
            assert g_e_opt is not None
            assert g_s_opt is not None
            g_e, g_s = g_e_opt * c * free, g_s_opt * c * free
            dwdt = poisson_apply(L, A, edge_index, g_e) + torch.bmm(M, g_s.unsqueeze(-1)).squeeze(-1)
            deg = degeneracy_loss(L, M, g_e, g_s, A, edge_index)
        if self.use_port:
            dwdt = dwdt + self.port(fn)
        dwdt = dwdt * free
        # dz/dt = z_std * dzn/dt = z_std * c * dw/dt = dzdt_std * (dw/dt) / c   (c^2 = dzdt_std / z_std)
        return dwdt / c, L, M, g_e, g_s, deg

    @torch.jit.export
    def impose(self, z: Tensor, node_type: Tensor, ref_pos: Tensor) -> Tensor:
        """Clamped nodes: q = reference position X, v = 0. z [N, D]."""
        fixed = torch.cat([ref_pos, torch.zeros(z.shape[0], self.dim - 3, dtype=z.dtype, device=z.device)], 1)
        return torch.where(self.imposed_entries(node_type), fixed, z)

    @torch.jit.export
    def rate_state(self, z: Tensor, z_next: Tensor) -> Tensor:
        """The state at which the integrator evaluates the rate of the step z -> z_next (training:
        both known): z for Euler, (z + z_next) / 2 for the midpoint rule. [N, D]"""
        if self.integrator == "midpoint":
            return 0.5 * (z + z_next)
        return z

    @torch.jit.export
    def step(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
             dt: Tensor) -> Tensor:
        """One step z_n -> z_{n+1} [N, D] in SI units, driven by the force f [N, 3] at t_{n+1}
        (``integrator``: euler, or midpoint by fixed-point sweeps from the Euler predictor). With
        mirror frames (``model.mirror_average``) the mean over the mesh's G symmetries g of
        g⁻¹ step(g z, g f): exactly equivariant, the mirror image of a motion steps as its image."""
        if self.n_frames > 0:
            return self.mirrored_step(z, f, edge_index, node_type, ref_pos, dt)
        return self.plain_step(z, f, edge_index, node_type, ref_pos, dt)

    def mirrored_step(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                      dt: Tensor) -> Tensor:
        """``step`` averaged over the mirror frames, the G images stepped as one batch
        (``frame_images``, then ``frame_mean``). z [B N, D] may hold B copies of the N-node mesh (a
        batch of states, as ``one_step_errors`` steps them)."""
        zg, fg, edges, types, pos = self.frame_images(z, f, edge_index, node_type, ref_pos)
        return self.frame_mean(self.plain_step(zg, fg, edges, types, pos, dt), node_type, ref_pos)

    @torch.jit.export
    def frame_images(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor,
                     ref_pos: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The state z [B N, D] (B copies of the N-node mesh) and the load f [B N, 3] seen in each of
        the G mirror frames, as one batch of G B meshes: (z' [G B N, D], f' [G B N, 3], edges
        [2, G B E], node types [G B N], reference positions [G B N, 3] [m]). A frame maps node
        source[k] to node k: z'[k] = A z[source[k]] + b (R on q, v and voigt(R σ Rᵀ) on the
        stresses; b = (I - R) c on q [m]), f'[k] = R f[source[k]]; the mesh, its node types and
        reference positions map onto themselves."""
        G, N, D = self.n_frames, self.frame_source.shape[1], self.dim
        B = z.shape[0] // N
        if B * N != z.shape[0]:
            raise ValueError("frame_images: the state's rows are not whole copies of the mesh")
        src = self.frame_source.reshape(-1)
        zg = z.reshape(B, N, D).index_select(1, src).reshape(B, G, N, D).transpose(0, 1)         # [G, B, N, D]
        zg = torch.matmul(zg, self.frame_matrix.transpose(1, 2).unsqueeze(1)) + self.frame_shift.view(G, 1, 1, D)
        fg = f.reshape(B, N, 3).index_select(1, src).reshape(B, G, N, 3).transpose(0, 1)         # [G, B, N, 3]
        rotation = self.frame_matrix[:, :3, :3]                          # [G, 3, 3]: R, the block acting on q
        fg = torch.matmul(fg, rotation.transpose(1, 2).unsqueeze(1))
        offsets = (torch.arange(G, device=z.device) * (B * N)).view(G, 1, 1)
        edges = (edge_index.unsqueeze(0) + offsets).transpose(0, 1).reshape(2, -1)              # [2, G B E]
        return (zg.reshape(G * B * N, D), fg.reshape(G * B * N, 3), edges, node_type.repeat(G),
                ref_pos.repeat(G, 1))

    @torch.jit.export
    def frame_mean(self, images: Tensor, node_type: Tensor, ref_pos: Tensor) -> Tensor:
        """The mean over the G mirror frames of states seen in them, images [G B N, D] in
        ``frame_images``' order, each mapped back to the mesh's own frame: [B N, D], the clamped
        entries imposed (node_type [B N], ref_pos [B N, 3] [m])."""
        G, N, D = self.n_frames, self.frame_source.shape[1], self.dim
        B = images.shape[0] // (G * N)
        nxt = images.reshape(G, B, N, D)
        back = torch.matmul(nxt - self.frame_shift.view(G, 1, 1, D), self.frame_inverse.transpose(1, 2).unsqueeze(1))
        back = torch.gather(back, 2, self.frame_back.view(G, 1, N, 1).expand(G, B, N, D))  # original node order
        return self.impose(back.mean(0).reshape(B * N, D), node_type, ref_pos)

    def plain_step(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                   dt: Tensor) -> Tensor:
        """``step`` in the mesh's own frame."""
        z0 = z.detach()
        rate = self.rates(z0, f, edge_index, node_type, ref_pos, False, False)[0].detach()
        z_next = self.advance(z0, rate, dt, node_type, ref_pos)
        if self.integrator == "midpoint":
            for _ in range(self.implicit_iterations):
                rate = self.rates(self.rate_state(z0, z_next), f, edge_index, node_type, ref_pos, False, False)[0].detach()
                z_next = self.advance(z0, rate, dt, node_type, ref_pos)
        return z_next

    def advance(self, z: Tensor, rate: Tensor, dt: Tensor, node_type: Tensor, ref_pos: Tensor) -> Tensor:
        """z_{n+1} = z_n + dt * rate * dzdt_std [N, D] (rate as ``rates`` gives it), the clamped
        entries imposed. With ``exact_kinematics`` the positions follow from the velocities by the
        trapezoidal rule instead, q_{n+1} = q_n + dt (v_n + v_{n+1}) / 2 [m] (Newmark with gamma =
        1/2, the FE data's own rule): dq/dt = v is an identity, not something to learn."""
        z_next = z + dt * rate * self.dzdt_std
        if self.exact_kinematics:
            v0 = z[:, self.v_col: self.v_col + 3]
            v1 = z_next[:, self.v_col: self.v_col + 3]
            z_next = torch.cat([z[:, :3] + 0.5 * dt * (v0 + v1), z_next[:, 3:]], 1)
        return self.impose(z_next, node_type, ref_pos)

    def reported_step(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                      dt: Tensor) -> Tensor:
        """``step``, then ``report`` of the new state under the load f [N, 3]: the state a rollout
        reports, as the benchmarks time it [N, D]."""
        return self.report(self.step(z, f, edge_index, node_type, ref_pos, dt), ref_pos, f)

    @torch.jit.export
    def report(self, z: Tensor, ref_pos: Tensor, f: Optional[Tensor] = None) -> Tensor:
        """The state z [N, D] as the model reports it: with a stress readout its stress read off the
        positions (``read_stress``; the load f [N, 3] of that state, None: unloaded), else z."""
        if self.use_readout:
            return self.read_stress(z, ref_pos, f)
        return z

    @torch.jit.export
    def read_stress(self, z: Tensor, ref_pos: Tensor, f: Optional[Tensor] = None) -> Tensor:
        """z [N, D] with its stress columns read off its positions by the stress readout,
        σ = readout(q - X, f) (``model.stress_readout``; the applied load f [N, 3] (N) of that state
        enters with ``model.stress_readout_load``, None: unloaded): the stress a rollout reports. The
        state the network steps keeps its own σ (fed back, the readout's made v worse: TIGNN beam,
        session 52)."""
        sigma = self.readout(z[:, :3] - ref_pos, f)                           # [N, S]
        return torch.cat([z[:, :self.readout_first], sigma, z[:, self.readout_end:]], 1)

    @torch.jit.export
    def energy_power(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor,
                     ref_pos: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """(E, dE/dt, port power) at state z [N, D] under load f [N, 3], all 0-dim: the learned
        energy, its rate along the model's own dynamics dE/dz . dz/dt, and the part of that rate
        the port term W f supplies. Without dissipation dE/dt equals the port power to round-off;
        an integrator's energy error is E_{n+1} - E_n minus the port work dt * power. With
        ``exact_kinematics`` the dynamics take dq/dt = v, and dE/dt includes dE/dq . (v - the
        network's dq/dt), which the learned operators do not cancel."""
        D = self.dim
        zn = ((z - self.z_mean) / self.z_std).detach().requires_grad_(True)
        fn = (f - self.f_mean) / self.f_std
        out = self.decode(zn, fn, edge_index, node_type, ref_pos)[0]
        energy = out[:, D * D].sum()
        g = torch.autograd.grad([energy], [zn])[0]
        assert g is not None
        rate = self.rates(z, f, edge_index, node_type, ref_pos, False, False)[0].detach()
        if self.exact_kinematics:                               # dq/dt = v on the free nodes
            v = z[:, self.v_col: self.v_col + 3] / self.dzdt_std[:3]
            rate = torch.cat([v * self.free_entries(node_type, z)[:, :3], rate[:, 3:]], 1)
        dzn_dt_scale = self.dzdt_std / self.z_std               # dzn/dt = r * dzdt_std / z_std
        de_dt = (g * rate * dzn_dt_scale).sum()
        power = torch.zeros_like(de_dt)
        if self.use_port:
            power = (g * self.port(fn) * self.free_entries(node_type, z) / self.balance() * dzn_dt_scale).sum()
        return energy.detach(), de_dt.detach(), power.detach()

    @torch.jit.export
    def energy_entropy(self, z: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                       f: Tensor) -> Tuple[Tensor, Tensor]:
        """Learned total energy E and entropy S (0-dim; S = 0 for Hamiltonian models)."""
        D = self.dim
        zn = (z - self.z_mean) / self.z_std
        fn = (f - self.f_mean) / self.f_std
        out = self.decode(zn, fn, edge_index, node_type, ref_pos)[0]
        energy = out[:, D * D].sum()
        if self.hamiltonian:
            return energy, torch.zeros_like(energy)
        return energy, out[:, 2 * D * D + 1].sum()


def hyperparameters(cfg_model, dim: int, velocity_columns: List[int], hamiltonian: bool) -> dict:
    """The constructor arguments of TIGNN from the ``model`` config group (stored in checkpoints)."""
    from omegaconf import OmegaConf

    sel = lambda k, d: OmegaConf.select(cfg_model, k, default=d)  # noqa: E731
    _choice("aggregation", str(sel("aggregation", "sum")), AGGREGATIONS)
    _choice("integrator", str(sel("integrator", "euler")), INTEGRATORS)
    return {
        "dim": int(dim),
        "velocity_columns": [int(c) for c in velocity_columns],
        "hidden": int(sel("hidden", 64)),
        "mlp_layers": int(sel("mlp_layers", 2)),
        "message_passing": int(sel("message_passing", 4)),
        "shared_weights": bool(sel("shared_weights", False)),
        "aggregation": str(sel("aggregation", "sum")),
        "hamiltonian": bool(hamiltonian),
        "port": bool(sel("port", True)),
        "reference_edges": bool(sel("reference_edges", True)),
        "balanced": True,
        "integrator": str(sel("integrator", "euler")),
        "implicit_iterations": int(sel("implicit_iterations", 3)),
        "velocity_edges": bool(sel("velocity_edges", True)) and len(velocity_columns) == 3,
        "edge_operators": bool(sel("edge_operators", False)),
        "exact_kinematics": _exact_kinematics(str(sel("kinematics", "learned")), velocity_columns, hamiltonian),
    }


def _exact_kinematics(kinematics: str, velocity_columns: List[int], hamiltonian: bool,
                      group: str = "model") -> bool:
    """``model.kinematics``: exact (q from v by the trapezoidal rule; needs v in the state), learned
    (the network's dq/dt), auto (exact in dissipative scenes with inertia; learned in Hamiltonian
    ones, whose dynamics then conserve the learned energy exactly). ``group`` names the config
    group in errors (``rollout`` when a trained model is stepped otherwise)."""
    _choice("kinematics", kinematics, ("auto", "exact", "learned"), group)
    if kinematics == "exact" and len(velocity_columns) != 3:
        raise ConfigError(f"{group}.kinematics = exact needs the velocity v in the state (effect 'inertia')")
    if kinematics == "auto":
        return len(velocity_columns) == 3 and not hamiltonian
    return kinematics == "exact"


def _choice(key: str, value: str, allowed: Tuple[str, ...], group: str = "model") -> None:
    """A one-line ConfigError naming ``<group>.<key>`` unless value is one of ``allowed``."""
    if value not in allowed:
        raise ConfigError(f"{group}.{key} = '{value}', expected " + " | ".join(allowed))


def step_settings(hparams: dict) -> dict:
    """How a model with these hyperparameters steps: {"integrator", "implicit_iterations",
    "kinematics": "exact" | "learned"}, with the constructor's defaults where a checkpoint of an
    earlier version lacks a key (the exported file's ``step`` metadata)."""
    defaults = inspect.signature(TIGNN.__init__).parameters
    get = lambda k: hparams.get(k, defaults[k].default)  # noqa: E731
    return {"integrator": str(get("integrator")), "implicit_iterations": int(get("implicit_iterations")),
            "kinematics": "exact" if get("exact_kinematics") else "learned"}


def stepping(hparams: dict, integrator=None, implicit_iterations=None, kinematics=None,
             group: str = "rollout") -> dict:
    """The hyperparameters ``hparams`` with another time step for the same learned dz/dt: the
    integrator, its fixed-point sweeps, the kinematics (None keeps the trained setting; errors
    name ``<group>.<key>``). What the network learned is unchanged, so a trained model may be
    stepped either way: the midpoint rule costs 1 + implicit_iterations network calls a step."""
    out = dict(hparams)
    if integrator is not None:
        _choice("integrator", str(integrator), INTEGRATORS, group)
        out["integrator"] = str(integrator)
    if implicit_iterations is not None:
        try:
            n = int(implicit_iterations)
        except (TypeError, ValueError):
            n = 0
        if n < 1 or str(n) != str(implicit_iterations).strip():
            raise ConfigError(f"{group}.implicit_iterations = {implicit_iterations!r}, expected an integer >= 1")
        out["implicit_iterations"] = n
    if kinematics is not None:
        out["exact_kinematics"] = _exact_kinematics(str(kinematics), list(hparams["velocity_columns"]),
                                                    bool(hparams["hamiltonian"]), group)
    return out


def grown_blocks(src: dict, here: dict) -> int:
    """How many processor blocks a checkpoint of hyperparameters ``src`` has where ``here`` is the
    same network with more blocks after them (``message_passing`` larger here, weights unshared on
    both sides; the rest is the caller's to compare): then ``load_grown`` loads it. 0 otherwise."""
    a, b = int(src.get("message_passing", 4)), int(here.get("message_passing", 4))
    unshared = not src.get("shared_weights", False) and not here.get("shared_weights", False)
    return a if b > a and unshared else 0


def load_grown(model: nn.Module, state: Dict[str, Tensor], src_blocks: int) -> None:
    """Load a checkpoint's weights ``state`` with ``src_blocks`` processor blocks into ``model`` (a
    TIGNN, or a module holding one), whose network has more: the checkpoint's blocks come first,
    and each new one starts as the identity, its edge and node MLPs' closing LayerNorm at zero scale
    and shift, so that both residual updates add nothing and the grown model computes exactly what
    the checkpoint's did. Training then opens the new blocks (the LayerNorm's scale and shift get
    gradients at once; the block's other weights as soon as they are nonzero)."""
    missing, unexpected = model.load_state_dict(state, strict=False)
    new_block = re.compile(r"(^|\.)blocks\.(\d+)\.")

    def added(key: str) -> bool:
        m = new_block.search(key)
        return m is not None and int(m.group(2)) >= src_blocks
    if unexpected or not all(added(k) for k in missing):
        raise ValueError(f"the checkpoint's weights do not fit this network grown from {src_blocks} blocks: "
                         f"unexpected {sorted(unexpected)[:3]}, missing {sorted(k for k in missing if not added(k))[:3]}")
    nets = [m for m in model.modules() if isinstance(m, TIGNN)]
    with torch.no_grad():
        for net in nets:
            for block in net.blocks[src_blocks:]:
                for mlp in (block.edge_mlp, block.node_mlp):
                    norm = mlp.net[-1]   # the closing LayerNorm: h + 0, e + 0
                    norm.weight.zero_()
                    norm.bias.zero_()


def build_model(hparams: dict, dtype: torch.dtype = torch.float32) -> TIGNN:
    """A fresh TIGNN on the default device (``train.device`` inside ``train``), its weights drawn
    on the CPU from torch's CPU generator: the same initial model on every device."""
    device = torch.get_default_device()
    with torch.device("cpu"):
        model = TIGNN(**hparams).to(dtype)
    return model.to(device)


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def readout_weight_count(model: nn.Module) -> int:
    """The fitted weights of the model's stress readout (``model.stress_readout``; 0 without one):
    buffers, not parameters, but learned from the data, so they count beside ``parameter_count``."""
    return model.readout.fitted_weights() if getattr(model, "use_readout", False) else 0
