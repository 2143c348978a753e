"""``model.prior = linear``: the data's own Newmark step of the solid linearised at rest, with the
nonlinear remainders learned by the graph network.

The FE solid's step, with its internal force split as f_int(u) = K u − G(u) and its stress as
σ = Σ u + H (``thermognn.train.prior``), is over the free DOFs::

    M a1 + αM M v1 + c K (u1 − u0) + K u1 = f1 + (1 + c) G1 − c G0,    c = βK / dt      [N]
    u1 = u0 + dt v0 + dt² ((1/2 − β) a0 + β a1),   v1 = v0 + dt ((1 − γ) a0 + γ a1)
    σ1 = Σ u1 + H1                                                                       [Pa]

The network's GENERIC rates at a state are read as the remainders: its v columns as G [N] (at
the free DOFs), its σ columns as H [Pa], each times ``dzdt_std`` (set to the remainders' RMS in
the training data). With ``positions_only`` the network sees the positions alone (G and H of a
hyperelastic solid are functions of the displacement); with ``correction`` (``model.prior_inputs``)
it sees the state with the step's correction from its predictor, w = (u1 − u0)/Δt − v0, in place
of the velocity (``correction_view``: what a fixed Newton budget misses depends on it). With ``order`` 2 (``model.prior_order``,
the ``model=linear_prior`` preset's) G and H are the network's second difference along the ray
from the unloaded rest state (``network_remainders``), so they start at second order in the load
as the true ones do, and gentle loads give the linearised FE model whatever the weights. A step: the linear step with the last G
predicts the state; the network gives G1, H1 there (``sweeps`` times, each at the latest
prediction); the linear step with them gives the state. With G = H = 0 this is the linearised
FE model that ``evaluate`` reports; with the exact remainders it is the FE step itself (test in
``tests/test_fe_modes.py``), so the network only learns what the linear solid misses, and the
linear solve spreads a local correction over the body.

Besides the physical state z [N, D] (q, v, σ), the step carries Newmark's acceleration a and the
last remainder G: the *carried state* is z with a [m/s²] and G [N] appended as nodal columns,
[N, D + 6] (zero at clamped DOFs). With ``model.prior_relax`` (a viscous scene) the prior relaxes
as the FE does (``thermognn.train.prior``), and the carried state also holds its Prony internal
variables, 9 nodal columns per term (``pack_internal``; the corotated prior's per-cell variables,
6 per cell and term, packed row-major into as many nodal columns as they fill, ``prony_cells_i``).
``carry`` makes it from a physical state
(a from the balance of forces there, as the FE starts; G from the network; the internal
variables as if the displacement were applied at once), ``step`` advances it, and the first D
columns are the physical state. The exported module steps the carried state, so ``serve`` keeps
a, G and the internal variables between ticks without knowing about them.

Training (:func:`train_linear_prior`, from ``thermognn train`` with ``model.prior=linear``) runs
in two phases (docs/accuracy.md, session 12: each alone fails): ``train.epochs`` epochs of a
one-step regression of the network's outputs on the exact remainders of the training
trajectories (``NewmarkPrior.remainders``; for the law prior, whose exact remainders are
round-off, ``train.fit_target=budget`` regresses on what its Newton budget leaves instead,
``budget_remainders``), then ``train.rollout_epochs`` epochs on rollouts (whole, or windows of
``train.rollout_window`` steps), back-propagated through the linear solves; optionally a third,
``train.whole_epochs`` epochs on whole trajectories from rest at a restarted rate.
``train.rollout_scale`` sets what each rollout group's error is relative to (the training
data's RMS, or its own trajectory's). Torch only; dense operators (meshes of a few thousand
free DOFs).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from omegaconf import OmegaConf
from torch import Tensor, nn

from thermognn.core.errors import ConfigError, DataError

from .device import cpu_randn
from .model import TIGNN, grown_blocks, load_grown
from .prior import DIVERGED, CorotatedNewmarkPrior, NewmarkPrior, stop_if_run_away

#: the state layout the prior steps: positions, velocities and stresses, nothing else
LAYOUT = ["q", "v", "sigma"]
#: the carried state's extra nodal columns after the physical ones: Newmark's acceleration, G
CARRIED = (("a", 3), ("G", 3))
#: ``model.prior_cut_loads``: a law prior's cut step holds its end load in its sub-steps (end) or
#: loads them linearly between its start and end loads (linear)
CUT_LOADS = ("end", "linear")
#: ... and with linear, the carried state's last columns: the load the last step ended under
CUT_LOADS_CARRIED = ("f", 3)
#: PRIORS: model.prior values
PRIORS = ("none", "linear")
#: model.prior_inputs values: what the network sees of a state (``LinearPriorModel``): the
#: positions alone; the whole state; the state with the step's correction from its predictor in
#: place of the velocity (``LinearPriorModel.correction_view``)
PRIOR_INPUTS = ("positions", "state", "correction")
#: model.prior_material values: the law prior's law is the scene's (data) or fitted to the data (learned)
LAW_MATERIALS = ("data", "learned")
#: model.prior_order values: the order at which the learned remainders start (LinearPriorModel.network_remainders)
ORDERS = (1, 2)


class LinearPriorModel(nn.Module):
    """The linearised FE Newmark step with the network's remainders (module docstring).

    Physical states z [B, N, D] in float64 (the prior's dtype); the network runs in its own dtype.
    Graph tensors (edge_index, node_type, ref_pos) are those of B disjoint copies of the mesh."""

    def __init__(self, net: TIGNN, prior: NewmarkPrior, reference_positions: Tensor,
                 positions_only: bool = True, sweeps: int = 1, order: int = 1, correction: bool = False,
                 learned: bool = True, cut_loads: str = "end") -> None:
        super().__init__()
        if net.dim != 12:
            raise ValueError(f"linear prior: state dimension {net.dim}, expected 12 (q, v, sigma)")
        if order not in ORDERS:
            raise ValueError(f"linear prior: order {order}, expected one of {ORDERS}")
        self.net = net
        self.prior = prior
        self.dim = int(net.dim)
        self.sweeps = int(sweeps)
        self.order = int(order)
        self.positions_only = bool(positions_only)
        # ``model.prior_inputs = correction``: the network's v inputs are the step's correction from
        # its predictor (``correction_view``), not the velocity
        self.correction = bool(correction) and not self.positions_only
        # ``rollout.remainders = zero``: G = H = 0 and the network not evaluated (the prior alone)
        self.learned = bool(learned)
        # ``model.prior_cut_loads = linear``: a law prior's cut step loads its sub-steps linearly
        # between the step's start and end loads (``HyperelasticNewmarkPrior.cut_step``), and the
        # carried state keeps the last step's load (``pack``: 3 more columns, CUT_LOADS_CARRIED)
        if cut_loads not in CUT_LOADS:
            raise ValueError(f"linear prior: cut_loads {cut_loads!r}, expected one of {CUT_LOADS}")
        self.cut_loads_linear = cut_loads == "linear"
        self.register_buffer("reference_positions", reference_positions.to(torch.float64).contiguous(),
                             persistent=False)                                       # [N, 3] m
        seen = torch.ones(self.dim, dtype=net.z_mean.dtype)
        if positions_only:
            seen[3:] = 0.0
        self.register_buffer("seen", seen, persistent=False)                        # [D] network inputs
        # the network's remainders at the unloaded reference state, subtracted once ``anchor`` has
        # set them: the true G and H vanish there by definition (G(0) = K 0 - f_int(0) = 0)
        n = int(prior.free_index.numel())
        self.register_buffer("rest_G", torch.zeros(1, n, dtype=torch.float64), persistent=False)    # [1, n] N
        self.register_buffer("rest_H", torch.zeros(1, reference_positions.shape[0], 6, dtype=torch.float64),
                             persistent=False)                                                     # [1, N, 6] Pa
        # order 2: the network's rates r(z₀, 0) at the rest state, kept by ``anchor`` so that a step
        # without gradients evaluates the network on 2B copies of the mesh, not 2B + 1
        self.register_buffer("rest_rates", torch.zeros(reference_positions.shape[0], self.dim,
                                                       dtype=net.z_mean.dtype), persistent=False)   # [N, D]
        self.anchored = False

    def rest_state(self) -> Tensor:
        """The unloaded reference state z₀ [1, N, D] (float64): q = X, v = 0, σ = 0."""
        X = self.reference_positions
        return torch.cat([X, torch.zeros(X.shape[0], self.dim - 3, dtype=X.dtype, device=X.device)], 1).unsqueeze(0)

    def network_remainders(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                           create_graph: bool, rest_rates: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """The remainders in the network's units (its v columns G / dzdt_std, its σ columns
        H / dzdt_std) at states z [B, N, D] under the loads f [B, N, 3] [N], and the network's
        degeneracy loss (0-dim): (r [B, N, D] in the network's dtype, degeneracy).

        ``order`` 1: the network's rates r(z, f). ``order`` 2: their second difference along the
        ray from the unloaded rest state z₀ (q = X, v = σ = 0, f = 0) through (z, f),
        2 [r(z, f) − 2 r(z½, f/2) + r(z₀, 0)] with z½ = z₀ + (z − z₀)/2: for any weights its
        constant and linear parts in (z − z₀, f) cancel (a quadratic r is returned unchanged), as
        the true G = K u − f_int(u) and H = σ − Σ u start at second order in u. So under small loads
        the model is the linearised FE model, with an error O(load²); each call evaluates the
        network on 2B + 1 copies of the mesh, or 2B given ``rest_rates`` r(z₀, 0) [N, D] (what
        ``rest_rates_once`` gives a rollout, once for all its steps) or once anchored and without
        gradients (then ``anchor`` kept it). The degeneracy loss is that of the 2B loaded copies, so that
        it weighs every sample alike whatever the batch."""
        B, N, D = z.shape[0], z.shape[1], z.shape[2]
        dtype = self.net.z_mean.dtype
        if self.order == 1:
            out = self.net.rates((z.to(dtype) * self.seen).reshape(B * N, D), f.to(dtype).reshape(B * N, 3),
                                 edge_index, node_type, ref_pos, create_graph, False)
            return out[0].reshape(B, N, D), out[5]
        rest = self.rest_state()                                          # [1, N, D]
        half = rest + 0.5 * (z.to(torch.float64) - rest)                  # z½ formed in float64: [B, N, D]
        zs = torch.cat([z.to(dtype), half.to(dtype)], 0)                                          # [2B, N, D]
        fs = torch.cat([f.to(dtype), 0.5 * f.to(dtype)], 0)
        out = self.net.rates((zs * self.seen).reshape(2 * B * N, D), fs.reshape(2 * B * N, 3),
                             torch.cat([edge_index, edge_index + B * N], 1), torch.cat([node_type, node_type]),
                             torch.cat([ref_pos, ref_pos]), create_graph, False)
        if rest_rates is not None:
            r0 = rest_rates                                               # [N, D]
        elif self.anchored and not create_graph:
            r0 = self.rest_rates                                          # kept by ``anchor``: [N, D]
        else:
            r0 = self.rest_network_rates(B, edge_index, node_type, ref_pos, create_graph)
        r = out[0].reshape(2 * B, N, D)
        return 2.0 * (r[:B] - 2.0 * r[B:] + r0.unsqueeze(0)), out[5]                             # [B, N, D]

    def rest_network_rates(self, B: int, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                           create_graph: bool) -> Tensor:
        """The network's rates r(z₀, 0) [N, D] (its dtype) at the unloaded rest state, on the first
        of the B copies of the mesh that the graph tensors hold."""
        N, D = self.reference_positions.shape[0], self.dim
        E = edge_index.shape[1] // B                                      # edges of one copy (copies in order)
        dtype = self.net.z_mean.dtype
        return self.net.rates((self.rest_state().to(dtype) * self.seen).reshape(N, D),
                              torch.zeros(N, 3, dtype=dtype, device=self.seen.device),
                              edge_index[:, :E], node_type[:N], ref_pos[:N], create_graph, False)[0]

    def rest_rates_once(self, B: int, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                        create_graph: bool) -> Optional[Tensor]:
        """r(z₀, 0) [N, D] for every step of one rollout of B bodies (graph tensors of B copies),
        evaluated once: the weights do not change within it. None where the steps need none
        (order 1) or take the one ``anchor`` kept (anchored, without gradients)."""
        if self.order == 1 or (self.anchored and not create_graph):
            return None
        return self.rest_network_rates(B, edge_index, node_type, ref_pos, create_graph)

    def remainders(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                   create_graph: bool, rest_rates: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """The network's remainders at states z [B, N, D] under the loads f [B, N, 3] [N]:
        G [B, n] N over the free DOFs and H [B, N, 6] Pa (float64); ``rest_rates`` as for
        ``network_remainders``. Zero, without evaluating the network, where the model steps
        its prior alone (``learned`` false, ``rollout.remainders = zero``)."""
        if not self.learned:
            B = z.shape[0]
            return (torch.zeros(B, self.rest_G.shape[1], dtype=torch.float64, device=z.device),
                    torch.zeros(B, self.rest_H.shape[1], 6, dtype=torch.float64, device=z.device))
        r = self.network_remainders(z, f, edge_index, node_type, ref_pos, create_graph, rest_rates)[0]
        if not create_graph:
            r = r.detach()
        r = r.to(torch.float64) * self.net.dzdt_std.to(torch.float64)              # [B, N, D] SI
        G, H = self.prior.gather(r[:, :, 3:6]), r[:, :, 6:12]
        if self.anchored:
            return G - self.rest_G, H - self.rest_H
        return G, H

    @torch.jit.ignore
    def anchor(self, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor) -> None:
        """Set the remainders to subtract: the network's at the unloaded reference state (q = X,
        v = 0, σ = 0, no load), with the current weights, on one copy of the mesh (its graph
        tensors). Trained models are stepped anchored (``model_from_checkpoint``, validation);
        the training losses use the raw outputs. Block, session 13: per snapshot σ 2.34 % ->
        1.45 %, v 2.36 % -> 1.85 % with the same weights (docs/accuracy.md)."""
        rest = self.rest_state()
        self.anchored = False
        with torch.enable_grad():
            r0 = self.rest_rates_once(1, edge_index, node_type, ref_pos, False)             # order 2: [N, D]
            if r0 is not None:
                self.rest_rates.copy_(r0.detach())
            G, H = self.remainders(rest, torch.zeros_like(rest[:, :, 0:3]), edge_index, node_type, ref_pos, False, r0)
        self.rest_G.copy_(G.detach())
        self.rest_H.copy_(H.detach())
        self.anchored = True

    def state(self, u: Tensor, v: Tensor, H: Tensor, h: Tensor) -> Tensor:
        """Physical states [B, N, D] (q = X + u, v, σ = σ_lin + H) from free-DOF u, v [B, n] and
        the prior's Prony internal variables h [B, T, n + 6N] (σ_lin = Σ u unless it relaxes)."""
        return self.prior.physical_state(self.reference_positions, u, v, H, h)

    def begin(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
              create_graph: bool, rest_rates: Optional[Tensor] = None
              ) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """(u, v, a, G, H, h) at the physical states z [B, N, D] under f [B, N, 3]: a from the
        balance of forces there, G and H from the network, the prior's internal variables h as if
        the displacement were applied at once (``NewmarkPrior.internal_variables``)."""
        self.prior.forget()             # a rollout's steps do not depend on what was stepped before it
        z, f = z.to(torch.float64), f.to(torch.float64)
        u, v, H = self.unpack(z)
        seen = self.with_correction(z, torch.zeros_like(u)) if self.correction else z   # no step behind a start
        G, _ = self.remainders(seen, f, edge_index, node_type, ref_pos, create_graph, rest_rates)
        a = self.prior.initial_acceleration(u, v, self.prior.gather(f), G)
        return u, v, a, G, H, self.prior.internal_variables(u)

    def correction_view(self, z1: Tensor, u0: Tensor, v0: Tensor, u1: Tensor) -> Tensor:
        """What the network sees of a step's end with ``model.prior_inputs = correction``: the
        physical state z1 [B, N, D] with its v columns replaced by the step's correction from its
        predictor, w = (u1 − u0) / Δt − v0 [m/s] (free-DOF u0, v0, u1 [B, n]; zero at clamped
        DOFs). The law prior's Newton iterations start from the predictor u0 + Δt v0, so what a
        fixed budget misses is a function of where the step ends and how far it moved from there,
        u1 − (u0 + Δt v0) = Δt w, which the velocity at the end does not give (the data's Newmark
        rule: Δt w = Δt² ((1/2 − β) a0 + β a1))."""
        return self.with_correction(z1, (u1 - u0) / self.prior.dt - v0)

    def with_correction(self, z: Tensor, w: Tensor) -> Tensor:
        """States z [B, N, D] with their v columns replaced by the free-DOF corrections w [B, n]
        m/s (zero at clamped DOFs): what the network sees with ``correction``."""
        return torch.cat([z[:, :, 0:3], self.prior.scatter(w).to(z.dtype), z[:, :, 6:]], -1)

    def trajectory_inputs(self, z: Tensor) -> Tensor:
        """What the network sees at each state of one trajectory z [S, N, D] from its start (the
        one-step errors' carried G, the stress term's, and the fit's without ``correction``): z
        itself, or with ``correction`` its ``correction_view`` of the data's step that ended there
        (none at the start: w = 0); the fit's with ``correction`` are ``step_inputs``."""
        if not self.correction:
            return z
        x = z.to(torch.float64)
        u, v = self.prior.gather(x[:, :, 0:3] - self.reference_positions.unsqueeze(0)), self.prior.gather(x[:, :, 3:6])
        w = torch.zeros_like(u)                                                     # [S, n] m/s
        w[1:] = (u[1:] - u[:-1]) / self.prior.dt - v[:-1]
        return self.with_correction(z, w)

    @torch.jit.unused
    def step_inputs(self, z: Tensor, f: Tensor, G: Tensor) -> Tensor:
        """What the model's own step from each of a trajectory's true states shows the network
        (the fit's inputs with ``correction``): states [S, N, D], the first ``begin``'s view of
        z[0] (w = 0), then for s >= 1 the ``correction_view`` of the step's prediction from state
        s − 1 with that state's true remainders, as ``advance`` predicts with the last G. The
        data's own next state would show the network the converged correction instead of the
        budgeted step's, which is what the network sees when it steps. z [S, N, D] physical
        states under loads f [S, N, 3] N, G [S, N, 3] N the remainders the fit learns."""
        P = self.prior
        with torch.no_grad():
            x = z.to(torch.float64)
            h = self.trajectory_internal_variables(x)                               # [S, T, ...]
            u, v, H = self.unpack(x, h)
            a = self.accelerations(x, f)                                            # [S, n]
            g = P.gather(G.to(torch.float64))                                       # [S, n] N
            P.forget()                                          # the law prior's kept step start
            u1, v1, _a1, h1 = P.step(u[:-1], v[:-1], a[:-1], P.gather(f[1:].to(torch.float64)), g[:-1], g[:-1], h[:-1])
            P.forget()
            ends = self.correction_view(self.state(u1, v1, H[:-1], h1), u[:-1], v[:-1], u1)    # [S - 1, N, D]
        start = self.with_correction(x[:1], torch.zeros_like(u[:1]))                          # [1, N, D]
        return torch.cat([start, ends]).to(z.dtype)

    def unpack(self, z: Tensor, h: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor]:
        """(u, v [B, n], H [B, N, 6]) of float64 states z [B, N, D(+...)]: the inverse of ``state``
        with the internal variables h [B, T, n + 6N] (None: those of a start, where the relaxing
        prior's σ_lin is Σ u)."""
        U = z[:, :, 0:3] - self.reference_positions.unsqueeze(0)                    # [B, N, 3]
        u = self.prior.gather(U)
        H = z[:, :, 6:12] - self.prior.stress(U, None)
        if h is not None:
            H = H - self.prior.stress_relaxation(u, h)
        return u, self.prior.gather(z[:, :, 3:6]), H

    def trajectory_internal_variables(self, z: Tensor) -> Tensor:
        """The prior's internal variables h [S, T, n + 6N] along one trajectory of physical states
        z [S, N, D] (from an unloaded start, as generate's): what a step from a true state
        mid-way carries (one-step error, rollout windows)."""
        U = z[:, :, 0:3].to(torch.float64) - self.reference_positions.unsqueeze(0)        # [S, N, 3]
        return self.prior.internal_history(self.prior.gather(U))

    def pack_internal(self, h: Tensor) -> Tensor:
        """The prior's internal variables h [B, T, ...] -> nodal columns [B, N, C]
        (``NewmarkPrior.pack_internal``: 9 per Prony term; the corotated prior's per cell, packed)."""
        return self.prior.pack_internal(h)

    def unpack_internal(self, x: Tensor) -> Tensor:
        """Nodal columns [B, N, C] -> the prior's internal variables: the inverse of ``pack_internal``."""
        return self.prior.unpack_internal(x)

    def accelerations(self, z: Tensor, f: Tensor) -> Tensor:
        """The data's own Newmark accelerations a [S, n] m/s² along one trajectory of physical
        states z [S, N, D] under its loads f [S, N, 3] (``NewmarkPrior.accelerations``): what a
        step from a true state mid-way starts with (one-step error, rollout windows)."""
        p = self.prior
        U = z[:, :, 0:3].to(torch.float64) - self.reference_positions.unsqueeze(0)        # [S, N, 3]
        return p.accelerations(p.gather(U), p.gather(z[:, :, 3:6].to(torch.float64)), p.gather(f.to(torch.float64)))

    def pack(self, u: Tensor, v: Tensor, a: Tensor, G: Tensor, H: Tensor, h: Tensor, f: Tensor) -> Tensor:
        """The carried state [N, D + 6 + 9 T (+ 3)] of one body ([1, ...] inputs): ``state`` with a,
        G and the relaxing prior's internal variables (``pack_internal``; none unless it relaxes),
        and with ``cut_loads_linear`` the load f [1, N, 3] N the state is under."""
        parts = [self.state(u, v, H, h)[0], self.prior.scatter(a)[0], self.prior.scatter(G)[0],
                 self.pack_internal(h)[0]]                                         # [N, D], [N, 3], [N, 3], [N, 9 T]
        if self.cut_loads_linear:
            parts.append(f[0].to(torch.float64))
        return torch.cat(parts, -1)

    def carried_columns(self) -> List[Tuple[str, int]]:
        """(name, width) of the carried state's column groups after a and G, as ``pack`` lays them
        out: the prior's internal variables (``internal_columns``) and, with ``cut_loads_linear``,
        the last load (CUT_LOADS_CARRIED); for the exported ``state_layout`` (``carried_layout``)."""
        return list(self.prior.internal_columns()) + ([CUT_LOADS_CARRIED] if self.cut_loads_linear else [])

    def start_loads(self, f0: Optional[Tensor]) -> Optional[Tensor]:
        """A step's start loads f0 [B, N, 3] N as the prior's step takes them: free-DOF rows [B, n]
        with ``cut_loads_linear`` (a cut step's sub-steps loaded between f0 and the end loads),
        else None (the end loads held)."""
        if self.cut_loads_linear and f0 is not None:
            return self.prior.gather(f0.to(torch.float64))
        return None

    def advance(self, u: Tensor, v: Tensor, a: Tensor, G: Tensor, H: Tensor, h: Tensor, f1: Tensor,
                edge_index: Tensor, node_type: Tensor, ref_pos: Tensor, create_graph: bool,
                rest_rates: Optional[Tensor] = None, f0: Optional[Tensor] = None
                ) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """One step under the loads f1 [B, N, 3] at its end: predict with the last G, evaluate
        the network there (``sweeps`` times), step with its G1; f0 [B, N, 3], the loads at its
        start, load a cut step's sub-steps with ``cut_loads_linear`` (None: f1 held)."""
        f1 = f1.to(torch.float64)
        f1_rows = self.prior.gather(f1)
        f0_rows = self.start_loads(f0)
        G1 = G
        if self.learned:
            for _ in range(self.sweeps):
                u1, v1, _a1, h1 = self.prior.step(u, v, a, f1_rows, G, G1, h, f0_rows)
                z1 = self.state(u1, v1, H, h1)
                if self.correction:
                    z1 = self.correction_view(z1, u, v, u1)
                G1, H = self.remainders(z1, f1, edge_index, node_type, ref_pos, create_graph, rest_rates)
        elif self.sweeps > 0:
            # the prior alone (``rollout.remainders = zero``): the sweep's remainders are zero
            # wherever it would step, so its step would be the final one over again (the law's
            # whole cost twice a model step until session 99); the final step alone is taken
            G1, H = torch.zeros_like(G), torch.zeros_like(H)
        u1, v1, a1, h1 = self.prior.step(u, v, a, f1_rows, G, G1, h, f0_rows)
        return u1, v1, a1, G1, H, h1

    # --- the carried state [N, D + 6 (+ 9 T)]: what rollouts, export and serve step -------------
    @torch.jit.export
    def carry(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor) -> Tensor:
        """The carried state [N, D + 6 + 9 T (+ 3)] (``pack``) of the physical state z [N, D] under
        the load f [N, 3]."""
        u, v, a, G, H, h = self.begin(z.unsqueeze(0), f.unsqueeze(0), edge_index, node_type, ref_pos, False)
        return self.pack(u, v, a, G, H, h, f.unsqueeze(0))

    @torch.jit.export
    def step(self, z: Tensor, f: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
             dt: Tensor) -> Tensor:
        """One step of the carried state z [N, D + 6 + 9 T (+ 3)] driven by the load f [N, 3] [N] at the
        step's end (dt is the prior's own; the argument keeps TIGNN's signature)."""
        D = self.dim
        x = z.to(torch.float64).unsqueeze(0)                                        # [1, N, D + 6 + 9 T (+ 3)]
        f0: Optional[Tensor] = None
        if self.cut_loads_linear:                  # the load the last step ended under: this one's start
            f0, x = x[:, :, -3:], x[:, :, :-3]
        h = self.unpack_internal(x[:, :, D + 6:])
        u, v, H = self.unpack(x, h)
        a, G = self.prior.gather(x[:, :, D:D + 3]), self.prior.gather(x[:, :, D + 3:D + 6])
        u, v, a, G, H, h = self.advance(u, v, a, G, H, h, f.unsqueeze(0), edge_index, node_type, ref_pos, False,
                                        None, f0)
        return self.pack(u, v, a, G, H, h, f.unsqueeze(0)).to(z.dtype)

    def rollouts(self, z0: Tensor, forces: Tensor, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                 steps: int, create_graph: bool, bound: Optional[Tensor] = None) -> Tensor:
        """Physical states [B, steps + 1, N, D] (float64) from z0 [B, N, D] under the loads
        forces [B, S, N, 3] (forces[:, s] at t_s; the last one held beyond S - 1 steps);
        ``bound`` [D] as ``roll`` takes it."""
        r0 = self.rest_rates_once(z0.shape[0], edge_index, node_type, ref_pos, create_graph)
        u, v, a, G, H, h = self.begin(z0, forces[:, 0], edge_index, node_type, ref_pos, create_graph, r0)
        return self.roll(u, v, a, G, H, h, forces, edge_index, node_type, ref_pos, steps, create_graph, r0,
                         bound=bound)

    def roll(self, u: Tensor, v: Tensor, a: Tensor, G: Tensor, H: Tensor, h: Tensor, forces: Tensor,
             edge_index: Tensor, node_type: Tensor, ref_pos: Tensor, steps: int, create_graph: bool,
             rest_rates: Optional[Tensor] = None, recompute: bool = False,
             bound: Optional[Tensor] = None) -> Tensor:
        """``rollouts`` from its start (u, v, a, G, H, h), e.g. ``begin``'s with another acceleration
        and internal variables;
        ``rest_rates`` as ``rest_rates_once`` gives them (None: each step evaluates its own where
        it needs them, as ``network_remainders`` says).

        ``bound`` [D]: a state past it (``prior.stop_if_run_away``: each column's largest |z|, the
        positions' as displacements) stops the rollout with the RuntimeError ``prior.RAN_AWAY``
        (a validation rollout that ran away, ``rollout.validation_error``: a runaway's later steps
        are the dearest, a law stepped to convergence cutting every one).

        ``recompute`` (with ``create_graph``; ``train.rollout_recompute``): keep only the states
        between steps for the backward pass and recompute each step's graph there
        (``torch.utils.checkpoint``, reentrant: the non-reentrant form still keeps the graphs of
        the network's own autograd.grad), so memory grows by one carried state a step instead of
        a whole step's graph (shell, 40 steps of the corotated prior: over 24 GiB without), for
        about one more forward pass of time; same values and gradients
        (tests/test_fe_modes.py), which reach the weights through ``loss.backward()`` only
        (reentrant checkpoints do not pass ``torch.autograd.grad``)."""
        from torch.utils.checkpoint import checkpoint

        S = forces.shape[1]
        out = [self.state(u, v, H, h)]
        for s in range(1, steps + 1):
            f0, f1 = forces[:, min(s - 1, S - 1)], forces[:, min(s, S - 1)]
            if recompute and create_graph:
                u, v, a, G, H, h = checkpoint(_checkpointed_advance, self, edge_index, node_type, ref_pos,
                                              u, v, a, G, H, h, f1, rest_rates, f0, use_reentrant=True)
            else:
                u, v, a, G, H, h = self.advance(u, v, a, G, H, h, f1, edge_index, node_type, ref_pos, create_graph,
                                                rest_rates, f0)
            out.append(self.state(u, v, H, h))
            if bound is not None:
                stop_if_run_away(out[-1], ref_pos, bound, s)
        return torch.stack(out, 1)


