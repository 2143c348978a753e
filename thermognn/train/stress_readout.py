"""A stress readout: the stress as a linear function of the displacements near each node, fitted to
the training data by least squares (``model.stress_readout``: its reach in graph hops).

Where the data's stress is an elastic (possibly geometrically linearised) function of the
displacement, σ is not an independent state but a constitutive function of q. A network that
integrates dσ/dt accumulates its rate errors over the rollout; reading σ off the predicted
positions does not. The readout is the discrete form of σ = C : ε(u) that a finite-element model
evaluates at its nodes: a linear stencil over the nodes within ``hops`` mesh edges::

    σ_i = Σ_{j ∈ N_k(i)} W_{c(i), j-i} u_j        u = q - X   [m],  σ  [Pa]

The weights W depend on the node's *neighbourhood shape* c(i): the set of reference offsets
X_j - X_i of its stencil, so nodes at the same place relative to the boundary share them (on a
structured grid, every interior node; near a face, edge or corner, one class per distinct shape).
A mesh whose neighbourhoods do not repeat has as many classes as nodes, and the fit refuses it
(it would interpolate, not learn). With u = 0 the readout gives σ = 0: the unloaded body is
stress-free, as the data's first state must be (the fit checks).

The readout is fitted after training to the network's own rollouts of the training trajectories
(``fit_readout_to_rollouts``: predicted positions against the data's stress), and a rollout reports
its stress in place of the network's integrated σ (``rollout``; the state stepped keeps the
network's). TIGNN beam (docs/accuracy.md, session 52): the data's nodal stress is such a function
of the *true* displacement within 3 hops to 1.1 % on the test trajectories, but fitted to true
positions the stencil amplifies a rollout's small nodal errors; fitted to the rollouts it reads
σ to 7.1 % from a network whose own σ was 20-30 % off.
"""

from __future__ import annotations

from typing import Dict, List, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..core.errors import DataError


#: ridge of the least-squares fit, relative to the equations' count in columns scaled to O(1):
#: keeps the weights of nearly collinear stencil displacements finite (TIGNN beam: with 0, weights of
#: 1e34 on round-off-sized clamped displacements; test error 1.12 % at 1e-12, 1.32 % at 1e-11)
RIDGE = 1e-12


class StressReadout(nn.Module):
    """σ [N, S] = readout(u [N, 3]) for the mesh it was fitted on (N nodes).

    Buffers (shapes from ``spec``, filled by ``fit_stress_readout`` or a checkpoint)::

        stencil     [N, K]       node indices of each node's stencil, padded with N (a zero row)
        node_class  [N]          its neighbourhood-shape class
        weight      [C, 3 K, S]  per class: stencil displacement (K nodes x 3, node-major) -> σ
    """

    def __init__(self, nodes: int, width: int, classes: int, columns: List[int]) -> None:
        super().__init__()
        self.nodes = int(nodes)
        self.columns: List[int] = [int(c) for c in columns]
        kept = self.nodes > 0            # an empty readout (off) is not part of the checkpoint
        self.register_buffer("stencil", torch.full((self.nodes, int(width)), self.nodes, dtype=torch.long), kept)
        self.register_buffer("node_class", torch.zeros(self.nodes, dtype=torch.long), kept)
        self.register_buffer("weight", torch.zeros(int(classes), 3 * int(width), len(self.columns)), kept)

    def forward(self, u: Tensor) -> Tensor:
        """Stress [N, S] (Pa, the state's stress columns ``columns``) of the displacement u [N, 3] (m)."""
        padded = torch.cat([u, torch.zeros(1, 3, dtype=u.dtype, device=u.device)], 0)   # [N + 1, 3]
        near = padded.index_select(0, self.stencil.reshape(-1)).reshape(self.nodes, -1)   # [N, 3 K]
        w = self.weight.index_select(0, self.node_class).to(u.dtype)                      # [N, 3 K, S]
        return torch.bmm(near.unsqueeze(1), w).squeeze(1)                                  # [N, S]

    def fitted_weights(self) -> int:
        """How many weights the fit set (the padding's excluded): the readout's parameter count."""
        real = (self.stencil < self.nodes).sum(1)                                       # [N] stencil sizes
        per_class = torch.zeros(self.weight.shape[0], dtype=torch.long).scatter_reduce(
            0, self.node_class, real, "amax", include_self=True)
        return int(per_class.sum()) * 3 * len(self.columns)


