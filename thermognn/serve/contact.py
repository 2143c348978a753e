"""Tool-surface contact: a spherical tool tip against the deformed boundary of the body (numpy only).

The tool centre ``x`` [3] m meets the surface triangles (``surface_faces``) at their current
positions ``q`` [N, 3] m through a penalty (virtual coupling) of stiffness ``k`` [N/m]:

    p_j, d_j closest point of triangle j to x and its distance; the triangles with d_j < r
             overlap the tool sphere and get the weight w_j = r - d_j (0 at release)
    n        = normalised sum_j w_j n_j of the outward face normals n_j: exact on flat
             tessellated surfaces, continuous in x, also in concave dimples where the closest
             point jumps between faces and at convex edges (blended normal)
    s        signed distance to the nearest triangle: min_j d_j, negative where the centre
             lies behind n from its closest point (inside the body). Not the smallest of the
             triangles' own signed distances: in a dimple a triangle whose plane the centre is
             behind may be 3 mm off while the surface is 0.5 mm away, which made the force
             chatter by 1 N from step to step under the sim press (docs/accuracy.md, session 77)
    delta    = r - s   penetration of the sphere of radius r                      [m]
             (no face within r: n and s from the nearest face(s) alone, so a centre pushed
             deeper than r into a soft body keeps its contact instead of passing through)
    f_user   = k delta n               force on the user (pushes the tool out)    [N]
    K        = d f_user / d x = -k n n^T   (contact stiffness, surface held)      [N/m]

The body receives the reaction -f_user as the external nodal load, shared by the loadable
surface nodes (node_type 2) within ``load_radius`` of p with hat weights (1 - d/R), or by the
closest triangle's vertices (barycentric) when none is that close. Without ``surface_faces``
the surface nodes act as points (closest node, no inside test).

K above holds the surface still. The body yields too, in series with the penalty spring, so
the physics process publishes the series stiffness instead (``series_stiffness``):

    k_eff    = k_c k_b / (k_c + k_b),   0 <= k_eff <= k_c                         [N/m]
    K        = -k_eff n n^T = (k_b / (k_c + k_b)) * (-k_c n n^T)                  [N/m]

with k_c = ``k`` and k_b the body's local normal stiffness at the contact over one physics
step, measured by finite differences on the model itself: one extra step from the same state
with the nodal loads scaled by (1 + eps), i.e. an extra load eps |f| [N] along the inward
normal, distributed like the contact load; then (``normal_compliance``)

    du       = -n . sum_i w_i (q_i^pert - q_i) / sum_i w_i,   w_i = |load_i|        [m]
    k_b      = eps |f| / du                                                      [N/m]

(du <= 0 or not finite: the body counts as rigid, k_b = inf, k_eff = k_c).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ContactResult:
    force: np.ndarray        # [3] N on the user (= -sum of nodal loads)
    stiffness: np.ndarray    # [3, 3] N/m, d force / d x
    in_contact: bool
    depth: float             # [m] penetration (<= 0: no contact)
    point: np.ndarray        # [3] m closest surface point
    normal: np.ndarray       # [3] outward unit normal at the contact


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Closest points of triangles (a, b, c) [F, 3] to the point p [3] (Ericson, RTCD 5.1.5).

    Returns points [F, 3] and barycentric coordinates [F, 3].
    """
    ab, ac = b - a, c - a
    ap, bp, cp = p - a, p - b, p - c
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = 1e-300
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        den = np.where(np.abs(den) > tiny, den, tiny)
        bary = np.stack([va / den, vb / den, vc / den], axis=1)        # interior
        w_bc = (d4 - d3) / np.maximum((d4 - d3) + (d5 - d6), tiny)
        w_ac = d2 / np.where(np.abs(d2 - d6) > tiny, d2 - d6, tiny)
        v_ab = d1 / np.where(np.abs(d1 - d3) > tiny, d1 - d3, tiny)
    regions = [  # later entries take precedence, as in Ericson's early returns
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), np.stack([0 * w_bc, 1 - w_bc, w_bc], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), np.stack([1 - w_ac, 0 * w_ac, w_ac], 1)),
        ((d6 >= 0) & (d5 <= d6), np.array([0.0, 0.0, 1.0])),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), np.stack([1 - v_ab, v_ab, 0 * v_ab], 1)),
        ((d3 >= 0) & (d4 <= d3), np.array([0.0, 1.0, 0.0])),
        ((d1 <= 0) & (d2 <= 0), np.array([1.0, 0.0, 0.0])),
    ]
    for mask, value in regions:
        bary = np.where(mask[:, None], value, bary)
    points = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return points, bary


