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

With ``symmetric`` (``model.stress_readout_symmetric``) the weights of mirror-image neighbourhoods
are mirror images: an isotropic solid on a mesh that a reflection or an axis swap g = (R, p)
maps onto itself (nodes X_p(i) = c + R (X_i - c) about the bounding box's centre c, edges onto
edges, clamped nodes onto clamped) has an equivariant stress, σ_p(i)(R u_p⁻¹) = R σ_i(u) Rᵀ. The
fit sees every training snapshot in each of these frames (``mirrored``), which makes its weights
equivariant exactly, and one neighbourhood shape per orbit of shapes (``shape_orbits``) holds the
readout's independent weights: the TIGNN beam's 6 x 6 cross-section has 8 such g, and its 3-hop
readout 30,636 weights instead of 182,880.

With ``load_hops`` (``model.stress_readout_load``) the applied nodal loads within that reach enter
the stencil too, σ_i = Σ_j W u_j + Σ_j V f_j [N]: the stress at a loaded face carries the load's
traction, which the displacements near a point load read poorly (TIGNN beam, 3 + 3 hops: σ 7.50 →
5.55 % on the reference metric, 3,084 more weights; 3 + 4 hops: 5.03 %, 17,172; docs/accuracy.md,
session 54). A load column that no training snapshot loads gets weight 0 and is not counted; a
load reach beyond ``hops`` tells nodes apart by both stencils' shapes (more shapes).

With ``modes`` (``model.stress_readout_modes``) u is first projected onto the span of the training
trajectories' r leading principal displacement fields (``displacement_modes``; in every mirror
frame when symmetric, so the span is closed under them): the stencil no longer amplifies the part
of a rollout's error that no training field has. A reduced basis, it helps only where the loads to
be read are combinations of the training ones (TIGNN beam, session 56: σ 4.41 → 2.71 % on the
reference split, whose test cases mirror training ones; 4.51 → 3.62 % with 3 of its 13 load
positions held out; 5.04 → 7.05 % with 5 held out, the two nearest the clamp among them);
``outside_modes`` measures how far a split's displacements lie outside the span (``evaluate``).