def stencils(ref_pos: np.ndarray, edge_index: np.ndarray, hops: int) -> tuple[list[list[int]], np.ndarray]:
    """Each node's stencil (the nodes within ``hops`` edges, ordered by reference offset) and its
    neighbourhood-shape class [N] (nodes whose stencils have the same offsets, to 1e-6 of the
    mean edge length, share one)."""
    n = len(ref_pos)
    nbr: list[set[int]] = [set() for _ in range(n)]
    for a, b in edge_index.T:
        nbr[int(a)].add(int(b))
        nbr[int(b)].add(int(a))
    h = float(np.mean(np.linalg.norm(ref_pos[edge_index[0]] - ref_pos[edge_index[1]], axis=1)))
    out, classes, keys = [], np.zeros(n, dtype=np.int64), {}
    for i in range(n):
        near, front = {i}, {i}
        for _ in range(hops):
            front = {j for f in front for j in nbr[f]} - near
            near |= front
        offsets = sorted((tuple(np.round((ref_pos[j] - ref_pos[i]) / h, 6)), j) for j in near)
        classes[i] = keys.setdefault(tuple(o for o, _ in offsets), len(keys))
        out.append([j for _, j in offsets])
    return out, classes


def check_determined(ref_pos: np.ndarray, edge_index: np.ndarray, snapshots: int, hops: int,
                     source: str = "dataset") -> tuple[list[list[int]], np.ndarray]:
    """``stencils`` of ``hops``, after checking that ``snapshots`` states give every neighbourhood
    shape at least as many equations as it has weights (else a DataError naming ``source``: the
    fit would interpolate). Training calls it before it starts, so a refusal costs nothing."""
    if hops < 1:
        raise DataError(f"{source}: model.stress_readout = {hops}, expected the stencil's reach in hops (>= 1) or 0 (off)")
    stencil, classes = stencils(ref_pos, edge_index, int(hops))
    for c in range(int(classes.max()) + 1):
        nodes = np.flatnonzero(classes == c)
        rows, cols = snapshots * len(nodes), 3 * len(stencil[nodes[0]])
        if rows < cols:
            raise DataError(f"{source}: model.stress_readout = {hops}: {len(nodes)} node(s) of one neighbourhood "
                            f"shape give {rows} equations for {cols} weights (a mesh whose neighbourhoods "
                            "do not repeat, or too few training snapshots); use fewer hops or 0")
    return stencil, classes


def fit_stress_readout(ref_pos: Tensor, edge_index: Tensor, trajectories: Sequence[Tensor],
                       columns: Sequence[int], hops: int, source: str = "dataset") -> tuple[StressReadout, Dict]:
    """Least-squares fit of the readout to the states z [T, N, D] of ``trajectories`` (the training
    split): σ = z[..., columns] against u = z[..., :3] - X. Returns the readout and a report
    {"hops", "classes", "weights", "fit_error"} (fit_error: relative L2 over the fitted snapshots).
    Raises DataError (naming ``source``) where the fit is underdetermined or the data's
    stress-free state is not at u = 0."""
    X = ref_pos.detach().cpu().double().numpy()
    z = np.concatenate([t.detach().cpu().double().numpy() for t in trajectories])        # [S, N, D]
    cols = [int(c) for c in columns]
    u, sigma = z[:, :, :3] - X, z[:, :, cols]                                             # [S, N, 3], [S, N, C]
    rest = np.linalg.norm(u, axis=(1, 2)) < 1e-12 * (1.0 + np.abs(X).max())
    if rest.any() and np.abs(sigma[rest]).max() > 1e-9 * max(np.abs(sigma).max(), 1e-300):
        raise DataError(f"{source}: the stress is not zero where the displacement is (u = 0): "
                        "model.stress_readout needs a stress-free reference state")
    reach = float(np.abs(u).max())                                                      # [m]
    stencil, classes = check_determined(X, edge_index.detach().cpu().numpy(), len(z), hops, source)
    n, width = len(X), max(len(s) for s in stencil)
    readout = StressReadout(n, width, int(classes.max()) + 1, cols)
    weight = np.zeros(tuple(readout.weight.shape))
    predicted = np.zeros_like(sigma)
    for c in range(weight.shape[0]):
        nodes = np.flatnonzero(classes == c)
        st = np.array([stencil[i] for i in nodes])                                       # [m, k]
        a = u[:, st].reshape(len(z) * len(nodes), -1)                                    # [S m, 3 k]
        b = sigma[:, nodes].reshape(len(z) * len(nodes), -1)                             # [S m, C]
        scale = np.abs(a).max(0)                                                         # columns to O(1)
        still = scale <= 1e-9 * reach                                    # clamped: round-off, weight 0
        scale[still] = 1.0
        an = np.where(still, 0.0, a / scale)
        w = np.linalg.solve(an.T @ an + RIDGE * len(an) * np.eye(an.shape[1]), an.T @ b)
        weight[c, : a.shape[1]] = np.where(still[:, None], 0.0, w / scale[:, None])
        predicted[:, nodes] = (a @ weight[c, : a.shape[1]]).reshape(len(z), len(nodes), -1)
    with torch.no_grad():
        readout.stencil.copy_(torch.tensor([s + [n] * (width - len(s)) for s in stencil]))
        readout.node_class.copy_(torch.from_numpy(classes))
        readout.weight.copy_(torch.from_numpy(weight))
    moving = ~rest
    err = float(np.mean([np.linalg.norm(p - s) / np.linalg.norm(s)
                         for p, s in zip(predicted[moving], sigma[moving]) if np.linalg.norm(s) > 0]))
    return readout, {"hops": int(hops), "classes": int(weight.shape[0]),
                     "weights": readout.fitted_weights(), "fit_error": err}