def prior_kind(cfg_model) -> str:
    """``model.prior``: none (the network steps the state) | linear (this module)."""
    kind = str(OmegaConf.select(cfg_model, "prior", default="none"))
    if kind not in PRIORS:
        raise ConfigError(f"model.prior = '{kind}', expected " + " | ".join(PRIORS))
    return kind


def _flag(cfg_model, key: str, meaning: str) -> bool:
    """The boolean ``model.<key>`` (default false); a one-line ConfigError saying what it means."""
    value = OmegaConf.select(cfg_model, key, default=False)
    if not isinstance(value, bool):
        raise ConfigError(f"model.{key} = {value!r}, expected true | false ({meaning})")
    return value


def _count(cfg_model, key: str, default: int, meaning: str) -> int:
    """The integer ``model.<key>`` >= 1; a one-line ConfigError saying what it counts."""
    value = OmegaConf.select(cfg_model, key, default=default)
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ConfigError(f"model.{key} = {value!r}, expected an integer >= 1 ({meaning})")
    return value


def prior_settings(cfg_model) -> dict:
    """The checkpoint's ``prior`` entry from the ``model`` config group."""
    sweeps = _count(cfg_model, "prior_sweeps", 1, "network calls per step")
    inputs = str(OmegaConf.select(cfg_model, "prior_inputs", default="positions"))
    if inputs not in PRIOR_INPUTS:
        raise ConfigError(f"model.prior_inputs = '{inputs}', expected " + " | ".join(PRIOR_INPUTS))
    order = OmegaConf.select(cfg_model, "prior_order", default=1)
    if order not in ORDERS or isinstance(order, bool):
        raise ConfigError(f"model.prior_order = {order!r}, expected 1 | 2 (the order in the load at which "
                          f"the learned remainders start)")
    relax = _flag(cfg_model, "prior_relax", "the prior relaxes as the viscous FE solid does")
    corotated = _flag(cfg_model, "prior_corotated", "the prior's solid corotated per cell")
    rotation_sweeps = _count(cfg_model, "prior_rotation_sweeps", 3, "fixed-point sweeps of the corotated step")
    stress = str(OmegaConf.select(cfg_model, "prior_stress", default="linear"))
    if stress not in ("linear", "material"):
        raise ConfigError(f"model.prior_stress = '{stress}', expected linear | material (the prior's stress: the "
                          f"linear one, or the dataset's material law of each cell's deformation)")
    if stress == "material" and not corotated:
        raise ConfigError("model.prior_stress = material needs model.prior_corotated = true (the law is applied "
                          "per P1 cell, as the corotated prior measures its cells)")
    if stress == "material" and relax:
        raise ConfigError("model.prior_stress = material with model.prior_relax = true: the material law's stress "
                          "has no Prony history (set model.prior_stress=linear to relax)")
    law = _flag(cfg_model, "prior_law", "the prior is the dataset's own hyperelastic law, stepped with "
                "model.prior_newton Newton iterations")
    newton = _count(cfg_model, "prior_newton", 1, "Newton iterations a step of the law prior")
    most = OmegaConf.select(cfg_model, "prior_newton_max", default=None)
    if most is not None:
        most = _count(cfg_model, "prior_newton_max", 1, "the most Newton iterations a step of the law prior, "
                      "past prior_newton while the step has not converged; null: prior_newton always")
        if most < newton:
            raise ConfigError(f"model.prior_newton_max = {most}, expected >= model.prior_newton = {newton} "
                              f"(or null: prior_newton iterations always)")
    rtol = OmegaConf.select(cfg_model, "prior_newton_rtol", default=None)
    if rtol is not None and (isinstance(rtol, bool) or not isinstance(rtol, (int, float)) or not 0 < rtol < 1):
        raise ConfigError(f"model.prior_newton_rtol = {rtol!r}, expected a number in (0, 1) (the largest Newton "
                          f"update past prior_newton, as a share of the largest displacement, at which a step stops)")
    if rtol is not None and not (most is not None and most > newton):
        raise ConfigError(f"model.prior_newton_rtol = {rtol!r} needs model.prior_newton_max > model.prior_newton "
                          f"(= {newton}): with a fixed budget no step stops early")
    from .law_prior import MAX_STEP_CUTS

    cuts = OmegaConf.select(cfg_model, "prior_step_cuts", default=0)
    if cuts is None:
        cuts = 0
    if isinstance(cuts, bool) or not isinstance(cuts, int) or not 0 <= cuts <= MAX_STEP_CUTS:
        raise ConfigError(f"model.prior_step_cuts = {cuts!r}, expected an integer 0 to {MAX_STEP_CUTS} (how many times "
                          f"the law prior halves a step that has not converged: down to Δt/2^k, the FE's own floor "
                          f"Δt/{2 ** MAX_STEP_CUTS})")
    if cuts and not (law and most is not None and most > newton):
        raise ConfigError(f"model.prior_step_cuts = {cuts} needs model.prior_law = true and model.prior_newton_max > "
                          f"model.prior_newton (= {newton}): only then can a step tell it has not converged")
    from .law_prior import TANGENTS

    tangent = str(OmegaConf.select(cfg_model, "prior_tangent", default="fresh"))
    if tangent not in TANGENTS:
        raise ConfigError(f"model.prior_tangent = '{tangent}', expected " + " | ".join(TANGENTS))
    if tangent == "kept" and not (law and most is not None and most > newton):
        raise ConfigError(f"model.prior_tangent = kept needs model.prior_law = true and model.prior_newton_max > "
                          f"model.prior_newton (= {newton}): a kept tangent iterates each step to "
                          f"model.prior_newton_rtol")
    from .law_prior import MAX_ANDERSON

    anderson = OmegaConf.select(cfg_model, "prior_anderson", default=0)
    anderson = 0 if anderson is None else anderson
    if isinstance(anderson, bool) or not isinstance(anderson, int) or not 0 <= anderson <= MAX_ANDERSON:
        raise ConfigError(f"model.prior_anderson = {anderson!r}, expected an integer 0 to {MAX_ANDERSON} (how many "
                          f"earlier chord updates of a step the law prior mixes each with, Anderson's method; 0: none)")
    if anderson and tangent != "kept":
        raise ConfigError(f"model.prior_anderson = {anderson} needs model.prior_tangent = kept: it mixes the kept "
                          f"tangent's chord updates")
    from .law_prior import MAX_HALVINGS

    search = OmegaConf.select(cfg_model, "prior_line_search", default=0)
    if search is None:
        search = 0
    if isinstance(search, bool) or not isinstance(search, int) or not 0 <= search <= MAX_HALVINGS:
        raise ConfigError(f"model.prior_line_search = {search!r}, expected an integer 0 to {MAX_HALVINGS} (how many "
                          f"times the law prior halves a Newton update that does not lower the residual norm)")
    if search and not law:
        raise ConfigError(f"model.prior_line_search = {search} needs model.prior_law = true (model=law_prior): it "
                          f"searches the law prior's Newton updates")
    from .law_prior import MAX_HHT, RULES

    rule = str(OmegaConf.select(cfg_model, "prior_rule", default="newmark") or "newmark")
    if rule not in RULES:
        raise ConfigError(f"model.prior_rule = '{rule}', expected " + " | ".join(RULES)
                          + " (the law prior's time rule: the data's Newmark, or the trapezoid with the stored "
                            "energy's discrete gradient)")
    hht = OmegaConf.select(cfg_model, "prior_hht", default=0.0)
    hht = 0.0 if hht is None else hht
    if isinstance(hht, bool) or not isinstance(hht, (int, float)) or not 0.0 <= float(hht) <= MAX_HHT:
        raise ConfigError(f"model.prior_hht = {hht!r}, expected a number 0 to 1/3 (HHT's numerical dissipation, "
                          f"alpha = -prior_hht; 0: the data's Newmark rule)")
    if (rule != "newmark" or hht) and not law:
        raise ConfigError("model.prior_rule and model.prior_hht need model.prior_law = true (model=law_prior): they "
                          "step the law prior's law in time")
    if rule == "energy" and hht:
        raise ConfigError(f"model.prior_hht = {hht} with model.prior_rule = energy: the energy rule conserves what "
                          f"HHT dissipates; set one of them")
    from .law_prior import SUBSTEPS

    substeps = OmegaConf.select(cfg_model, "prior_substeps", default=1)
    substeps = 1 if substeps is None else substeps
    if isinstance(substeps, bool) or substeps not in SUBSTEPS:
        raise ConfigError(f"model.prior_substeps = {substeps!r}, expected one of {list(SUBSTEPS)} (each step of the law "
                          f"prior as that many sub-steps, as data generated with scene.time.substeps were solved)")
    if substeps > 1 and not law:
        raise ConfigError(f"model.prior_substeps = {substeps} needs model.prior_law = true (model=law_prior): it "
                          f"steps the law prior's law in sub-steps")
    cut_loads = str(OmegaConf.select(cfg_model, "prior_cut_loads", default="end") or "end")
    if cut_loads not in CUT_LOADS:
        raise ConfigError(f"model.prior_cut_loads = '{cut_loads}', expected " + " | ".join(CUT_LOADS)
                          + " (a cut step's sub-steps under its end load, or linearly between its start and end loads)")
    if cut_loads == "linear" and not (law and (cuts or substeps > 1)):
        raise ConfigError("model.prior_cut_loads = linear needs model.prior_law = true and model.prior_step_cuts > 0 "
                          "(or model.prior_substeps > 1): it loads the sub-steps of a cut step")
    material = str(OmegaConf.select(cfg_model, "prior_material", default="data"))
    if material not in LAW_MATERIALS:
        raise ConfigError(f"model.prior_material = '{material}', expected " + " | ".join(LAW_MATERIALS)
                          + " (the law prior's hyperelastic law: the scene's, or a strain energy fitted to the data)")
    if material == "learned" and not law:
        raise ConfigError("model.prior_material = learned needs model.prior_law = true (model=law_prior): it is "
                          "the law the law prior steps")
    hidden = OmegaConf.select(cfg_model, "prior_material_hidden", default=None)
    if hidden is None:
        from .learned_law import HIDDEN as hidden
    hidden = list(hidden)
    prony = str(OmegaConf.select(cfg_model, "prior_material_prony", default="learned"))
    convex = OmegaConf.select(cfg_model, "prior_material_convex", default=False)
    if not isinstance(convex, bool):
        raise ConfigError(f"model.prior_material_convex = {convex!r}, expected true or false (a convex learned energy)")
    if prony not in LAW_MATERIALS:
        raise ConfigError(f"model.prior_material_prony = '{prony}', expected " + " | ".join(LAW_MATERIALS)
                          + " (a learned law's Prony terms: the scene's, or fitted with its energy)")
    if len(hidden) != 2 or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in hidden):
        raise ConfigError(f"model.prior_material_hidden = {hidden!r}, expected two integers >= 1 (the learned "
                          f"law's isochoric and volumetric hidden units)")
    if law and (corotated or stress == "material"):
        raise ConfigError("model.prior_law = true steps the dataset's own law (its stress and Prony history "
                          "included): set model.prior_corotated=false and model.prior_stress=linear")
    settings = {"kind": "linear", "sweeps": sweeps, "positions_only": inputs == "positions"}
    if inputs == "correction":                    # absent otherwise: older checkpoints keep their settings
        settings["inputs"] = "correction"
    if order != 1:
        settings["order"] = int(order)
    if relax:                                     # absent when false: older checkpoints keep their settings
        settings["relax"] = True
    if corotated:                                 # the corotated step's fixed-point sweeps
        settings["corotated"] = int(rotation_sweeps)
    if stress == "material":
        settings["stress"] = "material"
    if law:                                       # the law prior's Newton iterations a step
        settings["law"] = int(newton)
        if most is not None and most > newton:    # and the most, where the step has not converged, to what
            from .law_prior import NEWTON_RTOL

            settings["law_max"] = int(most)
            settings["law_rtol"] = float(NEWTON_RTOL if rtol is None else rtol)
            if cuts:                              # and how often a step that has not is halved
                settings["law_cuts"] = int(cuts)
                if cut_loads == "linear":         # its sub-steps loaded between the step's loads
                    settings["law_cut_loads"] = "linear"
            if tangent == "kept":                 # its tangent kept between iterations and steps
                settings["law_tangent"] = "kept"
                if anderson:                      # its chord updates Anderson-mixed (absent: not)
                    settings["law_anderson"] = int(anderson)
        if search:                                # its Newton updates line-searched (absent otherwise)
            settings["law_search"] = int(search)
        if rule != "newmark":                     # its time rule (absent: the data's Newmark rule)
            settings["law_rule"] = rule
        if hht:                                   # HHT's dissipation (absent: none)
            settings["law_hht"] = float(hht)
        if substeps > 1:                          # each step as sub-steps, loaded between its loads
            settings["law_substeps"] = int(substeps)
            settings["law_cut_loads"] = "linear"
        if material == "learned":                 # its law a strain energy fitted to the data
            settings["law_material"] = "learned"
            settings["law_hidden"] = [int(h) for h in hidden]
            if prony == "learned":                # its Prony terms too (their values: ``learned_law_of``)
                settings["law_prony"] = "learned"
            if convex:                            # fitted as a convex energy (absent otherwise)
                settings["law_convex"] = True
    return settings