The readout is fitted after training to the network's own rollouts of the training trajectories
(``fit_readout_to_rollouts``: predicted positions against the data's stress), and a rollout reports
its stress in place of the network's integrated σ (``rollout``; the state stepped keeps the
network's). TIGNN beam (docs/accuracy.md, session 52): the data's nodal stress is such a function
of the *true* displacement within 3 hops to 1.1 % on the test trajectories, but fitted to true
positions the stencil amplifies a rollout's small nodal errors; fitted to the rollouts it reads
σ to 7.1 % from a network whose own σ was 20-30 % off.
"""

from __future__ import annotations

import itertools
from collections import Counter
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from ..core.errors import DataError


#: the stress columns' order (Voigt: s11 s22 s33 s12 s13 s23), the project's convention
VOIGT = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))

#: ridge of the least-squares fit, relative to the equations' count in columns scaled to O(1):
#: keeps the weights of nearly collinear stencil displacements finite (TIGNN beam: with 0, weights of
#: 1e34 on round-off-sized clamped displacements; test error 1.12 % at 1e-12, 1.32 % at 1e-11)
RIDGE = 1e-12

#: the ridges ``model.stress_readout_ridge=auto`` chooses among per neighbourhood shape: 0 and
#: 1e-10 ... 1e-2 in half decades (TIGNN beam, session 63: on true fields the end shapes chose
#: 1e-7-1e-6; fitted to a barely trained network's rollouts, many chose 1e-5, the top of a shorter list)
AUTO_RIDGES = (0.0,) + tuple(float(f"{10.0 ** e:.3g}") for e in np.arange(-10.0, -1.99, 0.5))


class StressReadout(nn.Module):
    """σ [..., N, S] = readout(u [..., N, 3], f [..., N, 3]) for the mesh it was fitted on (N nodes).

    Buffers (shapes from ``spec``, filled by ``fit_stress_readout`` or a checkpoint)::

        stencil       [N, K]              node indices of each node's stencil, padded with N (a zero row)
        load_stencil  [N, Kf]             with a load reach (``model.stress_readout_load``): the nodes
                                          whose applied load enters, padded likewise (Kf = 0: none)
        node_class    [N]                 its neighbourhood-shape class
        weight        [C, 3 K + 3 Kf, S]  per class: stencil displacement (K nodes x 3, node-major),
                                          then stencil load (Kf x 3) -> σ
        modes         [3 N, r]            with ``model.stress_readout_modes``: an orthonormal basis of the
                                          training displacements' span (node-major), u projected onto it
                                          before the stencil reads it (r = 0: none)
    """

    def __init__(self, nodes: int, width: int, classes: int, columns: List[int], independent: int = 0,
                 load_width: int = 0, modes: int = 0, mode_values: int = 0) -> None:
        super().__init__()
        self.nodes = int(nodes)
        self.independent = int(independent)      # weights that determine the rest (symmetric fit), 0: all
        self.columns: List[int] = [int(c) for c in columns]
        self.load_width = int(load_width)
        self.mode_count = int(modes)
        self.mode_values = int(mode_values)      # the basis's independent values (its parameter count)
        kept = self.nodes > 0            # an empty readout (off) is not part of the checkpoint
        self.register_buffer("stencil", torch.full((self.nodes, int(width)), self.nodes, dtype=torch.long), kept)
        self.register_buffer("load_stencil", torch.full((self.nodes, self.load_width), self.nodes, dtype=torch.long),
                             kept and self.load_width > 0)       # (checkpoints from before loads load as before)
        self.register_buffer("modes", torch.zeros(3 * self.nodes, self.mode_count),
                             kept and self.mode_count > 0)       # (checkpoints from before modes load as before)
        self.register_buffer("node_class", torch.zeros(self.nodes, dtype=torch.long), kept)
        self.register_buffer("weight", torch.zeros(int(classes), 3 * (int(width) + self.load_width),
                                                   len(self.columns)), kept)

    def forward(self, u: Tensor, f: Optional[Tensor] = None) -> Tensor:
        """Stress [..., N, S] (Pa, the state's stress columns ``columns``) of the displacement
        u [..., N, 3] (m) under the applied nodal load f [..., N, 3] (N; with a load reach; None:
        unloaded, the part the displacement makes). Leading dimensions are a batch of fields
        (e.g. the B states of a training window's step, or the S snapshots of a rollout)."""
        lead = u.shape[:-2]
        n = self.nodes
        u = u.reshape(-1, n, 3)                                                           # [B, N, 3]
        B = u.shape[0]
        zero = torch.zeros(B, 1, 3, dtype=u.dtype, device=u.device)
        if self.mode_count > 0:          # u projected onto the training displacements' span
            basis = self.modes.to(u.dtype)                                                # [3 N, r]
            u = ((u.reshape(B, 3 * n) @ basis) @ basis.t()).reshape(B, n, 3)              # [B, N, 3]
        padded = torch.cat([u, zero], 1)                                                  # [B, N + 1, 3]
        near = padded.index_select(1, self.stencil.reshape(-1)).reshape(B, n, -1)         # [B, N, 3 K]
        if self.load_width > 0:
            load = torch.zeros_like(u) if f is None else f.to(u.dtype).reshape(B, n, 3)
            padded_load = torch.cat([load, zero], 1)                                      # [B, N + 1, 3]
            near = torch.cat([near, padded_load.index_select(1, self.load_stencil.reshape(-1))
                              .reshape(B, n, -1)], 2)                                     # [B, N, 3 K + 3 Kf]
        w = self.weight.index_select(0, self.node_class).to(u.dtype)                      # [N, 3 (K + Kf), S]
        sigma = torch.bmm(near.transpose(0, 1), w).transpose(0, 1)                        # [B, N, S]
        return sigma.reshape(lead + sigma.shape[-2:])                                     # [..., N, S]

    def fitted_weights(self) -> int:
        """How many weights the fit set (the padding's excluded): the readout's parameter count. With
        symmetric weights, those of one neighbourhood shape per orbit (the others are their mirror images)."""
        if self.independent > 0:
            return self.independent + self.mode_values
        return int(self.shape_sizes().sum()) * 3 * len(self.columns) + self.mode_values

    def shape_sizes(self) -> Tensor:
        """Each neighbourhood shape's stencil size [C] (nodes, the padding excluded)."""
        real = (self.stencil < self.nodes).sum(1)                                       # [N] stencil sizes
        return torch.zeros(self.weight.shape[0], dtype=torch.long).scatter_reduce(
            0, self.node_class, real, "amax", include_self=True)


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


def symmetry_centre(ref_pos: np.ndarray) -> np.ndarray:
    """The point c [3] (m) the mesh's reflections and axis swaps act about: its bounding box's centre."""
    X = np.asarray(ref_pos, dtype=np.float64)
    return 0.5 * (X.min(0) + X.max(0))


def mesh_symmetries(ref_pos: np.ndarray, edge_index: np.ndarray,
                    node_type: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The reflections and axis swaps that map the mesh onto itself: each (R [3, 3], a signed
    permutation matrix, and p [N], the node each node goes to: X[p[i]] = c + R (X[i] - c) about the
    bounding box's centre c = ``symmetry_centre``, to 1e-6 of the mean edge length), taking edges onto edges and each
    node's type (free, clamped, ...) onto the same. The identity comes first."""
    from scipy.spatial import cKDTree

    X = np.asarray(ref_pos, dtype=np.float64)
    e = np.asarray(edge_index)
    h = float(np.mean(np.linalg.norm(X[e[0]] - X[e[1]], axis=1)))
    c = symmetry_centre(X)
    nodes = cKDTree(X - c)
    edges = set(zip(e[0].tolist(), e[1].tolist()))
    found = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            dist, p = nodes.query((X - c) @ R.T, distance_upper_bound=1e-6 * h)   # [N]: image's node
            if not np.isfinite(dist).all() or len(np.unique(p)) < len(X):
                continue
            if node_type is not None and (np.asarray(node_type)[p] != np.asarray(node_type)).any():
                continue
            if all((int(p[a]), int(p[b])) in edges for a, b in zip(e[0], e[1])):
                found.append((R, p))
    return sorted(found, key=lambda g: not np.array_equal(g[0], np.eye(3)))


def stress_action(R: np.ndarray) -> np.ndarray:
    """Q [6, 6] with voigt(R σ Rᵀ) = Q voigt(σ) (``VOIGT`` order) for an orthogonal R [3, 3]."""
    Q = np.zeros((6, 6))
    for a, (i, j) in enumerate(VOIGT):
        for b, (k, l) in enumerate(VOIGT):
            Q[a, b] = R[i, k] * R[j, l] + (R[i, l] * R[j, k] if k != l else 0.0)
    return Q


def mirrored(u: np.ndarray, sigma: np.ndarray, symmetries) -> tuple[np.ndarray, np.ndarray]:
    """The snapshots u [S, N, 3] (m) and σ [S, N, 6] (Pa, ``VOIGT``) seen in every frame g = (R, p)
    of ``symmetries``: u'[p[j]] = R u[j], σ'[p[i]] = R σ[i] Rᵀ. Returns [S |G|, N, 3], [S |G|, N, 6]."""
    ss = [sigma[:, np.argsort(p)] @ stress_action(R).T for R, p in symmetries]   # argsort(p): where from
    return mirrored_vectors(u, symmetries), np.concatenate(ss)


def orbits(size: int, pairs) -> np.ndarray:
    """The orbit of each of ``size`` items [size] joined by the item ``pairs`` (a, b) (each an item
    and its image under a symmetry): the smallest item of the set that a chain of pairs links it to."""
    root = list(range(int(size)))

    def find(a: int) -> int:
        while root[a] != a:
            a = root[a]
        return a

    for a, b in pairs:
        ra, rb = find(int(a)), find(int(b))
        root[max(ra, rb)] = min(ra, rb)              # roots stay their set's smallest item
    return np.array([find(a) for a in range(len(root))])


def shape_orbits(classes: np.ndarray, symmetries) -> np.ndarray:
    """The orbit of each neighbourhood shape under ``symmetries`` [C]: the smallest shape that one
    of them, or a chain of them, maps it to (the shapes of one orbit have mirror-image weights)."""
    return orbits(int(classes.max()) + 1, {pair for _, p in symmetries                 # node i's shape, its image's
                                           for pair in zip(classes.tolist(), classes[p].tolist())})


def check_determined(ref_pos: np.ndarray, edge_index: np.ndarray, snapshots: int, hops: int,
                     source: str = "dataset") -> tuple[list[list[int]], np.ndarray]:
    """``stencils`` of ``hops``, after checking that ``snapshots`` states give every neighbourhood
    shape at least as many equations as it has weights (else a DataError naming ``source``: the
    fit would interpolate). Training calls it before it starts, so a refusal costs nothing."""
    if hops < 1:
        raise DataError(f"{source}: model.stress_readout = {hops}, expected the stencil's reach in hops (>= 1) or 0 (off)")
    stencil, classes = stencils(ref_pos, edge_index, int(hops))
    _check_rows(stencil, classes, snapshots, f"{source}: model.stress_readout = {hops}")
    return stencil, classes


def _check_rows(stencil: list[list[int]], classes: np.ndarray, snapshots: int, what: str) -> None:
    """DataError (starting with ``what``) where a shape's nodes give fewer equations than it has
    displacement weights."""
    for c in range(int(classes.max()) + 1):
        nodes = np.flatnonzero(classes == c)
        rows, cols = snapshots * len(nodes), 3 * len(stencil[nodes[0]])
        if rows < cols:
            raise DataError(f"{what}: {len(nodes)} node(s) of one neighbourhood shape give {rows} equations "
                            f"for {cols} weights (a mesh whose neighbourhoods do not repeat, or too few "
                            "training snapshots); use fewer hops or 0")


def load_stencils(ref_pos: np.ndarray, edge_index: np.ndarray, load_hops: int,
                  classes: np.ndarray) -> tuple[list[list[int]], np.ndarray]:
    """Each node's load stencil (the nodes within ``load_hops`` edges whose applied load enters its
    stress, ordered by reference offset) and the neighbourhood-shape classes [N] refined so that
    nodes of one class share both stencils' shapes (``classes``: the displacement stencil's)."""
    load, load_classes = stencils(ref_pos, edge_index, int(load_hops))
    pairs = {}
    joint = np.array([pairs.setdefault((int(c), int(k)), len(pairs)) for c, k in zip(classes, load_classes)])
    return load, joint


def mirrored_vectors(a: np.ndarray, symmetries) -> np.ndarray:
    """Nodal vectors a [S, N, 3] (displacements, loads) seen in every frame g = (R, p) of
    ``symmetries``: a'[p[j]] = R a[j]. Returns [S |G|, N, 3] (frames in ``mirrored``'s order)."""
    return np.concatenate([a[:, np.argsort(p)] @ R.T for R, p in symmetries])


def displacement_modes(fields: np.ndarray, modes: int, symmetries,
                       source: str = "dataset") -> tuple[np.ndarray, int]:
    """An orthonormal basis [3 N, r] (node-major) of the span of the leading ``modes`` principal
    displacement fields of the snapshots ``fields`` [S, N, 3] (m) seen in every frame of
    ``symmetries`` (their proper orthogonal decomposition, uncentred: u = 0 is the rest state), and
    its parameter count. A degenerate pair of singular values is never split (r grows by one), so
    with mirror frames the span is closed under them. The count is r times the displacement
    components that move, one per orbit under the frames (a mirror-symmetric field is determined
    by those; the clamped components are zero in every mode).

    Projecting a rollout's displacement onto this span before the stencil reads it removes the
    part of its error that no training field has: a stencil is a strain, a difference of nearby
    displacements, and amplifies exactly that short-wave part (TIGNN beam, docs/accuracy.md,
    session 56)."""
    snapshots = mirrored_vectors(fields, symmetries).reshape(len(fields) * len(symmetries), -1)   # [S |G|, 3 N]
    if modes < 1 or modes > min(snapshots.shape):
        raise DataError(f"{source}: model.stress_readout_modes = {modes}, expected between 1 and "
                        f"{min(snapshots.shape)} (the training snapshots' count, seen in each mirror frame, "
                        "and the displacement components') or 0 (off)")
    _, s, vt = np.linalg.svd(snapshots, full_matrices=False)
    r = int(modes)
    while r < len(s) and s[r] >= s[r - 1] * (1.0 - 1e-6) and s[r] > 1e-9 * s[0]:   # do not split a degenerate pair
        r += 1
    basis = vt[:r].T                                                                   # [3 N, r]
    moving = np.abs(snapshots).max(0) > 1e-9 * np.abs(snapshots).max()                 # [3 N]
    n = fields.shape[1]
    pairs = []
    for R, p in symmetries:           # component c of node i goes to component a_of[c] of node p[i]
        a_of = np.argmax(np.abs(R), axis=0)                       # [3]: R[a_of[c], c] = ±1
        pairs += zip((3 * np.arange(n)[:, None] + np.arange(3)).ravel(),
                     (3 * np.asarray(p)[:, None] + a_of).ravel())
    held = len(np.unique(orbits(3 * n, pairs)[moving]))          # moving components, one per orbit
    basis[~moving] = 0.0
    return basis, r * held


def outside_modes(readout: StressReadout, u: Tensor) -> float:
    """How far the displacements u [S, N, 3] (m) lie outside the span of ``readout``'s displacement
    modes: ||u - P u|| / ||u|| over all snapshots and nodes (P the projection onto the span; 0: no
    modes, or inside it). Of a test split's true displacements, well above the training split's: its
    loads are not combinations of the training loads, and the projection cuts real deformation."""
    if readout.mode_count == 0:
        return 0.0
    basis = readout.modes.detach().cpu().double()                                      # [3 N, r]
    flat = u.detach().cpu().double().reshape(len(u), -1)                               # [S, 3 N]
    total = float(flat.norm())
    return float((flat - (flat @ basis) @ basis.T).norm()) / total if total > 0 else 0.0


def fit_stress_readout(ref_pos: Tensor, edge_index: Tensor, trajectories: Sequence[Tensor],
                       columns: Sequence[int], hops: int, source: str = "dataset", symmetric: bool = False,
                       node_type: Tensor | None = None, forces: Sequence[Tensor] | None = None,
                       load_hops: int = 0, modes: int = 0,
                       span: Sequence[Tensor] | None = None,
                       held_out: Sequence[int] | None = None,
                       ridge: float | Sequence[float] = 0.0,
                       relative: bool | float = False) -> tuple[StressReadout, Dict]:
    """Least-squares fit of the readout to the states z [T, N, D] of ``trajectories`` (the training
    split): σ = z[..., columns] against u = z[..., :3] - X, and with ``load_hops`` >= 1
    (``model.stress_readout_load``) the applied loads ``forces`` [T, N, 3] (N) of the same snapshots
    within that reach (a load column no snapshot loads gets weight 0; a reach beyond ``hops`` tells
    nodes apart by both stencils' shapes, so there are more shapes, each with its own weights).
    ``symmetric``: mirror-image shapes get mirror-image weights (the snapshots fitted in every frame
    of ``mesh_symmetries``, which ``node_type`` [N] constrains; needs the 6 stress components).
    ``modes`` >= 1 (``model.stress_readout_modes``): u is first projected onto the span of the leading
    ``modes`` principal displacement fields of ``span`` (states [T, N, D], the training split's true
    ones; default ``trajectories``), in every frame when ``symmetric`` (``displacement_modes``).
    Returns the readout and a report {"hops", "load_hops", "modes", "classes", "weights", "symmetries",
    "fit_error"} (weights: the independent ones, the load's that a snapshot loads; fit_error:
    relative L2 over the fitted snapshots). Raises DataError (naming ``source``) where the fit is
    underdetermined or the data's stress-free state is not at u = 0.

    ``held_out`` (a fold k >= 0 per trajectory, -1: in every fit; not with ``modes``, whose basis
    would depend on the fold): the report's "held_out_readouts" [K] also holds, for each fold k, the
    readout of the same shape fitted without fold k's trajectories, from the same pass over the
    shapes (each fold's normal equations subtracted from the whole's, so the K readouts cost about
    no more than the fit itself: TIGNN beam, 200 s against 204 s; ``held_out_loads_check``).

    ``ridge`` (``model.stress_readout_ridge``): a ridge on the weights, relative as ``RIDGE`` (added to
    it), that draws them towards 0 where the training loads leave them undetermined. Several values
    need ``held_out`` folds: each neighbourhood shape takes the one whose weights, fitted without a
    fold, read that fold's rows best (least squared error summed over the folds), and each fold's
    readout the one the *other* folds chose, so the held-out check does not score a choice made on
    its own rows. The report's "ridge" is each shape's [C], and "first_ridge_readouts" the readouts
    with every shape at the first ridge of the list ([K] fold ones, then the whole), for the check
    to set beside the choice. On the TIGNN beam's true fields (session
    63) only the shapes near the free end choose one, where the stencil extrapolates to loads it
    never saw: held-out σ 3.87 → 2.38 %, in sample 0.53 → 1.17 % (3 hops, no loads; docs/accuracy.md).

    ``relative`` (``model.stress_readout_relative``): each snapshot's equations weighed by 1 / |σ| of
    that snapshot (the norm over its nodes and columns, times the snapshots' median |σ|), so the fit
    minimises the sum of the snapshots' squared *relative* errors, the per-snapshot metric's kind,
    instead of their absolute ones, which the snapshots of the largest stress (late in a loading)
    dominate; the ridge choice then sums weighed squared errors too, and ``fit_error`` is unchanged
    in kind. A number p in [0, 1] weighs them by 1 / |σ|^p: p = 1 is ``True``, p = 0 ``False``, in
    between a compromise between the per-snapshot and whole-rollout metrics (TIGNN beam,
    docs/accuracy.md, session 67: p = 0.5 read the validation split best per snapshot)."""
    X = ref_pos.detach().cpu().double().numpy()
    z = np.concatenate([t.detach().cpu().double().numpy() for t in trajectories])        # [S, N, D]
    cols = [int(c) for c in columns]
    u, sigma = z[:, :, :3] - X, z[:, :, cols]                                             # [S, N, 3], [S, N, C]
    load_hops = int(load_hops or 0)
    if load_hops < 0:
        raise DataError(f"{source}: model.stress_readout_load = {load_hops}, expected the loads' reach "
                        "in hops (>= 1) or 0 (off)")
    if load_hops and forces is None:
        raise ValueError("fit_stress_readout: load_hops needs the snapshots' forces")
    f = (np.concatenate([t.detach().cpu().double().numpy() for t in forces]) if load_hops
         else np.zeros_like(u))                                                           # [S, N, 3] (N)
    rest = (np.linalg.norm(u, axis=(1, 2)) < 1e-12 * (1.0 + np.abs(X).max())) & ~np.any(f != 0, axis=(1, 2))
    if rest.any() and np.abs(sigma[rest]).max() > 1e-9 * max(np.abs(sigma).max(), 1e-300):
        raise DataError(f"{source}: the stress is not zero where the displacement is (u = 0): "
                        "model.stress_readout needs a stress-free reference state")
    reach = float(np.abs(u).max())                                                      # [m]
    edges = edge_index.detach().cpu().numpy()
    stencil, classes = check_determined(X, edges, len(z), hops, source)
    load_stencil: list[list[int]] = [[] for _ in range(len(X))]
    if load_hops:
        load_stencil, classes = load_stencils(X, edges, load_hops, classes)   # beyond hops: more shapes
        _check_rows(stencil, classes, len(z), f"{source}: model.stress_readout_load = {load_hops}")
    symmetries = [(np.eye(3), np.arange(len(X)))]
    if symmetric:
        if len(cols) != 6:
            raise DataError(f"{source}: model.stress_readout_symmetric needs the 6 stress components "
                            f"(s11 s22 s33 s12 s13 s23), the state has {len(cols)}")
        symmetries = mesh_symmetries(X, edges, None if node_type is None else node_type.detach().cpu().numpy())
        u, sigma = mirrored(u, sigma, symmetries)                          # [S |G|, N, 3], [S |G|, N, 6]
        f = mirrored_vectors(f, symmetries)                                # [S |G|, N, 3]
        rest = np.tile(rest, len(symmetries))
    # each snapshot's weight in the fit [S |G|]: 1, or with ``relative`` = p (median |σ| / its |σ|)^p
    # (dimensionless, about 1, so the round-off test of the clamped columns keeps its scale); the
    # stress-free snapshots (σ = 0, u = 0: no equations) weigh 0
    snapshot_norm = np.linalg.norm(sigma.reshape(len(sigma), -1), axis=1)               # [S |G|] (Pa)
    power = float(relative)
    if not 0.0 <= power <= 1.0:
        raise DataError(f"{source}: model.stress_readout_relative = {relative!r}, expected true, false or "
                        "the power p in [0, 1] of the snapshots' weights 1 / |σ|^p")
    row_weight = np.ones(len(sigma))
    if power and (snapshot_norm > 0).any():
        row_weight = np.where(snapshot_norm > 0, (np.median(snapshot_norm[snapshot_norm > 0])
                                                  / np.where(snapshot_norm > 0, snapshot_norm, 1.0)) ** power, 0.0)
    folds = 0
    if held_out is not None:
        if modes:
            raise ValueError("fit_stress_readout: held_out folds with modes (the basis would depend on the fold)")
        per_snapshot = np.concatenate([np.full(len(t), int(k)) for t, k in zip(trajectories, held_out)])   # [S]
        row_fold = np.tile(per_snapshot, len(symmetries))                  # [S |G|], mirrored's frame order
        folds = int(row_fold.max()) + 1 if len(row_fold) else 0
    basis, mode_values = np.zeros((3 * len(X), 0)), 0
    if modes:
        fields = np.concatenate([t.detach().cpu().double().numpy() for t in (span or trajectories)])[:, :, :3] - X
        basis, mode_values = displacement_modes(fields, int(modes), symmetries, source)      # [3 N, r]
        u = ((u.reshape(len(u), -1) @ basis) @ basis.T).reshape(u.shape)                   # [S, N, 3]
    n, width = len(X), max(len(s) for s in stencil)
    load_width = max(len(s) for s in load_stencil)
    weight = np.zeros((int(classes.max()) + 1, 3 * (width + load_width), len(cols)))   # StressReadout.weight's
    fold_weights = np.zeros((folds,) + weight.shape)            # [K, classes, ...]: each without fold k
    loaded = np.zeros(weight.shape[0], dtype=np.int64)          # per class: load columns some snapshot loads

    def solve(gram, rhs, column_max, rows, k, lam):
        """Weights [3 k + 3 kf, C] from the normal equations (gram = aᵀa, rhs = aᵀb of ``rows`` rows),
        each column scaled to O(1) by its largest value ``column_max``, with a ridge of RIDGE + ``lam``
        (relative); a clamped column (round-off) and a load column no row loads get weight 0. Also
        returns the loaded load columns' count. ``lam`` an array [L]: the weights [L, 3 k + 3 kf, C]
        of each ridge, from one eigendecomposition."""
        scale = column_max.copy()
        still = scale <= 1e-9 * reach                            # clamped: round-off, weight 0
        still[3 * k:] = scale[3 * k:] == 0.0                     # a load column no snapshot loads: 0
        scale[still] = 1.0
        gn = gram / scale[:, None] / scale[None, :]
        gn[still], gn[:, still] = 0.0, 0.0
        rn = np.where(still[:, None], 0.0, rhs / scale[:, None])
        if np.ndim(lam):                 # gn = V diag(e) Vᵀ: (gn + r I)⁻¹ rn = V diag(1 / (e + r)) Vᵀ rn
            e, V = np.linalg.eigh(gn)
            proj = V.T @ rn                                                               # [P, C]
            w = np.stack([V @ (proj / (e + (RIDGE + lv) * rows)[:, None]) for lv in lam])  # [L, P, C]
        else:
            w = np.linalg.solve(gn + (RIDGE + lam) * rows * np.eye(len(scale)), rn)
        return np.where(still[:, None], 0.0, w / scale[:, None]), int((~still[3 * k:]).sum())

    # the snapshots in blocks: one per fold, then those never held out (all of them without folds)
    blocks = ([np.flatnonzero(row_fold == j) for j in range(folds)] + [np.flatnonzero(row_fold < 0)]
              if folds else [np.arange(len(u))])
    blocks = [snaps for snaps in blocks if len(snaps)]           # (each fold has a snapshot)
    ridges = np.atleast_1d(np.asarray(ridge, dtype=np.float64))                     # [L] candidates
    if len(ridges) < 1 or (ridges < 0).any():
        raise DataError(f"{source}: model.stress_readout_ridge = {list(ridges)}, expected one ridge >= 0 "
                        "or several to choose from")
    if len(ridges) > 1 and not folds:
        raise DataError(f"{source}: model.stress_readout_ridge = {list(ridges)}: choosing among several "
                        "ridges needs training trajectories with at least 2 load groups to hold out "
                        "(train.readout_folds >= 2, without model.stress_readout_modes)")
    chosen = np.full(weight.shape[0], ridges[0])                # per class: its ridge
    first_weights = np.zeros((folds + 1,) + weight.shape) if len(ridges) > 1 else None   # the first ridge's: folds, whole

    def place(into, c, k, w):
        """Shape c's weights w [3 k + 3 kf, C] into ``into`` [classes, 3 (width + load_width), C]: the
        displacement stencil's first, the load stencil's from column 3 width (StressReadout.weight's layout)."""
        into[c, :3 * k] = w[:3 * k]
        into[c, 3 * width:3 * width + (w.shape[0] - 3 * k)] = w[3 * k:]
    predicted = np.zeros_like(sigma)
    for c in range(weight.shape[0]):
        nodes = np.flatnonzero(classes == c)
        st = np.array([stencil[i] for i in nodes])                                       # [m, k]
        lst = np.array([load_stencil[i] for i in nodes]) if load_hops else None          # [m, kf]
        k = st.shape[1]
        parts = []                       # per block: (a [s m, 3 k + 3 kf], b [s m, C], aᵀa, aᵀb, row weights [s m, 1])
        for snaps in blocks:
            rows_of = snaps[:, None, None]                                               # [s, 1, 1]
            a = u[rows_of, st].reshape(len(snaps) * len(nodes), -1)                      # [s m, 3 k]
            if load_hops:
                a = np.concatenate([a, f[rows_of, lst].reshape(len(snaps) * len(nodes), -1)], 1)
            b = sigma[snaps[:, None], nodes].reshape(len(snaps) * len(nodes), -1)        # [s m, C]
            rw = np.repeat(row_weight[snaps], len(nodes))[:, None]                       # [s m, 1]: 1 unless weighed
            if power:                    # each snapshot's rows weighed by 1 / |σ|^p of that snapshot
                a, b = a * rw, b * rw
            parts.append((a, b, a.T @ a, a.T @ b, rw))
        gram, rhs = sum(p[2] for p in parts), sum(p[3] for p in parts)
        column_max = np.stack([np.abs(p[0]).max(0) for p in parts])                   # [blocks, P]
        rows = sum(len(p[0]) for p in parts)

        def without(j, lam):                 # the weights fitted without fold j's rows
            return solve(gram - parts[j][2], rhs - parts[j][3], np.delete(column_max, j, axis=0).max(0),
                         rows - len(parts[j][0]), k, lam)[0]

        fold_ridge = np.full(folds, ridges[0])
        if len(ridges) > 1:                  # each candidate's squared error on each held-out fold's rows
            sse = np.zeros((len(ridges), folds))
            for j in range(folds):
                _, bj, gj, rj, _ = parts[j]        # |a w - b|² = wᵀ aᵀa w - 2 wᵀ aᵀb + |b|²
                for li, wj in enumerate(without(j, ridges)):
                    sse[li, j] = (wj * (gj @ wj)).sum() - 2.0 * (wj * rj).sum() + (bj ** 2).sum()
            chosen[c] = ridges[int(np.argmin(sse.sum(1)))]
            fold_ridge = ridges[np.argmin(sse.sum(1, keepdims=True) - sse, axis=0)]   # the other folds' choice
            alone = [without(j, ridges[0]) for j in range(folds)] + [solve(gram, rhs, column_max.max(0), rows, k,
                                                                           ridges[0])[0]]
            for j, wj in enumerate(alone):               # every shape at the first ridge: folds, then whole
                place(first_weights[j], c, k, wj)
        w, loaded[c] = solve(gram, rhs, column_max.max(0), rows, k, chosen[c])
        place(weight, c, k, w)
        for snaps, (a, _b, _g, _r, rw) in zip(blocks, parts):
            read = (a @ w) / np.where(rw > 0, rw, 1.0)                                   # [s m, C] (Pa), unweighed
            predicted[snaps[:, None], nodes[None, :]] = read.reshape(len(snaps), len(nodes), -1)
        for j in range(folds):        # each fold's normal equations taken out of the whole's
            place(fold_weights[j], c, k, without(j, fold_ridge[j]))

    def filled(w_all: np.ndarray) -> StressReadout:
        r = StressReadout(n, width, int(classes.max()) + 1, cols, load_width=load_width,
                          modes=basis.shape[1], mode_values=mode_values)
        with torch.no_grad():
            r.stencil.copy_(torch.tensor([s + [n] * (width - len(s)) for s in stencil]))
            if load_hops:
                r.load_stencil.copy_(torch.tensor([s + [n] * (load_width - len(s)) for s in load_stencil]))
            r.node_class.copy_(torch.from_numpy(classes))
            r.weight.copy_(torch.from_numpy(w_all))
            if basis.shape[1]:
                r.modes.copy_(torch.from_numpy(basis))
        return r

    readout = filled(weight)
    if symmetric or load_hops:             # one shape per orbit holds the independent weights
        held = np.unique(shape_orbits(classes, symmetries))
        readout.independent = (int(readout.shape_sizes()[torch.from_numpy(held)].sum()) * 3
                               + int(loaded[held].sum())) * len(cols)
    moving = ~rest
    err = float(np.mean([np.linalg.norm(p - s) / np.linalg.norm(s)
                         for p, s in zip(predicted[moving], sigma[moving]) if np.linalg.norm(s) > 0]))
    report = {"hops": int(hops), "load_hops": load_hops, "modes": basis.shape[1], "classes": int(weight.shape[0]),
              "weights": readout.fitted_weights(), "symmetries": len(symmetries), "fit_error": err,
              "ridge": chosen, "relative": power}
    if held_out is not None:
        report["held_out_readouts"] = [filled(w) for w in fold_weights]
    if len(ridges) > 1:              # the readouts at the first ridge alone, for the check to compare
        report["first_ridge_readouts"] = [filled(w) for w in first_weights]
    return readout, report


def readout_spec(readout: StressReadout, hops: int, load_hops: int = 0) -> Dict:
    """The readout's shape for a checkpoint's hyperparameters (TIGNN's ``stress_readout``)."""
    return {"hops": int(hops), "nodes": readout.nodes, "width": int(readout.stencil.shape[1]),
            "classes": int(readout.weight.shape[0]), "columns": list(readout.columns),
            "independent": readout.independent, "load_hops": int(load_hops), "load_width": readout.load_width,
            "modes": readout.mode_count, "mode_values": readout.mode_values}


def with_stress_readout(ckpt: Dict, readout: StressReadout, hops: int, load_hops: int = 0) -> Dict:
    """A TIGNN checkpoint ``ckpt`` with ``readout`` attached (its hyperparameters and weights): the
    trained network's positions and velocities, the stress read off the positions (and loads)."""
    hparams = {**ckpt["hparams"], "stress_readout": readout_spec(readout, hops, load_hops)}
    state = {k: v for k, v in ckpt["state_dict"].items() if not k.startswith("readout.")}
    state.update({f"readout.{k}": v.detach().cpu() for k, v in readout.state_dict().items()})
    return {**ckpt, "hparams": hparams, "state_dict": state}


def ridge_counts(chosen) -> list[list[float]]:
    """[[ridge, shapes], ...]: how many of the readout's neighbourhood shapes chose each ridge
    (``fit_stress_readout``'s report "ridge" [C]), smallest ridge first."""
    return [[v, c] for v, c in sorted(Counter(float(v) for v in chosen).items())]


def load_groups(forces: Sequence[Tensor], symmetries) -> np.ndarray:
    """Each trajectory's load group [T]: trajectories whose loaded nodes (any nonzero applied load
    over the trajectory; forces [S, N, 3] each) are the same set, or mirror images of one another
    under ``symmetries`` ((R, p) pairs, ``mesh_symmetries``), share one. Groups are numbered by
    their loaded nodes' canonical image, so the numbering does not depend on the trajectories' order."""
    keys = []
    for f in forces:
        loaded = np.flatnonzero((f.detach().cpu().abs().sum((0, 2)) > 0).numpy())        # node indices
        keys.append(min(tuple(sorted(int(j) for j in p[loaded])) for _, p in symmetries))
    order = {k: i for i, k in enumerate(sorted(set(keys)))}
    return np.array([order[k] for k in keys], dtype=np.int64)


def load_folds(graph, forces: Sequence[Tensor], folds: int, symmetric: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(the fold [T] of each trajectory, its load group [T]): the trajectories' load groups
    (``load_groups``, up to the mesh's mirrors when ``symmetric``) dealt into min(``folds``, groups)
    folds, group g into fold g mod K; the folds are empty ([0]) where there are fewer than 2 groups."""
    X = graph.ref_pos.detach().cpu().double().numpy()
    symmetries = (mesh_symmetries(X, graph.edge_index.cpu().numpy(), graph.node_type.cpu().numpy())
                  if symmetric else [(np.eye(3), np.arange(len(X)))])
    groups = load_groups(forces, symmetries)
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    k = min(int(folds), n_groups)
    return (groups % k if k >= 2 else np.zeros(0, dtype=np.int64)), groups


def held_out_loads_check(graph, rolled: Sequence[Tensor], truths: Sequence[Tensor], forces: Sequence[Tensor],
                         columns: Sequence[int], hops: int, folds: int, symmetric: bool = False,
                         load_hops: int = 0, modes: int = 0, source: str = "dataset",
                         ridge: float | Sequence[float] = 0.0,
                         fit: tuple[StressReadout, Dict] | None = None, relative: bool | float = False) -> Dict:
    """How the readout does on loads it was not fitted to (``train.readout_folds``): the
    trajectories' load groups (``load_folds``: the loaded nodes, up to the mesh's mirrors, which a
    symmetric fit would otherwise see in the held-out ones' place) are dealt into ``folds`` folds;
    each fold's trajectories are read by a readout of the same shape fitted to the others'
    ``rolled`` states [S, N, D] (and ``forces``; ``modes`` from the others' true states ``truths``)
    and scored against their true stress. The fold readouts come from one pass over the shapes
    (``fit_stress_readout``'s ``held_out``: its report's "held_out_readouts"), the whole split's fit
    ``fit`` = (readout, report) where given (``fit_readout_to_rollouts``), else fitted here; with
    ``modes``, whose basis depends on the fold, one fit each. On the reference split of the
    TIGNN beam, whose test cases mirror training ones, the test error does not show this
    (docs/accuracy.md, session 62).

    Returns {"folds", "groups", "per_snapshot", "whole", "in_sample_per_snapshot",
    "in_sample_whole", "worst_group_per_snapshot", "worst_group_load_point"} (means over the
    trajectories; in sample: read by the readout fitted to all, ``fit``'s where given; the load
    group read worst held out, and its load's place [m]: the mean reference position of a
    trajectory's loaded nodes; with ``ridge`` a list, also "ridge", ``ridge_counts`` of the shapes'
    choice, and "first_ridge": {"ridge", "per_snapshot", "in_sample_per_snapshot"}, the same with
    every shape at the list's first ridge, from the fit's "first_ridge_readouts"), or {"folds": 0,
    "groups", "reason"} where there are fewer than 2 load groups or a fold's complement leaves the
    fit underdetermined."""
    from thermognn.core.state import StateLayout

    from .rollout import rrmse_per_step, trajectory_error, trajectory_rrmse

    fold_of, groups = load_folds(graph, forces, folds, symmetric)
    n_groups = int(groups.max()) + 1 if len(groups) else 0
    if not len(fold_of):
        return {"folds": 0, "groups": n_groups, "reason": f"{n_groups} load group(s): nothing to hold out"}
    k = int(fold_of.max()) + 1
    cols = [int(c) for c in columns]
    X = graph.ref_pos

    def refit(idx, held_out=None):
        return fit_stress_readout(X, graph.edge_index, [rolled[i] for i in idx], cols, hops, source=source,
                                  symmetric=symmetric, node_type=graph.node_type,
                                  forces=[forces[i] for i in idx], load_hops=load_hops, modes=modes,
                                  span=[truths[i] for i in idx], held_out=held_out, ridge=ridge,
                                  relative=relative)

    try:
        fitted, report = fit if fit is not None else refit(range(len(rolled)), held_out=None if modes else fold_of)
        fold_readouts = report.get("held_out_readouts")
        if fold_readouts is None:                # modes: the basis depends on the fold
            fold_readouts = [refit([i for i in range(len(rolled)) if fold_of[i] != j])[0] for j in range(k)]
    except DataError as exc:
        return {"folds": 0, "groups": n_groups, "reason": f"a fold left out: {exc}"}

    stress = StateLayout((("sigma", len(cols)),))

    def errors(readout, i):
        """(per snapshot, whole) relative L2 error of trajectory i's stress read by ``readout``."""
        with torch.no_grad():
            u = rolled[i][:, :, :3].detach().cpu().double() - X.detach().cpu().double()       # [S, N, 3]
            read = readout(u, forces[i].detach().cpu().double())                                # [S, N, C]
        true = truths[i][:, :, cols].detach().cpu().double()
        return (trajectory_rrmse(rrmse_per_step(read, true, stress))["sigma"],
                trajectory_error(read, true, stress)["sigma"])

    held = [errors(fold_readouts[int(fold_of[i])], i) for i in range(len(rolled))]
    in_sample = [errors(fitted, i) for i in range(len(rolled))]
    # the load group read worst, and where its load is (the mean reference position of the first
    # such trajectory's loaded nodes)
    per_group = {int(g): float(np.mean([held[i][0] for i in range(len(held)) if groups[i] == g])) for g in set(groups)}
    worst = max(per_group, key=per_group.get)
    first = int(np.flatnonzero(groups == worst)[0])
    loaded = (forces[first].detach().cpu().abs().sum((0, 2)) > 0).numpy()
    out = {"folds": k, "groups": n_groups,
           "per_snapshot": float(np.mean([e[0] for e in held])), "whole": float(np.mean([e[1] for e in held])),
           "in_sample_per_snapshot": float(np.mean([e[0] for e in in_sample])),
           "in_sample_whole": float(np.mean([e[1] for e in in_sample])),
           "worst_group_per_snapshot": per_group[worst],
           "worst_group_load_point": [float(v) for v in X.detach().cpu().double().numpy()[loaded].mean(0)]}
    first_ridge_readouts = report.get("first_ridge_readouts")
    if first_ridge_readouts is not None:      # a list of ridges: the shapes' choice, and every shape at the first
        out["ridge"] = ridge_counts(report["ridge"])
        r0 = float(np.atleast_1d(ridge)[0])
        held0 = [errors(first_ridge_readouts[int(fold_of[i])], i)[0] for i in range(len(rolled))]
        out["first_ridge"] = {"ridge": r0, "per_snapshot": float(np.mean(held0)),
                              "in_sample_per_snapshot": float(np.mean([errors(first_ridge_readouts[-1], i)[0]
                                                                        for i in range(len(rolled))]))}
    return out


def fit_readout_to_rollouts(model: nn.Module, data, trajectories, hops: int,
                            roll=None, symmetric: bool = False, load_hops: int = 0,
                            modes: int = 0, folds: int = 0,
                            ridge: float | Sequence[float] = 0.0,
                            relative: bool | float = False) -> tuple[StressReadout, Dict]:
    """The readout fitted to the trained ``model``'s own rollouts of ``trajectories`` (the training
    split, ``TrajectoryTensors``): its predicted positions against the data's stress at each step.
    Fitted to the true positions instead, the readout's stencil (a strain: differences of nearby
    displacements) amplifies a rollout's small nodal errors: TIGNN beam, 1.1 % on true test
    positions, 64-87 % on a rollout's 0.6 % off (docs/accuracy.md, session 52). ``roll(model, t)``
    -> [S, N, D] rolls a trajectory out as the evaluation will (default: ``rollout`` from t's first
    state; the TIGNN beam benchmark imposes the clamped nodes' whole true state at every step, and
    its readout is fitted to such rollouts: 7.1 % against 9.0 % fitted to ``rollout``'s).
    ``symmetric``: mirror-image weights, ``load_hops``: the applied loads within that reach too,
    ``modes``: the rollouts' displacements projected onto the span of the trajectories' own
    (true) leading displacement fields first, ``relative``: each snapshot weighed by 1 / |σ| of it
    (``fit_stress_readout``). ``folds`` >= 2: the report's
    "held_out_loads" is ``held_out_loads_check`` on the same rollouts."""
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
    forces = [t.force for t in trajectories]
    fold_of = load_folds(data.graph, forces, folds, symmetric)[0] if folds >= 2 and not modes else None
    readout, fit = fit_stress_readout(data.graph.ref_pos, data.graph.edge_index, rolled, columns, hops,
                                      source=str(data.path), symmetric=symmetric, node_type=data.graph.node_type,
                                      forces=forces, load_hops=load_hops, modes=modes,
                                      span=[t.z for t in trajectories],
                                      held_out=fold_of if fold_of is not None and len(fold_of) else None,
                                      ridge=ridge, relative=relative)
    if folds >= 2:                   # the same pass gave the fold readouts (without modes)
        fit["held_out_loads"] = held_out_loads_check(
            data.graph, rolled, [t.z for t in trajectories], forces, columns, hops, folds, symmetric=symmetric,
            load_hops=load_hops, modes=modes, source=str(data.path), ridge=ridge, fit=(readout, fit),
            relative=relative)
    for kept_out in ("held_out_readouts", "first_ridge_readouts"):      # readouts the check alone reads
        fit.pop(kept_out, None)
    return readout, fit