def readout_spec(readout: StressReadout, hops: int) -> Dict:
    """The readout's shape for a checkpoint's hyperparameters (TIGNN's ``stress_readout``)."""
    return {"hops": int(hops), "nodes": readout.nodes, "width": int(readout.stencil.shape[1]),
            "classes": int(readout.weight.shape[0]), "columns": list(readout.columns)}


def with_stress_readout(ckpt: Dict, readout: StressReadout, hops: int) -> Dict:
    """A TIGNN checkpoint ``ckpt`` with ``readout`` attached (its hyperparameters and weights): the
    trained network's positions and velocities, the stress read off the positions."""
    hparams = {**ckpt["hparams"], "stress_readout": readout_spec(readout, hops)}
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith("readout.")}
    state.update({f"readout.{k}": v.detach().cpu() for k, v in readout.state_dict().items()})
    return {**ckpt, "hparams": hparams, "state_dict": state}


def fit_readout_to_rollouts(model: nn.Module, data, trajectories, hops: int,
                            roll=None) -> tuple[StressReadout, Dict]:
    """The readout fitted to the trained ``model``'s own rollouts of ``trajectories`` (the training
    split, ``TrajectoryTensors``): its predicted positions against the data's stress at each step.
    Fitted to the true positions instead, the readout's stencil (a strain: differences of nearby
    displacements) amplifies a rollout's small nodal errors: TIGNN beam, 1.1 % on true test
    positions, 64-87 % on a rollout's 0.6 % off (docs/accuracy.md, session 52). ``roll(model, t)``
    -> [S, N, D] rolls a trajectory out as the evaluation will (default: ``rollout`` from t's first
    state; the TIGNN beam benchmark imposes the clamped nodes' whole true state at every step, and
    its readout is fitted to such rollouts: 7.1 % against 9.0 % fitted to ``rollout``'s)."""
    from .rollout import rollout

    if roll is None:
        def roll(m, t):
            return rollout(m, data.graph, t.z[0], t.force, data.dt)

    layout = data.layout
    columns = list(range(*layout.slice("sigma").indices(layout.dim)))
    was = getattr(model, "use_readout", False)
    model.use_readout = False                            # the network's positions, whatever it reads
    try:
        rolled = []
        for t in trajectories:
            pred = roll(model, t).double()                                             # [S, N, D]
            pred[:, :, columns] = t.z[:, :, columns].double().to(pred.device)
            rolled.append(pred)
    finally:
        model.use_readout = was
    return fit_stress_readout(data.graph.ref_pos, data.graph.edge_index, rolled, columns, hops,
                              source=str(data.path))