def neo_hookean_of(ds) -> Tuple[float, float]:
    """(C10 [Pa], D1 [1/Pa]) of the dataset's material (``scene.material`` of the config it was
    generated with) for ``model.prior_stress = material``; one-line errors where the law is another
    or the solid is viscous (its stress then has a history the law alone does not give)."""
    mat = ds.material
    if "law" not in mat:
        raise DataError(f"{ds.path}: no scene.material in the dataset's config (model.prior_stress = material)")
    law = str(mat["law"])
    if law != "neo_hookean":
        raise ConfigError(f"model.prior_stress = material: {ds.path} is of material law '{law}', expected "
                          f"neo_hookean (the one law the prior applies yet)")
    if list(mat.get("prony") or []):
        raise ConfigError(f"model.prior_stress = material: {ds.path}'s material is viscous (Prony terms), expected "
                          f"an elastic one (its stress has a history the law alone does not give)")
    return float(mat["C10"]), float(mat["D1"])


def build_prior(ds, dt: float, relax: bool = False, corotated: int = 0, material: bool = False,
                law: int = 0, law_max: Optional[int] = None, law_rtol: Optional[float] = None,
                law_cuts: int = 0, law_tangent: str = "fresh", law_search: int = 0, law_hht: float = 0.0,
                law_rule: str = "newmark", law_substeps: int = 1, law_anderson: int = 0,
                learned_law: Optional[Sequence[int]] = None,
                prony: Optional[Sequence[Sequence[float]]] = None) -> NewmarkPrior:
    """The dataset's ``/linear`` as a NewmarkPrior (float64), relaxing as its viscous solid does
    with ``relax``, or corotated per cell with ``corotated`` > 0 fixed-point sweeps a step
    (:class:`CorotatedNewmarkPrior`), its stress the material's law with ``material``, or with
    ``law`` > 0 the dataset's own hyperelastic law stepped with that many Newton iterations, and up
    to ``law_max`` where a step has not converged to ``law_rtol``, halved up to ``law_cuts`` times
    where it still has not, its tangent ``law_tangent`` (fresh | kept), a kept tangent's chord
    updates Anderson-mixed with up to ``law_anderson`` earlier ones, its updates line-searched
    with up to ``law_search`` halvings (0: none; ``prior_settings`` records them)
    (:class:`thermognn.train.law_prior.HyperelasticNewmarkPrior`), its law with ``learned_law``
    (hidden units) a learned strain energy (:mod:`thermognn.train.learned_law`; its weights come
    from a fit or a state_dict), its Prony terms ``prony`` [(ḡ_i, τ_i s)] where given (a learned
    law's fitted ones), else the dataset's;
    one-line errors where it cannot be."""
    names = list(ds.layout.names)
    if names != LAYOUT:
        raise ConfigError(f"model.prior = linear: {ds.path} has state variables {names}, expected {LAYOUT} "
                          f"(a scene with inertia and no stored internal variables)")
    linear = ds.linear_solid()
    if linear is None:
        raise DataError(f"{ds.path}: no linearised FE operators (/linear) for model.prior = linear "
                        f"(regenerate the dataset with this version of thermognn generate)")
    if corotated or law:
        try:
            lam, mu = linear.lame()
        except ValueError:
            raise DataError(f"{ds.path}: /linear holds no moduli at rest for "
                            f"{'model.prior_law' if law else 'model.prior_corotated'} = true "
                            f"(regenerate the dataset with this version of thermognn generate)") from None
    try:
        if corotated or law:
            tets = np.asarray(ds.mesh.tets)
            if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
                raise ValueError(f"the {'law' if law else 'corotated'} prior needs P1 tets in /mesh/tets")
        if law:
            from thermognn.core.hyperelastic import law_from_config

            from .law_prior import HyperelasticNewmarkPrior

            if "law" not in ds.material:
                raise DataError(f"{ds.path}: no scene.material in the dataset's config (model.prior_law = true)")
            solid_law, scene_prony = law_from_config(ds.material)
            if not np.allclose(np.asarray(scene_prony).reshape(-1, 2), np.asarray(linear.prony).reshape(-1, 2)):
                raise ValueError(f"scene.material.prony {scene_prony} is not /linear's {tuple(linear.prony)}")
            if prony is not None:
                if len(prony) != len(linear.prony):
                    raise ValueError(f"{len(prony)} learned Prony terms, the scene has {len(linear.prony)}")
                linear = dataclasses.replace(linear, prony=tuple((float(g), float(t)) for g, t in prony))
            if learned_law is not None:
                from .learned_law import StrainEnergy

                solid_law = StrainEnergy(learned_law, mu=mu, kappa=lam + 2.0 * mu / 3.0)
            return HyperelasticNewmarkPrior(linear, len(ds.mesh.nodes), float(dt), ds.mesh.nodes, tets, lam, mu,
                                            solid_law, iterations=int(law), max_iterations=law_max,
                                            newton_rtol=law_rtol, step_cuts=int(law_cuts), tangent=law_tangent,
                                            line_search=int(law_search), hht=float(law_hht),
                                            rule=str(law_rule), substeps=int(law_substeps),
                                            anderson=int(law_anderson))
        if corotated:
            return CorotatedNewmarkPrior(linear, len(ds.mesh.nodes), float(dt), ds.mesh.nodes, tets, lam, mu,
                                         sweeps=int(corotated), neo_hookean=neo_hookean_of(ds) if material else None,
                                         relax=relax)
        return NewmarkPrior(linear, len(ds.mesh.nodes), float(dt), relax=relax)
    except ValueError as exc:
        raise ConfigError(f"model.prior = linear: {ds.path}: {exc}") from None