def orient_outward(faces: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Faces [F, 3] re-wound so that their normals point away from the body centroid (reference X [N, 3])."""
    faces = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return faces
    a, b, c = X[faces[:, 0]], X[faces[:, 1]], X[faces[:, 2]]
    n = np.cross(b - a, c - a)
    outward = np.einsum("ij,ij->i", n, (a + b + c) / 3.0 - X.mean(axis=0)) >= 0
    faces[~outward] = faces[~outward][:, [0, 2, 1]]
    return faces


def series_stiffness(k_contact: float, k_body: float) -> float:
    """Stiffness [N/m] of the contact spring ``k_contact`` in series with the body ``k_body`` [N/m].

    k_eff = k_c k_b / (k_c + k_b), clamped to [0, k_c]: k_b = inf (rigid body) or not a number
    (unknown) gives k_c, k_b <= 0 gives 0.
    """
    k_c, k_b = float(k_contact), float(k_body)
    if not k_c > 0.0:
        return 0.0
    if np.isnan(k_b) or k_b == np.inf:
        return k_c
    if k_b <= 0.0:
        return 0.0
    return min(max(k_c / (1.0 + k_c / k_b), 0.0), k_c)


def normal_compliance(q: np.ndarray, q_pert: np.ndarray, loads: np.ndarray, n: np.ndarray) -> float:
    """Inward normal displacement [m] of the loaded nodes caused by a perturbation of their loads.

    ``q``, ``q_pert`` [N, 3] m: positions after one step with the loads and with the perturbed
    loads; ``loads`` [N, 3] N: the (unperturbed) nodal loads, whose magnitudes weight the nodes;
    ``n`` [3]: outward unit normal. Returns du = -n . sum_i w_i (q_pert_i - q_i) / sum_i w_i with
    w_i = |loads_i| (positive when the extra inward load pushed the surface in); NaN without loads.
    The body's stiffness is then k_b = |extra load| / du [N/m].
    """
    w = np.linalg.norm(np.asarray(loads, dtype=float), axis=1)
    total = float(w.sum())
    if not total > 0.0:
        return float("nan")
    idx = np.flatnonzero(w)
    dq = np.asarray(q_pert, dtype=float)[idx] - np.asarray(q, dtype=float)[idx]
    mean = (w[idx, None] * dq).sum(axis=0) / total
    return float(-np.dot(np.asarray(n, dtype=float), mean))


class SurfaceContact:
    """Contact of a spherical tool with a body's deformed surface; see the module docstring."""

    def __init__(self, reference_positions: np.ndarray, node_type: np.ndarray, surface_faces: np.ndarray,
                 tool_radius: float, stiffness: float, load_radius: float) -> None:
        X = np.asarray(reference_positions, dtype=float)
        self.n_nodes = len(X)
        self.faces = orient_outward(surface_faces, X)
        node_type = np.asarray(node_type).reshape(-1)
        surface_nodes = np.unique(self.faces) if len(self.faces) else np.flatnonzero(node_type == 2)
        if len(surface_nodes) == 0:
            surface_nodes = np.flatnonzero(node_type != 1)
        loadable = np.flatnonzero(node_type == 2)
        self.surface_nodes = surface_nodes
        self.loadable = loadable if len(loadable) else surface_nodes
        self.radius = float(tool_radius)          # [m]
        self.k = float(stiffness)                 # [N/m]
        self.load_radius = float(load_radius)     # [m]
        self.loads = np.zeros((self.n_nodes, 3))  # [N, 3] N, reused
        self.lo, self.hi = X.min(axis=0), X.max(axis=0)

    def surface_triangles(self) -> np.ndarray:
        """The surface triangles [F, 3] as indices into ``surface_nodes`` (what a virtual device's
        ``attach_surface`` takes beside those nodes' positions; [0, 3] without faces)."""
        if not len(self.faces):
            return np.zeros((0, 3), dtype=np.int64)
        return np.searchsorted(self.surface_nodes, self.faces).astype(np.int64)

    def __call__(self, x: np.ndarray, q: np.ndarray) -> ContactResult:
        """Contact of the tool centred at ``x`` [3] m with the surface at positions ``q`` [N, 3] m.

        Fills ``self.loads`` [N, 3] with the nodal load on the body (zero without contact).
        """
        x = np.asarray(x, dtype=float)
        q = np.asarray(q, dtype=float)
        self.loads[:] = 0.0
        if len(self.faces):
            f = self.faces
            a, b, c = q[f[:, 0]], q[f[:, 1]], q[f[:, 2]]
            pts, bary = closest_points_on_triangles(x, a, b, c)
            u = x - pts                                                   # [F, 3]
            d = np.sqrt(np.einsum("ij,ij->i", u, u))                      # [F]
            near = np.flatnonzero(d < self.radius)
            if len(near):
                w = self.radius - d[near]                                 # overlap weights, 0 at release
            else:                       # the nearest face(s), the centre outside or deeper than r inside
                d_min = float(d.min())
                near = np.flatnonzero(d <= d_min + 1e-9 * max(d_min, self.radius))
                w = np.ones(len(near))
            nf = np.cross(b[near] - a[near], c[near] - a[near])          # outward face normals [M, 3]
            nf /= np.maximum(np.linalg.norm(nf, axis=1, keepdims=True), 1e-300)
            dn = d[near]
            un = u[near]
            n = (w[:, None] * nf).sum(axis=0)
            n /= max(float(np.linalg.norm(n)), 1e-300)
            k = int(np.argmin(dn))                                        # the nearest triangle
            s = float(dn[k]) if float(un[k] @ n) >= 0.0 else -float(dn[k])
            p = (w[:, None] * pts[near]).sum(axis=0) / w.sum()
            tri, w_tri = f[near[k]], bary[near[k]]
        else:
            u = x - q[self.surface_nodes]
            dist2 = np.einsum("ij,ij->i", u, u)
            j = int(np.argmin(dist2))
            p, dj = q[self.surface_nodes[j]], float(np.sqrt(dist2[j]))
            n = u[j] / dj if dj > 1e-12 else np.array([0.0, 0.0, 1.0])
            s = dj
            tri, w_tri = self.surface_nodes[j:j + 1], np.ones(1)
        depth = self.radius - s
        if depth <= 0.0:
            return ContactResult(np.zeros(3), np.zeros((3, 3)), False, depth, p, n)
        force = self.k * depth * n                                        # on the user
        stiffness = -self.k * np.outer(n, n)
        self._distribute(-force, p, q, tri, w_tri)
        return ContactResult(force, stiffness, True, depth, p, n)

    def _distribute(self, load: np.ndarray, p: np.ndarray, q: np.ndarray, tri: np.ndarray, w_tri: np.ndarray) -> None:
        """Share the body load [3] N among loadable nodes near p (hat weights), else the triangle's vertices."""
        if self.load_radius > 0:
            r = np.linalg.norm(q[self.loadable] - p, axis=1)
            w = np.clip(1.0 - r / self.load_radius, 0.0, None)
            total = w.sum()
            if total > 0:
                self.loads[self.loadable] = (w / total)[:, None] * load
                return
        self.loads[tri] = w_tri[:, None] * load