def prior_model(net: TIGNN, settings: dict, ds, dt: float) -> LinearPriorModel:
    """The LinearPriorModel of a network, the checkpoint's ``prior`` settings and the dataset."""
    X = torch.as_tensor(ds.mesh.nodes, dtype=torch.float64)
    return LinearPriorModel(net, build_prior(ds, dt, bool(settings.get("relax", False)),
                                             int(settings.get("corotated", 0)),
                                             settings.get("stress", "linear") == "material",
                                             int(settings.get("law", 0)), settings.get("law_max"),
                                             settings.get("law_rtol"), int(settings.get("law_cuts", 0)),
                                             str(settings.get("law_tangent", "fresh")),
                                             int(settings.get("law_search", 0)),
                                             float(settings.get("law_hht", 0.0)),
                                             str(settings.get("law_rule", "newmark")),
                                             int(settings.get("law_substeps", 1)),
                                             int(settings.get("law_anderson", 0)),
                                             settings.get("law_hidden") if settings.get("law_material") == "learned"
                                             else None,
                                             settings["law_prony"] if isinstance(settings.get("law_prony"), list)
                                             else None), X,
                            bool(settings.get("positions_only", True)),
                            int(settings.get("sweeps", 1)), int(settings.get("order", 1)),
                            settings.get("inputs") == "correction",
                            settings.get("remainders", "learned") != "zero",
                            str(settings.get("law_cut_loads", "end")))


def carried_layout(layout_json: str, internal: Sequence[Tuple[str, int]] = ()) -> str:
    """The exported state layout of a prior model: the physical one plus a and G, and the relaxing
    prior's internal variables as its ``internal_columns`` give them ((name, width) per group: per
    Prony term its force (3) and stress (6) variables, or the corotated prior's cell variables)."""
    import json

    return json.dumps(json.loads(layout_json) + [list(g) for g in CARRIED] + [[n, int(w)] for n, w in internal])


# --- training ---------------------------------------------------------------------------------
#: the network's last layers start at this fraction of their initial size, so that a fresh model
#: is the linearised FE model to within 1 % of the remainders' scale
START_SCALE = 0.01
#: gradient-norm clip of both phases
CLIP = 1.0


def exact_remainders(model: LinearPriorModel, trajs) -> Tuple[List[Tensor], List[Tensor]]:
    """The exact remainders of each trajectory: G as nodal vectors [S, N, 3] N (zero at clamped
    DOFs) and H [S, N, 6] Pa, float64."""
    P, X = model.prior, model.reference_positions
    Gs, Hs = [], []
    for t in trajs:
        z, f = t.z.double(), t.force.double()
        G, H = P.remainders(z[..., 0:3] - X, z[..., 3:6], z[..., 6:12], f)
        Gs.append(P.scatter(G))
        Hs.append(H)
    return Gs, Hs


def budget_remainders(model: LinearPriorModel, trajs) -> Tuple[List[Tensor], List[float]]:
    """The law prior's remainders of its Newton budget along each trajectory (``train.fit_target
    = budget``): G [S, N, 3] N (float64) such that the model's step from each of the data's
    states, with G0 = G[s] and G1 = G[s + 1] and ``model.prior_newton`` iterations, lands on the
    data's next state (``HyperelasticNewmarkPrior.budget_loads`` e, carried into G as the step
    does, ``NewmarkPrior.carried_remainders``); and each trajectory's largest miss the load
    corrections left (relative to its largest displacement; see ``BUDGET_MISS_TOL``). H is the
    exact remainders' (``exact_remainders``: round-off, the law's stress being exact at the true
    displacement)."""
    P, X = model.prior, model.reference_positions
    Gs, misses = [], []
    for t in trajs:
        z = t.z.double()
        e, miss = P.budget_loads(P.gather(z[..., 0:3] - X), P.gather(z[..., 3:6]), P.gather(t.force.double()))
        misses.append(miss)                                                          # e: [S - 1, n]
        Gs.append(P.scatter(P.carried_remainders(e)))
    return Gs, misses


#: a trajectory whose budget corrections leave a step's end further than this from the data's
#: (relative to its largest displacement) has no budget remainders: no load lands the budgeted
#: step there (the shell at 2 iterations a step, where it snaps through: the corrections diverge,
#: docs/accuracy.md session 69); the fit leaves it out
BUDGET_MISS_TOL = 1.0e-6


def budget_fit_trajectories(model: LinearPriorModel, trajs, H: List[Tensor]):
    """(trajectories, G, H, [(name, miss)] left out) of the budget fit (``train.fit_target =
    budget``): each trajectory's ``budget_remainders`` and its H, leaving out those whose load
    corrections left a miss above ``BUDGET_MISS_TOL`` (no load lands the budgeted step there); a
    one-line DataError where that leaves none."""
    G, misses = budget_remainders(model, trajs)
    keep = [i for i, m in enumerate(misses) if m <= BUDGET_MISS_TOL]
    if not keep:
        raise DataError(f"train.fit_target = budget: no load lands the {model.prior.iterations}-iteration step on "
                        f"the data in any training trajectory (raise model.prior_newton)")
    unreached = [(t.name, m) for t, m in zip(trajs, misses) if m > BUDGET_MISS_TOL]
    return [trajs[i] for i in keep], [G[i] for i in keep], [H[i] for i in keep], unreached


#: train.fit_target values: what the fit phase regresses the network's remainders on
FIT_TARGETS = ("exact", "budget")


def remainder_scale(stats: Dict[str, Tensor], G: List[Tensor], H: List[Tensor], free_nodes: Tensor,
                    floor: Optional[Tensor] = None) -> Tensor:
    """The network's output scale ``dzdt_std`` [D]: the RMS of G over the free nodes [N] (v
    columns, one number) and of each H component (σ columns) in the training data, at least
    ``floor`` [D] (``law_scale_floor``: the law prior's exact remainders are round-off)."""
    scale = stats["dzdt_std"].clone().double()
    scale[3:6] = torch.cat([g[:, free_nodes] for g in G]).pow(2).mean().sqrt()
    scale[6:12] = torch.cat([h.reshape(-1, 6) for h in H]).pow(2).mean(0).sqrt()
    if floor is not None:
        scale = torch.maximum(scale, floor.double())
    return scale.clamp(min=1e-30)


#: a trajectory whose exact law-prior remainder G exceeds this fraction of its loads (RMS) was not
#: stepped with one Newmark step a Δt (the FE cut steps there): the law prior leaves it out of its fit
LAW_STEP_TOL = 1.0e-4


def law_fit_trajectories(trajs, G: List[Tensor], H: List[Tensor], free_nodes: Tensor):
    """(trajectories, G, H, [(name, RMS G / RMS load)] left out) of the law prior's fit: its exact
    remainders are round-off (the data's own step) except where the FE cut its steps (shell: 11 of
    192 cases, G up to 0.16 of the loads), which are not what the network should learn."""
    keep, cut = [], []
    for i, t in enumerate(trajs):
        load = t.force.double()[:, free_nodes].pow(2).mean().sqrt()
        ratio = float(G[i][:, free_nodes].pow(2).mean().sqrt() / load.clamp(min=1e-300))
        (cut.append((t.name, ratio)) if ratio > LAW_STEP_TOL else keep.append(i))
    if not keep:
        raise DataError("the law prior: every training trajectory's FE cut its steps (no one-step data to fit)")
    return [trajs[i] for i in keep], [G[i] for i in keep], [H[i] for i in keep], cut


#: the law prior's output scale, as a fraction of the training data's loads (G) and stresses (H)
LAW_SCALE = 1.0e-2


def law_scale_floor(trajs, free_nodes: Tensor, D: int) -> Tensor:
    """The law prior's output scale [D]: its exact remainders vanish (the prior is the data's own
    step, converged), so the network learns only what the Newton budget leaves, which is no
    round-off: ``LAW_SCALE`` of the RMS load on the free nodes (G, v columns) and of each stress
    component (H, σ columns) in the training data."""
    floor = torch.zeros(D, dtype=torch.float64)
    floor[3:6] = torch.cat([t.force.double()[:, free_nodes] for t in trajs]).pow(2).mean().sqrt() * LAW_SCALE
    floor[6:12] = torch.cat([t.z.double()[..., 6:12].reshape(-1, 6) for t in trajs]).pow(2).mean(0).sqrt() * LAW_SCALE
    return floor


#: the learned law's fit, kept beside the checkpoints (``learned_law_of``)
LAW_FIT_FILE = "learned_law.pt"


def learned_law_of(model: LinearPriorModel, trajs, out_dir: Path, ds, tc, init_ckpt: Optional[dict],
                   dist, prony: bool = False, convex: bool = False) -> Tuple[set, Optional[list]]:
    """Put the learned law (``model.prior_material=learned``) of a law prior in place before its
    network trains: ``train.init``'s, else the fit kept in ``out_dir/learned_law.pt`` for this
    dataset and shape (a rerun or a resumed run does not fit again), else fitted now to the training
    trajectories (:func:`thermognn.train.learned_law.fit_strain_energy`, ``train.law_fit_iterations``
    L-BFGS iterations on at most ``train.law_fit_trajectories`` of them, picked by
    ``train.law_fit_pick``) and kept there, written atomically; with ``prony`` the Prony terms are
    fitted with it. Returns (the training trajectories' names the fit left out (where the FE cut
    its steps), the fitted Prony terms [(ḡ_i, τ_i)] or None); ``convex`` fits the convex family."""
    from thermognn.core.io import atomic_path

    from .data import fingerprint
    from .learned_law import FIT_ITERATIONS, FIT_TRAJECTORIES, fit_strain_energy, invariant_scales
    from .loop import _sel
    from .model import _choice

    prior = model.prior
    law = prior.learned_law
    prefix = "prior.learned_law."
    if _sel(tc, "init", None):
        from thermognn.core.config import project_path

        from .checkpoint import load_checkpoint

        src = init_ckpt if init_ckpt is not None else load_checkpoint(project_path(str(tc.init)))
        state = {k[len(prefix):]: v for k, v in src["state_dict"].items() if k.startswith(prefix)}
        if not state:
            raise ConfigError(f"train.init = '{tc.init}': its checkpoint holds no learned law (model.prior_material)")
        law.load_state_dict(state)
        fitted = (src.get("prior") or {}).get("law_prony")
        if prony and prior.n_terms and not isinstance(fitted, list):   # (none to fit: an elastic scene)
            raise ConfigError(f"train.init = '{tc.init}': its learned law has the scene's Prony terms "
                              f"(set model.prior_material_prony=data)")
        return set(), (fitted if prony and isinstance(fitted, list) else None)
    counts = {}                                  # train.law_fit_iterations, train.law_fit_trajectories
    for name, default in (("iterations", FIT_ITERATIONS), ("trajectories", FIT_TRAJECTORIES)):
        value = _sel(tc, f"law_fit_{name}", default)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"train.law_fit_{name} = {value!r}: expected a whole number of at least 1")
        counts[name] = value
    pick = str(_sel(tc, "law_fit_pick", "widest"))
    _choice("law_fit_pick", pick, ("widest", "spread"), "train")
    elliptic = _sel(tc, "law_fit_elliptic", 0.0)
    if isinstance(elliptic, bool) or not isinstance(elliptic, (int, float)) or not math.isfinite(elliptic) or elliptic < 0:
        raise ConfigError(f"train.law_fit_elliptic = {elliptic!r}: expected a number >= 0 (the weight of the "
                          f"learned law's ellipticity penalty; 0: none)")
    elliptic = float(elliptic)
    path = out_dir / LAW_FIT_FILE
    key = {"dataset": repr(sorted(fingerprint(ds).items())),
           "hidden": list(law.hidden), "trajectories": sorted(t.name for t in trajs),
           "iterations": counts["iterations"], "at_most": counts["trajectories"], "prony": bool(prony)}
    if convex:                                   # absent otherwise: fits kept before keep their keys
        key["convex"] = True
    if pick == "widest":                         # fits kept before session 81 picked by spread
        key["pick"] = pick
    if elliptic > 0:                             # absent otherwise: fits kept before keep their keys
        key["elliptic"] = elliptic
    if path.exists():
        kept = torch.load(path, weights_only=True)
        if kept.get("key") == key:
            law.load_state_dict(kept["state"])
            if dist.main:
                print(f"train: the learned law from {path} (fitted before: RMS force remainder "
                      f"{kept['report']['force']:.3e} of the loads, stress {kept['report']['stress']:.3e} of σ)")
            return set(kept["report"]["left_out"]), kept["report"].get("prony")
    X = model.reference_positions
    with torch.no_grad():
        extents = []                             # each trajectory's largest |Ī1 − 3|, |Ī2 − 3|, |J − 1|
        for t in trajs:
            F = prior.cells(prior.gather(t.z.double()[..., 0:3] - X))                      # [S, T, 3, 3]
            extents.append(invariant_scales(F.transpose(-1, -2) @ F))
        extents = torch.tensor(extents, dtype=torch.float64)                               # [n, 3]
        law.scales.copy_(extents.max(0).values.to(law.scales.dtype))                        # the split's largest
    report = fit_strain_energy(prior, trajs, X, counts["iterations"], counts["trajectories"],
                               log=(lambda m: print(m, flush=True)) if dist.main else (lambda *_: None),
                               prony=prony, convex=convex, extents=extents if pick == "widest" else None,
                               elliptic=elliptic)
    if dist.main:
        with atomic_path(path) as tmp:
            torch.save({"key": key, "state": law.state_dict(),
                        "report": {"force": report["force"], "stress": report["stress"],
                                   "seconds": report["seconds"], "left_out": [n for n, _ in report["left_out"]],
                                   "prony": report["prony"], "ellipticity": report["ellipticity"]}},
                       tmp)
    return {n for n, _ in report["left_out"]}, report["prony"]


def _lr(base: float, decay: float, progress: float) -> float:
    """Exponential schedule: base at progress 0, base * decay at 1."""
    return base * decay ** min(max(progress, 0.0), 1.0)


class _FitPhase:
    """Phase 1: the network's outputs at the data's states (with training noise) regressed on
    the exact remainders, in its own units (``dzdt_std``); samples are (trajectory, snapshot)."""

    def __init__(self, model: LinearPriorModel, trajs, G: List[Tensor], H: List[Tensor], noise: float,
                 lambda_data: float, lambda_degeneracy: float, inputs: Optional[List[Tensor]] = None) -> None:
        net = model.net
        dtype, N, D = net.z_mean.dtype, trajs[0].z.shape[1], model.dim
        free_nodes = model.prior.free_nodes()                                           # [N]
        scale = net.dzdt_std.detach().double()
        self.model, self.trajs = model, trajs
        self.targets = [(torch.cat([torch.zeros_like(g), g, h], -1) / scale).to(dtype)
                        for g, h in zip(G, H)]                                          # [S, N, D] each
        self.weight = torch.zeros(N, D, dtype=dtype)                                     # q columns: unused
        self.weight[:, 3:] = 1.0
        self.weight[~free_nodes, 3:6] = 0.0
        # what the network sees at each sample: the states themselves, or (``correction``) the
        # model's step ends from them (``LinearPriorModel.step_inputs``)
        self.inputs = inputs if inputs is not None else [model.trajectory_inputs(t.z) for t in trajs]
        step_rms = torch.cat([x.diff(dim=0).reshape(-1, D) for x in self.inputs]).double().pow(2).mean(0).sqrt()
        self.noise = (step_rms * noise).to(dtype) * free_nodes.to(dtype).view(N, 1)      # [N, D]
        self.noisy = noise > 0
        self.samples = [(i, s) for i, t in enumerate(trajs) for s in range(t.z.shape[0])]
        self.lambda_data, self.lambda_degeneracy = lambda_data, lambda_degeneracy

    def loss(self, chosen, g, gen: torch.Generator) -> Tuple[Tensor, float, float]:
        """(loss, data loss, degeneracy loss) of the samples ``chosen`` on the mesh copies g."""
        k = len(chosen)
        N, D = self.weight.shape
        z = torch.stack([self.inputs[i][s] for i, s in chosen])                           # [k, N, D]
        f = torch.stack([self.trajs[i].force[s] for i, s in chosen])                      # [k, N, 3]
        y = torch.stack([self.targets[i][s] for i, s in chosen])
        if self.noisy:                       # (no draw without noise: the generator also orders the epochs)
            z = z + cpu_randn(z.shape, gen, z) * self.noise
        r, deg = self.model.network_remainders(z, f, g.edge_index, g.node_type, g.ref_pos, True)   # [k, N, D]
        data_loss = ((r - y).pow(2) * self.weight).sum() / (self.weight.sum() * k)
        return self.lambda_data * data_loss + self.lambda_degeneracy * deg, float(data_loss.detach()), float(deg.detach())


#: train.rollout_scale values: what a rollout's error in each group is relative to
ROLLOUT_SCALES = ("data", "trajectory")

#: train.stress_remainder_weight's term takes every this-many-th true state of a window (steps 1,
#: 4, 7, 10 of a 10-step window): one batched network call on that many mesh copies a batch
STRESS_STRIDE = 3


class _RolloutPhase:
    """Phase 2: rollouts from true states, back-propagated through the linear solves (whole
    trajectories, or windows of ``window`` steps tiling them); each group's error relative to its
    RMS (q: the displacement's) in the training data (``scale`` "data") or in the sample's own
    trajectory ("trajectory": each trajectory weighs alike, as in the whole-rollout error that
    validation and the test report, so gentle load cases are not drowned by the strong ones).
    Samples are (trajectory, first state)."""

    def __init__(self, model: LinearPriorModel, trajs, window: int = 0, scale: str = "data",
                 recompute: bool = False, weights: Tuple[float, float, float] = (1.0, 1.0, 1.0),
                 stress_weight: float = 0.0, mesh=None) -> None:
        self.model, self.trajs, self.recompute, self.weights = model, trajs, recompute, tuple(weights)
        self.stress_weight, self.mesh = float(stress_weight), mesh     # mesh(k): k copies of the mesh graph
        if self.stress_weight > 0 and mesh is None:
            raise ValueError("_RolloutPhase: stress_weight > 0 needs the mesh copies (mesh)")
        Z = [t.z.double() for t in trajs]
        X = model.reference_positions
        self.Z = Z
        groups = [(slice(0, 3), [z[..., 0:3] - X for z in Z]), (slice(3, 6), [z[..., 3:6] for z in Z]),
                  (slice(6, 12), [z[..., 6:12] for z in Z])]
        rms = lambda xs: torch.cat(xs).pow(2).mean().sqrt()                           # noqa: E731
        # per group: its scale for each trajectory [T]
        self.scales = [(sl, torch.stack([rms([x]) for x in xs]) if scale == "trajectory"
                        else rms(xs).expand(len(xs))) for sl, xs in groups]
        longest = max(z.shape[0] for z in Z) - 1
        self.window = window if 0 < window < longest else longest           # steps per sample
        # samples: (trajectory, first state) of windows tiling every trajectory
        self.samples = [(i, s) for i, z in enumerate(Z) for s in range(0, z.shape[0] - 1, self.window)]
        # the data's Newmark accelerations (and the relaxing prior's internal variables), where a
        # window starts mid-way
        mid_way = self.window < longest
        self.accelerations = [model.accelerations(z, t.force) for z, t in zip(Z, trajs)] if mid_way else []
        self.internal = ([model.trajectory_internal_variables(z) for z in Z]
                         if (mid_way or self.stress_weight > 0) and model.prior.n_terms else [])
        self.left_out = 0        # samples left out of the loss since the last reset: a cell turned inside out

    def loss(self, chosen, g) -> Tuple[Tensor, float, float]:
        """Rollouts of ``window`` steps (fewer where a trajectory ends: a batch runs to its
        shortest) from the true states of the samples ``chosen``: from a trajectory's start as
        ``LinearPriorModel.rollouts`` steps it, from a later state with the data's own Newmark
        acceleration there (as ``rollout.one_step_errors``)."""
        W = min(min(self.window, self.Z[i].shape[0] - 1 - s) for i, s in chosen)
        truth = torch.stack([self.Z[i][s:s + W + 1] for i, s in chosen])                  # [k, W + 1, N, D]
        forces = torch.stack([self.trajs[i].force[s:s + W + 1] for i, s in chosen])       # [k, W + 1, N, 3]
        mesh = (g.edge_index, g.node_type, g.ref_pos)
        r0 = self.model.rest_rates_once(len(chosen), *mesh, True)        # once per batch: weights fixed within it
        u, v, a, G, H, h = self.model.begin(truth[:, 0], forces[:, 0], *mesh, True, r0)
        if any(s > 0 for _, s in chosen):
            a = torch.stack([self.accelerations[i][s] if s > 0 else a[j] for j, (i, s) in enumerate(chosen)])
            if self.internal:                # the relaxing prior: the data's history, and H relative to it
                h = torch.stack([self.internal[i][s] for i, s in chosen])
                H = H - self.model.prior.stress_relaxation(u, h)     # begin's H is σ − Σ u (unpack of a start)
        pred = self.model.roll(u, v, a, G, H, h, forces, *mesh, W, True, r0, self.recompute)
        rows = torch.tensor([i for i, _ in chosen])
        per_sample = sum(w * ((pred[:, 1:, :, sl] - truth[:, 1:, :, sl]) / sc[rows].view(-1, 1, 1, 1)).pow(2)
                         .mean((1, 2, 3)) for w, (sl, sc) in zip(self.weights, self.scales))        # [k]
        # a rollout that turns a cell inside out has left the prior's physics (the corotated
        # force pushes on through): its error says nothing a gradient can use, so it is left out
        with torch.no_grad():
            keep = ~self.model.prior.inverted(pred[:, 1:, :, 0:3].flatten(0, 1)).view(len(chosen), W).any(1)
        self.left_out += int((~keep).sum())
        loss = (per_sample * keep.to(per_sample.dtype)).sum() / max(int(keep.sum()), 1)
        rollout_loss = float(loss.detach())
        if self.stress_weight > 0:
            loss = loss + self.stress_weight * self.stress_remainder_loss(chosen, truth, forces, rows, r0)
        return loss, rollout_loss, 0.0

    def stress_remainder_loss(self, chosen, truth: Tensor, forces: Tensor, rows: Tensor,
                              rest_rates: Optional[Tensor]) -> Tensor:
        """``train.stress_remainder_weight``'s term: the network's stress remainder H at true states
        of the windows (every ``STRESS_STRIDE``-th from the first step) against the exact one,
        H = σ − the prior's stress of the true displacement (``unpack``; relaxing: of its history
        too), each relative to the trajectory's σ scale as the rollout's σ term. In the rollout
        loss alone H is learned only through σ's error along the predicted path, where a change
        of the displacement field can stand in for it (shell, session 45: the learned H was 3.4 %
        of the exact one's size, the predicted displacements' strains 9 % off the data's); this
        term gives H its own target. truth [k, W + 1, N, D], forces [k, W + 1, N, 3]."""
        k, N, D = truth.shape[0], truth.shape[2], truth.shape[3]
        states = truth[:, 1::STRESS_STRIDE]                                          # [k, s, N, D]
        s = states.shape[1]
        flat = states.reshape(k * s, N, D)                                           # [k s, N, D]
        seen = torch.stack([self.model.trajectory_inputs(x) for x in truth])[:, 1::STRESS_STRIDE].reshape(k * s, N, D)
        g = self.mesh(k * s)
        _, H = self.model.remainders(seen, forces[:, 1::STRESS_STRIDE].reshape(k * s, N, 3), g.edge_index,
                                     g.node_type, g.ref_pos, True, rest_rates)        # [k s, N, 6] Pa
        h = (torch.stack([self.internal[i][first + 1::STRESS_STRIDE][:s] for i, first in chosen]).flatten(0, 1)
             if self.internal else None)                                             # [k s, T, n + 6N]
        exact = self.model.unpack(flat.to(torch.float64), h)[2]                      # [k s, N, 6] Pa
        scale = self.scales[2][1][rows].repeat_interleave(s).view(-1, 1, 1)          # [k s, 1, 1] Pa
        return ((H - exact) / scale).pow(2).mean()


def _checkpointed_advance(model: LinearPriorModel, edge_index: Tensor, node_type: Tensor, ref_pos: Tensor,
                          u: Tensor, v: Tensor, a: Tensor, G: Tensor, H: Tensor, h: Tensor, f1: Tensor,
                          rest_rates: Optional[Tensor], f0: Optional[Tensor] = None
                          ) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """``LinearPriorModel.advance`` as ``roll``'s checkpoint runs it (``recompute``): with gradients on
    (the recomputation in the backward pass) the step with its whole graph; with them off (the
    forward pass) the step's values alone, its network still differentiated for ∂E/∂z and ∂S/∂z
    but nothing kept."""
    if torch.is_grad_enabled():
        return model.advance(u, v, a, G, H, h, f1, edge_index, node_type, ref_pos, True, rest_rates, f0)
    with torch.enable_grad():
        out = model.advance(u.detach(), v.detach(), a.detach(), G.detach(), H.detach(), h.detach(), f1,
                            edge_index, node_type, ref_pos, False,
                            None if rest_rates is None else rest_rates.detach(), f0)
    return tuple(x.detach() for x in out)


class Phases(NamedTuple):
    """The schedule of ``train_linear_prior``, from ``cfg.train``: the epochs of its three phases
    and how its rollouts are cut and scaled."""

    fit: int        #: train.epochs: epochs on the exact remainders (0: a fine-tune from train.init)
    rollout: int    #: train.rollout_epochs: epochs on rollouts (windows or whole)
    whole: int      #: train.whole_epochs: epochs on whole trajectories at a restarted rate
    window: int     #: train.rollout_window: steps per rollout window (0: whole rollouts)
    scale: str      #: train.rollout_scale: one of ROLLOUT_SCALES
    weights: Tuple[float, float, float] = (1.0, 1.0, 1.0)   #: train.rollout_weights: q, v, σ in the rollout loss
    stress_weight: float = 0.0   #: train.stress_remainder_weight: H against the exact one at true states
    fit_target: str = "exact"    #: train.fit_target: one of FIT_TARGETS


#: ``train.prior_alone_candidate`` values (``prior_alone_candidate``)
PRIOR_ALONE = ("auto", "true", "false")


def prior_alone_candidate(tc, settings: dict) -> bool:
    """``train.prior_alone_candidate``: whether the prior alone (its remainders zero, the network
    not evaluated; ``rollout.remainders = zero``) is the first candidate for the best checkpoint,
    validated before any epoch, so that an epoch is kept only where it beats it. auto (default):
    where the prior's law is learned from the data (``model.prior_material = learned``: the prior
    alone is then itself a model learned from the data, and a network on top of it may only make
    it worse, as on session 80's liver law); true: every prior model; false: never. A one-line
    ``ConfigError`` for anything else."""
    value = OmegaConf.select(tc, "prior_alone_candidate", default="auto")
    value = {True: "true", False: "false"}.get(value, value) if isinstance(value, bool) else value
    if value not in PRIOR_ALONE:
        raise ConfigError(f"train.prior_alone_candidate = {value!r}, expected " + " | ".join(PRIOR_ALONE))
    return value == "true" or (value == "auto" and settings.get("law_material") == "learned")


def training_phases(tc, none_ok: bool = False) -> Phases:
    """``Phases`` from ``cfg.train``: each phase's epochs >= 0 and at least one epoch in all (the
    fit phase may be skipped: a fine-tune of rollouts from ``train.init``; all of them where
    ``none_ok``: the prior alone is the model, ``prior_alone_candidate``), the window >= 0 and
    the scale one of ``ROLLOUT_SCALES``, else a one-line ``ConfigError``. Checked before the
    dataset is read."""
    fit = int(tc.epochs)
    roll = int(OmegaConf.select(tc, "rollout_epochs", default=0))
    whole = int(OmegaConf.select(tc, "whole_epochs", default=0))
    if roll < 0:
        raise ConfigError(f"train.rollout_epochs = {roll}, expected >= 0")
    if whole < 0:
        raise ConfigError(f"train.whole_epochs = {whole}, expected >= 0")
    if fit < 0 or fit + roll + whole < (0 if none_ok else 1):
        raise ConfigError(f"train.epochs = {fit}, train.rollout_epochs = {roll}"
                          + (f", train.whole_epochs = {whole}" if whole else "")
                          + ": expected >= 0 each and >= 1 together")
    window = int(OmegaConf.select(tc, "rollout_window", default=0))
    if window < 0:
        raise ConfigError(f"train.rollout_window = {window}, expected >= 0 (0: whole rollouts)")
    scale = str(OmegaConf.select(tc, "rollout_scale", default="data"))
    if scale not in ROLLOUT_SCALES:
        raise ConfigError(f"train.rollout_scale = '{scale}', expected one of: {' | '.join(ROLLOUT_SCALES)}")
    weights = rollout_weights(tc)
    raw = OmegaConf.select(tc, "stress_remainder_weight", default=0.0)
    try:
        stress_weight = float(raw or 0.0)
    except (TypeError, ValueError):
        stress_weight = math.nan
    if not (math.isfinite(stress_weight) and stress_weight >= 0):
        raise ConfigError(f"train.stress_remainder_weight = {raw}, expected a number >= 0 (0: off)")
    target = str(OmegaConf.select(tc, "fit_target", default="exact"))
    if target not in FIT_TARGETS:
        raise ConfigError(f"train.fit_target = '{target}', expected one of: {' | '.join(FIT_TARGETS)}")
    return Phases(fit, roll, whole, window, scale, weights, stress_weight, target)


def rollout_weights(tc) -> Tuple[float, float, float]:
    """``train.rollout_weights``: the weights of q, v and σ's terms in the rollout loss (each
    group's mean squared error relative to its scale, ``train.rollout_scale``), three finite
    numbers >= 0, not all 0, else a one-line ``ConfigError``. Default 1, 1, 1."""
    raw = OmegaConf.select(tc, "rollout_weights", default=None)
    if raw is None:
        return (1.0, 1.0, 1.0)
    shown = OmegaConf.to_container(raw) if OmegaConf.is_config(raw) else raw
    try:
        w = tuple(float(x) for x in shown)
    except (TypeError, ValueError):
        w = ()
    if len(w) != 3 or not all(math.isfinite(x) and x >= 0 for x in w) or sum(w) == 0:
        raise ConfigError(f"train.rollout_weights = {shown}, expected three numbers >= 0 for q, v, sigma "
                          "(not all 0), e.g. [1, 1, 2]")
    return w


def train_linear_prior(cfg, data, hparams: dict, dtype_name: str, structure: str, ckpt_path: Path,
                       out_dir: Path, dist, phases: Phases, init_ckpt: dict | None = None) -> Path:
    """``thermognn train`` with ``model.prior=linear`` (module docstring): ``train.epochs`` fit
    epochs on the exact remainders, then ``train.rollout_epochs`` epochs on rollouts (windows of
    ``train.rollout_window`` steps, or whole), then ``train.whole_epochs`` epochs on whole
    trajectories at a restarted rate (``train.whole_lr``; session 17: after windows this lowered the
    block's σ by 15 %); best
    checkpoint by the validation rollout error, ``model.last.ckpt`` after every epoch and every
    ``train.checkpoint_minutes`` within one (resumed, an interrupted epoch at its next batch with
    the same order, rates and random streams; under torchrun by as many processes),
    ``metrics.csv`` with the phase of each epoch. Validation runs every epoch; with
    ``train.patience`` p > 0 a phase ends after p epochs without improving on its own best (the
    fit phase hands over to the rollouts, the rollouts to the whole trajectories, the last phase
    ends training). ``init_ckpt``: ``train.init``'s checkpoint as ``train`` already read it (None:
    read here).

    Under torchrun (``dist``: ``loop._Dist``) each of the W processes takes every W-th sample of
    an epoch's shuffled order (the same order everywhere: one seeded generator) and the gradients
    are averaged before clipping, so W processes with ``train.batch_size`` k take the steps one
    process takes with batch size W k. Rank 0 writes the checkpoints, metrics and the test table.
    ``phases``: the schedule, as ``training_phases`` checked it."""
    from thermognn.core.config import project_path

    from .checkpoint import last_path, load_checkpoint, save_checkpoint, torch_dtype
    from .data import compute_stats
    from .evaluation import linear_validation_error
    from .loop import (EpochCheckpoints, _base_checkpoint, _progress, _sel, _tensorboard, _write_metrics,
                       identity_changes, print_rrmse_table, training_identity)
    from .model import build_model, parameter_count
    from .rollout import rollout_errors, validation_error

    tc, ds = cfg.train, data.dataset
    dtype = torch_dtype(dtype_name)
    seed = int(_sel(cfg, "seed", 0))
    fit_epochs, roll_epochs, whole_epochs, window, scale, weights, stress_weight, fit_target = phases
    roll_end = fit_epochs + roll_epochs
    epochs = roll_end + whole_epochs
    settings = prior_settings(cfg.model)
    if int(settings.get("law_substeps", 1)) > 1:
        raise ConfigError(f"model.prior_substeps = {settings['law_substeps']}: training fits the law prior's one step of "
                          f"dt between stored states; train with 1 and step the trained law in sub-steps with "
                          f"rollout.prior_substeps at evaluate and export")
    if "law" in settings and getattr(ds, "substeps", 1) > 1 and dist.main:
        print(f"train: {ds.path} was solved with {ds.substeps} FE steps a stored step (scene.time.substeps); the law "
              f"prior fits one step of dt between stored states, its remainders take the difference; "
              f"rollout.prior_substeps={ds.substeps} steps the law as the data were solved (evaluate, export)")
    torch.manual_seed(seed)
    net = build_model(hparams, dtype)
    model = prior_model(net, settings, ds, ds.dt)
    train_trajs, val_trajs = data.of("train"), data.of("val")
    graph = data.graph
    law_left_out = None
    if settings.get("law_material") == "learned":   # the law itself first: fitted, read from train.init, or kept
        law_left_out, prony = learned_law_of(model, train_trajs, out_dir, ds, tc, init_ckpt, dist,
                                             settings.get("law_prony") == "learned", bool(settings.get("law_convex")))
        if prony is not None:                    # the prior again, with its fitted Prony terms
            settings["law_prony"] = [list(t) for t in prony]
            law_state = model.prior.learned_law.state_dict()
            model = prior_model(net, settings, ds, ds.dt)
            model.prior.learned_law.load_state_dict(law_state)
    G_true, H_true = exact_remainders(model, train_trajs)
    fit_trajs = train_trajs
    if law_left_out is not None:                 # the learned law's residual is what the network learns
        keep = [i for i, t in enumerate(train_trajs) if t.name not in law_left_out]
        fit_trajs, G_true, H_true = [train_trajs[i] for i in keep], [G_true[i] for i in keep], [H_true[i] for i in keep]
    elif "law" in settings:                        # the data's own step: its remainders vanish but where the FE cut steps
        fit_trajs, G_true, H_true, cut = law_fit_trajectories(train_trajs, G_true, H_true, model.prior.free_nodes())
        if cut and dist.main:
            print(f"train: the law prior leaves {len(cut)} of {len(train_trajs)} training trajectories out of the fit "
                  f"phase, where the FE cut its steps (the data's step is not one Newmark step of dt there; exact G "
                  f"up to {max(r for _, r in cut):.2e} of the loads): " + ", ".join(n for n, _ in cut))
    if fit_target == "budget" and "law" not in settings:
        raise ConfigError("train.fit_target = budget needs model=law_prior (model.prior_law=true): only the law "
                          "prior has a Newton budget whose misses the network can learn")
    if fit_target == "budget" and "law_max" in settings:
        raise ConfigError(f"train.fit_target = budget with model.prior_newton_max = {settings['law_max']}: the fit "
                          f"learns what a fixed budget leaves (set model.prior_newton_max=null)")
    if fit_target == "budget" and fit_epochs > 0:   # what the Newton budget leaves, not the converged law's round-off
        n_fit = len(fit_trajs)
        fit_trajs, G_true, H_true, unreached = budget_fit_trajectories(model, fit_trajs, H_true)
        if dist.main and unreached:
            print(f"train: no load lands the {settings['law']}-iteration step on the data in {len(unreached)} "
                  f"of {n_fit} training trajectories (the corrections left up to {max(m for _, m in unreached):.1e} "
                  f"of the largest displacement); the fit leaves them out: " + ", ".join(n for n, _ in unreached))
        if dist.main:
            free = model.prior.free_nodes()
            ratio = float(torch.cat([g[:, free] for g in G_true]).pow(2).mean().sqrt()
                          / torch.cat([t.force.double()[:, free] for t in fit_trajs]).pow(2).mean().sqrt())
            print(f"train: the fit phase learns what {settings['law']} Newton iteration(s) a step leave: RMS G "
                  f"{ratio:.3e} of the loads ({len(fit_trajs)} trajectories)")
    # with correction inputs the fit shows the network the model's own step ends from the data's
    # states (w of the budgeted step, not the converged one), and its normalisation is of those
    fit_inputs, seen_trajs = None, train_trajs
    if model.correction and fit_epochs > 0:
        fit_inputs = [model.step_inputs(t.z, t.force, g) for t, g in zip(fit_trajs, G_true)]
        seen_trajs = [SimpleNamespace(z=x, force=t.force) for t, x in zip(fit_trajs, fit_inputs)]
    elif model.correction:
        seen_trajs = [SimpleNamespace(z=model.trajectory_inputs(t.z), force=t.force) for t in train_trajs]
    stats = compute_stats(seen_trajs, graph, ds.dt, hparams)
    floor = law_scale_floor(train_trajs, model.prior.free_nodes(), model.dim) if "law" in settings else None
    stats["dzdt_std"] = remainder_scale(stats, G_true, H_true, model.prior.free_nodes(), floor)
    net.set_stats(stats)
    with torch.no_grad():                        # start at (1 % from) the linearised FE model
        for p in [*net.decoder.net[-1].parameters(), *net.port.parameters(),
                  *(p for dec in net.edge_decoders for p in dec.net[-1].parameters())]:
            p.mul_(START_SCALE)
    if _sel(tc, "init", None):                   # warm start from a checkpoint of the same model (its prior's
        #                                              stress law may differ: it holds no weights)
        src = init_ckpt if init_ckpt is not None else load_checkpoint(project_path(str(tc.init)))
        grown = grown_blocks(src.get("hparams") or {}, hparams)   # or this model with more processor blocks
        # (nor whether it stepped its prior alone: a law-only checkpoint starts a network on its law)
        weights_of = lambda prior: {k: v for k, v in (prior or {}).items()  # noqa: E731
                                    if k not in ("stress", "remainders")}
        if weights_of(src.get("prior")) != weights_of(settings) or (src.get("hparams") or {}) | (
                {"message_passing": hparams["message_passing"]} if grown else {}) != hparams:
            raise ConfigError(f"train.init = '{tc.init}': not a model.prior=linear checkpoint of this model "
                              "(or of it with fewer processor blocks)")
        if grown:
            load_grown(model, src["state_dict"], grown)
        else:
            model.load_state_dict(src["state_dict"])
        stats = {k: v.clone() for k, v in src["stats"].items()}
    base = {**_base_checkpoint(cfg, data, hparams, dtype_name, structure, stats), "prior": settings}
    identity = {**training_identity(cfg, hparams, dtype_name), "prior": settings,
                "rollout_lr": float(_sel(tc, "rollout_lr", 1e-3)),
                "rollout_lr_decay": float(_sel(tc, "rollout_lr_decay", 0.01)),
                **({"rollout_window": window} if window else {}),
                **({"rollout_scale": scale} if scale != "data" else {}),     # older runs resume
                **({"rollout_weights": list(weights)} if weights != (1.0, 1.0, 1.0) else {}),
                **({"stress_remainder_weight": stress_weight} if stress_weight else {}),
                **({"fit_target": fit_target} if fit_target != "exact" else {}),
                **({"whole_lr": float(_sel(tc, "whole_lr", 1e-4)), "whole_lr_decay": float(_sel(tc, "whole_lr_decay", 0.1))}
                   if whole_epochs else {})}

    fit = _FitPhase(model, fit_trajs, G_true, H_true, float(_sel(tc, "noise", 0.1)),
                    float(_sel(tc, "lambda_data", 100.0)), float(_sel(tc, "lambda_degeneracy", 1.0)), fit_inputs)
    copies: Dict[int, object] = {}

    def mesh(k: int):
        """k disjoint copies of the mesh graph (made once per batch size)."""
        if k not in copies:
            copies[k] = graph.copies(k)
        return copies[k]

    recompute = bool(_sel(tc, "rollout_recompute", False))
    rollouts = _RolloutPhase(model, train_trajs, window, scale, recompute, weights, stress_weight, mesh)
    # phase 3: whole trajectories; the rollout phase's own where its samples already are (no windows)
    whole = (rollouts if not whole_epochs or all(s == 0 for _, s in rollouts.samples)
             else _RolloutPhase(model, train_trajs, 0, scale, recompute, weights, stress_weight, mesh))
    batch_size = max(1, int(tc.batch_size))

    def optimizer(epoch: int) -> torch.optim.Adam:
        lr = (float(tc.lr) if epoch < fit_epochs else identity["rollout_lr"] if epoch < roll_end
              else identity["whole_lr"])
        return torch.optim.Adam(net.parameters(), lr=lr)

    gen = torch.Generator().manual_seed(seed)             # on the CPU, whatever train.device

    def resume_state(epoch_done: int, val: float, resume_at: int, **extra) -> dict:
        """``model.last.ckpt``'s contents: everything a resumed run needs to go on exactly."""
        return {**base, "state_dict": model.state_dict(), "epoch": epoch_done, "val_error": val,
                "resume_at": resume_at, "optimizer": opt.state_dict(), "history": history,
                "best_val": best_val, "phase_best": phase_best, "stale_rounds": stale,
                "rng": {"generator": gen.get_state(), "torch": torch.get_rng_state()},
                "identity": identity, **extra}

    start, history, best_val = 0, [], math.inf
    mid = None                                   # an interrupted epoch's place (checkpoint "mid_epoch")
    saves = EpochCheckpoints(_sel(tc, "checkpoint_minutes", 10), dist)
    patience = int(_sel(tc, "patience", 0))
    phase_best, stale = math.inf, 0              # early stopping ends a phase (the fit phase: on to rollouts)
    opt = optimizer(0) if epochs else None       # (none without epochs: the prior alone is the model)
    last = last_path(ckpt_path)
    if bool(_sel(tc, "resume", True)) and last.exists() and epochs > 0:
        state = load_checkpoint(last)
        if identity_changes(state.get("identity") or {}, identity):
            if dist.main:
                print(f"{last}: configuration changed; training from scratch")
        else:
            model.load_state_dict(state["state_dict"])
            start, history, best_val = (int(state.get("resume_at", state["epoch"])), list(state["history"]),
                                        float(state["best_val"]))
            phase_best, stale = float(state.get("phase_best", math.inf)), int(state.get("stale_rounds", 0))
            mid = state.get("mid_epoch")                             # written within epoch `start`
            if mid:
                order, next_batch, _ = saves.resume(mid, last, start + 1)
            opt = optimizer(start if mid else start - 1)             # the phase that wrote it
            opt.load_state_dict(state["optimizer"])
            gen.set_state(state["rng"]["generator"])
            torch.set_rng_state(state["rng"]["torch"])
            if dist.main:
                print(f"resuming from {last} " + (f"within epoch {start + 1}, at batch {next_batch + 1} of "
                                                   f"{len(order) // dist.world // max(1, int(tc.batch_size))}"
                                                   if mid else f"at epoch {start}"))
    more = f" + {whole_epochs} whole-trajectory epochs" if whole_epochs else ""
    if dist.main:
        print(f"train (model.prior=linear): {len(train_trajs)} train / {len(val_trajs)} val / "
              f"{len(data.split['test'])} test trajectories, {fit_epochs} fit + {roll_epochs} rollout epochs{more}, "
              f"{parameter_count(model)} parameters, {model.prior.free_index.numel()} free DOFs"
              + (f", {dist.world} processes" if dist.world > 1 else "")
              + linear_validation_error(data, val_trajs, corotated="corotated" in settings))

    if prior_alone_candidate(tc, settings) and start == 0 and best_val == math.inf:
        t0 = time.perf_counter()
        model.eval()
        model.learned = False                    # G = H = 0, the network not evaluated
        best_val = validation_error(model, graph, val_trajs, data.layout, ds.dt)
        model.learned = True
        if dist.main:
            save_checkpoint({**base, "prior": {**settings, "remainders": "zero"}, "state_dict": model.state_dict(),
                             "epoch": 0, "val_error": best_val}, ckpt_path)
            print(f"train: the prior alone (its remainders zero) validates at {best_val:.4e} "
                  f"({time.perf_counter() - t0:.0f} s): {ckpt_path.name}"
                  + (" until an epoch beats it " if epochs else ", the model (no epochs) ")
                  + "(train.prior_alone_candidate)", flush=True)
    tb = _tensorboard(_sel(tc, "tensorboard", "auto"), out_dir / "tensorboard") if dist.main else None
    fields = ["epoch", "phase", "lr", "loss", "data_loss", "degeneracy_loss", "val_error", "seconds"]
    with _progress(disable=not dist.main) as progress:
        task = progress.add_task("train", total=epochs, completed=start, info="")
        epoch = start
        while epoch < epochs:
            t0 = time.perf_counter() - (mid["seconds"] if mid else 0.0)
            if (epoch == fit_epochs or (whole_epochs and epoch == roll_end)) and not mid:
                opt = optimizer(epoch)                               # phases 2 and 3 start their own Adam
                phase_best, stale = math.inf, 0
            model.train()
            if epoch < fit_epochs:          # phase 1: one step from the data's states, exact remainders
                phase, items, base_lr, decay = "fit", fit.samples, float(tc.lr), float(_sel(tc, "lr_decay", 0.1))
                progress_at = lambda b: (epoch + b / nb) / fit_epochs  # noqa: E731
            elif epoch < roll_end:          # phase 2: rollouts (or windows) through the linear solves
                phase, items, base_lr, decay = ("rollout", rollouts.samples, identity["rollout_lr"],
                                                identity["rollout_lr_decay"])
                progress_at = lambda b: (epoch - fit_epochs + b / nb) / roll_epochs  # noqa: E731
            else:                           # phase 3: whole trajectories from rest, at a restarted rate
                phase, items, base_lr, decay = ("whole", whole.samples, identity["whole_lr"],
                                                identity["whole_lr_decay"])
                progress_at = lambda b: (epoch - roll_end + b / nb) / whole_epochs  # noqa: E731
            if mid:                         # an interrupted epoch goes on where its checkpoint left it
                order, b0, (total, data_total, deg_total) = saves.resume(mid, last, epoch + 1)
                mid = None
            else:
                order = torch.randperm(len(items), generator=gen, device="cpu").tolist()
                b0, total, data_total, deg_total = 0, 0.0, 0.0, 0.0
            perm = order[dist.rank:len(order) // dist.world * dist.world:dist.world]   # this process's share
            nb = max(1, len(perm) // batch_size)
            saves.start()
            for b in range(b0, nb):
                for group in opt.param_groups:
                    group["lr"] = _lr(base_lr, decay, progress_at(b))
                chosen = [items[j] for j in perm[b * batch_size:(b + 1) * batch_size]]
                g = mesh(len(chosen))
                try:
                    loss, data_loss, deg = (fit.loss(chosen, g, gen) if phase == "fit" else
                                            (rollouts if phase == "rollout" else whole).loss(chosen, g))
                except RuntimeError as exc:                  # the corotated step met a non-finite state
                    if DIVERGED not in str(exc):
                        raise
                    raise DataError(f"{data.path}: training diverged at epoch {epoch + 1}, batch {b + 1} ({phase}: "
                                    f"{str(exc).strip().splitlines()[-1]}); lower train.lr or train.rollout_lr "
                                    f"({last.name} resumes from its last write)") from None
                opt.zero_grad(set_to_none=True)
                loss.backward()
                dist.average_gradients(net)
                torch.nn.utils.clip_grad_norm_(net.parameters(), CLIP)
                opt.step()
                total, data_total, deg_total = total + float(loss.detach()), data_total + data_loss, deg_total + deg
                if saves.due(b + 1 < nb):
                    place = saves.place(order, b + 1, [total, data_total, deg_total],
                                        seconds=time.perf_counter() - t0)
                    if dist.main:
                        save_checkpoint(resume_state(epoch, history[-1]["val_error"] if history else math.nan,
                                                     epoch, mid_epoch=place), last)
                        print(f"epoch {epoch + 1} ({phase}): batch {b + 1} of {nb}, loss {total / (b + 1):.3e}; "
                              f"{last.name} written (train.checkpoint_minutes)", flush=True)
            total, data_total, deg_total = dist.mean([total, data_total, deg_total])
            if phase != "fit":                  # the rollout or whole phase's samples a crushed cell left out
                rolled = rollouts if phase == "rollout" else whole
                if rolled.left_out and dist.main:
                    print(f"epoch {epoch + 1} ({phase}): {rolled.left_out} of {nb * batch_size} samples left out of the "
                          f"loss: their rollout turned a cell inside out (det F <= 0)", flush=True)
                rolled.left_out = 0
            if not math.isfinite(total):
                raise DataError(f"{data.path}: training diverged (non-finite loss at epoch {epoch + 1}, {phase}); "
                                f"lower train.lr or train.rollout_lr")
            model.eval()
            model.anchor(graph.edge_index, graph.node_type, graph.ref_pos)      # stepped as it will be used
            val = validation_error(model, graph, val_trajs, data.layout, ds.dt)
            model.anchored = False
            done = epoch + 1
            row = {"epoch": done, "phase": phase, "lr": opt.param_groups[0]["lr"], "loss": total / nb,
                   "data_loss": data_total / nb, "degeneracy_loss": deg_total / nb, "val_error": val}
            improved = val < best_val or best_val == math.inf
            best_val = min(val, best_val)
            stale = 0 if val < phase_best else stale + 1
            phase_best = min(val, phase_best)
            epoch = done
            if patience > 0 and stale >= patience and done < epochs:    # early stopping ends the phase
                epoch = fit_epochs if done < fit_epochs else roll_end if done < roll_end else epochs
                if dist.main:
                    print(f"early stopping: the {phase} phase ends at epoch {done} "
                          f"(no improvement in {patience} epochs)")
            if improved and dist.main:
                save_checkpoint({**base, "state_dict": model.state_dict(), "epoch": done, "val_error": val},
                                ckpt_path)
            row["seconds"] = time.perf_counter() - t0
            history.append(row)
            if dist.main:
                save_checkpoint(resume_state(done, val, epoch), last)
                _write_metrics(out_dir / "metrics.csv", history, fields)
            if tb is not None:
                for key, value in row.items():
                    if key not in ("epoch", "phase") and math.isfinite(value):
                        tb.add_scalar(f"train/{key}", value, done)
                tb.flush()
            progress.update(task, completed=epoch, info=f"{phase} loss {row['loss']:.3e} val {val:.3e}")
    if tb is not None:
        tb.close()
    dist.barrier()                                  # rank 0 has written its last checkpoint
    if not dist.main:
        return ckpt_path
    if not ckpt_path.exists():
        raise DataError(f"{ckpt_path}: no best checkpoint written (delete {last} and retrain)")
    from .checkpoint import model_from_checkpoint

    kept = load_checkpoint(ckpt_path)
    if (kept.get("prior") or {}).get("remainders") == "zero" and history:
        tried = min((r["val_error"] for r in history), default=math.nan)
        print(f"train: no epoch beat the prior alone on validation ({tried:.4e} at best against "
              f"{kept['val_error']:.4e}): {ckpt_path.name} steps the prior alone, its remainders zero; "
              f"{last.name} holds the last epoch's network")
    best = model_from_checkpoint(kept, ds)
    mean = rollout_errors(best, graph, data.of("test"), data.layout, ds.dt)[0]
    print_rrmse_table(f"test rollout RRMSE ({len(data.split['test'])} trajectories)", {"test": mean})
    return ckpt_path
