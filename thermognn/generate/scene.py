"""A scene = mesh + node types + material + loads + time stepping, read from ``cfg.scene``.

Node types (``thermognn.core.schema``): 0 free, 1 clamped (Dirichlet u = 0), 2 loadable surface.
Face selectors for ``mesh.clamp`` / ``mesh.loadable`` (a string or a list of strings):
``bottom``/``top`` (= ``zmin``/``zmax``), ``xmin``, ``xmax``, ``ymin``, ``ymax``, ``zmin``, ``zmax``,
optionally with a band ``zmin:0.1`` (nodes within 10 % of the extent from that side),
``surface`` (every boundary node) and ``upper`` (boundary nodes whose outward normal points up,
n_z > 0.5: the top of a curved shell). Clamped wins over loadable.

Loads: the load points are the loadable nodes in one seeded order
(``numpy.random.default_rng(loads.seed).permutation``), case k pressing the k-th. ``loads.magnitude``
is the total force [N], or a list of them: with P loadable nodes, case k presses point k mod P with
the (k // P)-th magnitude, so the first P cases press P distinct points at the first magnitude and
the next P press them again harder or softer (``loads.n_trajectories`` can be at most P times the
number of magnitudes). Cases that share a point share a split in ``train`` (trajectories are split
by load point), so no test trajectory repeats a training point. ``loads.between_nodes`` adds that
many load points between the nodes (seeded, uniform over the area of the loadable surface), each
pressed at every magnitude after all the node cases (case P·R + r·B + j presses point j with the
r-th of R magnitudes); each shares the split group of the loadable node nearest to it, so a
held-out node keeps its neighbourhood out of training, and a point whose loaded nodes are those of
an earlier case is drawn again (every case distinct). The loadable nodes within
``loads.radius`` of the point share the force equally, directed along the inward surface normal at
the load point (at the nearest loadable node), and that node shares it too;
the force ramps over ``ramp_steps`` steps and is then held. ``ramp_shape``: ``linear`` or
``smooth`` (cubic smoothstep 3s² − 2s³: zero load rate at start and end, so the dynamic response
is not kicked by a jump in load rate, which the undamped trapezoidal rule would keep ringing in
the modes faster than the time step).

Time: ``time.dt`` [s] is the step between stored states. ``time.substeps`` k solves each stored
step as k FE steps of dt/k, the loads linear between the stored steps' loads (the loads the
dataset stores define its loading, as every later stage reads them): the trapezoidal rule's error
falls as (dt/k)² where the motion is resolved (about as dt/k where stiff damped modes ring), so a
scene whose dt does not resolve its motion can be stored at dt and solved finer; the priors of
``train`` still step at dt. ``time.convergence_check`` n (default 1) re-solves the first n cases
at 2k sub-steps and stores how far the data are from that (``generate``'s ``time_convergence``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from thermognn.core.errors import ConfigError
from thermognn.core.schema import NODE_CLAMPED, NODE_FREE, NODE_SURFACE, Mesh
from thermognn.core.state import check_effects

from .materials import Material, material_from_config
from .solid import SolverOptions

INTEGRATORS = ("newmark", "generalized_alpha", "quasi_static")
RAMP_SHAPES = ("linear", "smooth")


@dataclass
class LoadSpec:
    n_trajectories: int
    magnitude: float | tuple[float, ...]  # [N] total force of every case, or one per round of points
    radius: float           # [m]
    ramp_steps: int
    ramp_shape: str         # linear | smooth
    seed: int
    between_nodes: int = 0  # load points between the loadable nodes, after the node cases (module docstring)

    @property
    def magnitudes(self) -> tuple[float, ...]:
        """The total forces [N] of the rounds of load points (one value: every case alike)."""
        m = self.magnitude
        return tuple(float(x) for x in m) if isinstance(m, (tuple, list)) else (float(m),)


@dataclass
class SceneSpec:
    """Everything needed to simulate a scene, validated (no dolfinx objects yet)."""

    name: str
    effects: tuple[str, ...]
    store_internal: bool
    material: Material
    options: SolverOptions
    points: np.ndarray       # (N0, 3) [m] mesh vertices as read (dolfinx reorders them)
    tets: np.ndarray         # (T, 4)
    mesh_cfg: object
    loads: LoadSpec
    dt: float                # [s] between stored states
    steps: int
    substeps: int = 1        # FE steps per stored step (each Δt / substeps), loads linear between
    convergence_check: int = 1   # cases re-solved at twice the substeps to measure the data's time error


def _get(node, key, default=None):
    return node.get(key, default) if node is not None else default


def _positive(value, key: str, kind=float):
    try:
        v = kind(value)
    except (TypeError, ValueError):
        raise ConfigError(f"scene.{key} = {value!r}: expected a positive {kind.__name__}") from None
    if v <= 0:
        raise ConfigError(f"scene.{key} = {value!r}: expected a positive {kind.__name__}")
    return v


def _non_negative_int(value, key: str) -> int:
    try:
        v = int(value)
    except (TypeError, ValueError):
        v = -1
    if v < 0 or v != value:
        raise ConfigError(f"{key} = {value!r}: expected a whole number >= 0")
    return v


def scene_from_config(sc) -> SceneSpec:
    """Validate ``cfg.scene`` and read its mesh; ConfigError/DataError name the bad key."""
    from .meshing import load_scene_mesh

    if sc is None:
        raise ConfigError("config: missing group 'scene'")
    effects = check_effects(_get(sc, "effects", ["elastic"]))
    mat = material_from_config(_get(sc, "material", {}))
    if "viscous" in effects and not mat.prony:
        raise ConfigError("scene.material.prony: the 'viscous' effect needs at least one Prony term")
    t = _get(sc, "time", {})
    dt = _positive(_get(t, "dt"), "time.dt")
    steps = _positive(_get(t, "steps"), "time.steps", int)
    substeps = _get(t, "substeps", 1)
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise ConfigError(f"scene.time.substeps = {substeps!r}: expected a whole number >= 1 (FE steps per stored step)")
    check = _non_negative_int(_get(t, "convergence_check", 1), "scene.time.convergence_check")
    integrator = str(_get(t, "integrator", "newmark"))
    if integrator not in INTEGRATORS:
        raise ConfigError(f"scene.time.integrator = {integrator!r}: expected one of {list(INTEGRATORS)}")
    if "inertia" in effects and integrator == "quasi_static":
        raise ConfigError("scene.time.integrator = 'quasi_static' contradicts the 'inertia' effect")
    if "inertia" not in effects:
        integrator = "quasi_static"
    rho_inf = float(_get(t, "rho_inf", 1.0))
    if not 0.0 <= rho_inf <= 1.0:
        raise ConfigError(f"scene.time.rho_inf = {rho_inf}: expected in [0, 1] (generalized-alpha)")
    rayleigh = [float(x) for x in (_get(t, "rayleigh", None) or [0.0, 0.0])]
    if len(rayleigh) != 2 or min(rayleigh) < 0:
        raise ConfigError(f"scene.time.rayleigh = {rayleigh}: expected [alpha_M >= 0, beta_K >= 0]")
    s = _get(sc, "solver", {})
    options = SolverOptions(
        degree=1,
        quadrature_degree=int(_positive(_get(s, "quadrature_degree", 2), "solver.quadrature_degree", int)),
        integrator=integrator,
        beta=float(_get(t, "beta", 0.25)), gamma=float(_get(t, "gamma", 0.5)),
        rho_inf=float(_get(t, "rho_inf", 1.0)),
        rayleigh=(rayleigh[0], rayleigh[1]),
        gravity=tuple(float(x) for x in (_get(sc, "gravity", None) or [0.0, 0.0, -9.81])),
        rtol=float(_get(s, "newton_rtol", 1e-8)), atol=float(_get(s, "newton_atol", 1e-10)),
        max_iterations=int(_positive(_get(s, "max_iterations", 25), "solver.max_iterations", int)),
        min_step_fraction=float(_positive(_get(s, "min_step_fraction", 1 / 16), "solver.min_step_fraction")),
    )
    ld = _get(sc, "loads", {})
    loads = LoadSpec(
        n_trajectories=_positive(_get(ld, "n_trajectories"), "loads.n_trajectories", int),
        magnitude=_magnitudes(_get(ld, "magnitude", 1.0)),
        radius=float(_get(ld, "radius", 0.0)),
        ramp_steps=max(1, int(_get(ld, "ramp_steps", 1))),
        ramp_shape=str(_get(ld, "ramp_shape", "linear")),
        seed=int(_get(ld, "seed", 0)),
        between_nodes=_non_negative_int(_get(ld, "between_nodes", 0), "scene.loads.between_nodes"),
    )
    if loads.ramp_shape not in RAMP_SHAPES:
        raise ConfigError(f"scene.loads.ramp_shape = {loads.ramp_shape!r}: expected one of {list(RAMP_SHAPES)}")
    mesh_cfg = _get(sc, "mesh", None)
    if mesh_cfg is None:
        raise ConfigError("scene.mesh: missing (expected 'geometry' or 'file')")
    points, tets = load_scene_mesh(mesh_cfg)
    return SceneSpec(str(_get(sc, "name", "scene")), effects, bool(_get(sc, "store_internal", False)), mat,
                     options, points, tets, mesh_cfg, loads, dt, steps, substeps, check)


# -- node types and surface geometry ---------------------------------------------------------


def boundary_faces_outward(nodes: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (F, 3), oriented with outward normals."""
    local = np.array([[1, 2, 3, 0], [0, 3, 2, 1], [0, 1, 3, 2], [0, 2, 1, 3]])  # face + opposite vertex
    faces = np.concatenate([tets[:, f[:3]] for f in local])
    opposite = np.concatenate([tets[:, f[3]] for f in local])
    key = np.sort(faces, axis=1)
    _, idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    sel = idx[counts == 1]
    f, o = faces[sel], opposite[sel]
    a, b, c = nodes[f[:, 0]], nodes[f[:, 1]], nodes[f[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", n, nodes[o] - a) > 0
    f[flip] = f[flip][:, [0, 2, 1]]
    return f


def vertex_normals(nodes: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted outward unit normals (N, 3) (zero for interior nodes)."""
    a, b, c = nodes[faces[:, 0]], nodes[faces[:, 1]], nodes[faces[:, 2]]
    n = np.cross(b - a, c - a)  # (F, 3), |n| = 2 area
    out = np.zeros_like(nodes)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    norm = np.linalg.norm(out, axis=1)
    out[norm > 0] /= norm[norm > 0, None]
    return out


def select_nodes(selector, nodes: np.ndarray, surface: np.ndarray, key: str,
                 normals: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask (N,) of the nodes a face selector names (see module docstring)."""
    sels = [selector] if isinstance(selector, str) else list(selector or [])
    lo, hi = nodes.min(0), nodes.max(0)
    extent = np.maximum(hi - lo, 1e-30)
    mask = np.zeros(len(nodes), dtype=bool)
    axes = {"x": 0, "y": 1, "z": 2}
    for sel in sels:
        sel = str(sel)
        name, _, band = sel.partition(":")
        name = {"bottom": "zmin", "top": "zmax"}.get(name, name)
        if name == "surface":
            mask |= surface
            continue
        if name == "upper" and normals is not None:
            mask |= surface & (normals[:, 2] > 0.5)
            continue
        if len(name) != 4 or name[0] not in axes or name[1:] not in ("min", "max"):
            raise ConfigError(f"scene.mesh.{key} = {sel!r}: expected top, bottom, surface, upper, "
                              "xmin..zmax (optionally ':fraction')")
        ax = axes[name[0]]
        try:
            frac = float(band) if band else 1e-6
        except ValueError:
            raise ConfigError(f"scene.mesh.{key} = {sel!r}: band after ':' must be a number") from None
        if name.endswith("min"):
            mask |= nodes[:, ax] <= lo[ax] + frac * extent[ax]
        else:
            mask |= nodes[:, ax] >= hi[ax] - frac * extent[ax]
    return mask


def node_types(nodes: np.ndarray, tets: np.ndarray, mesh_cfg) -> np.ndarray:
    """(N,) int8: 0 free, 1 clamped, 2 loadable surface."""
    faces = boundary_faces_outward(nodes, tets)
    surface = np.zeros(len(nodes), dtype=bool)
    surface[faces.ravel()] = True
    normals = vertex_normals(nodes, faces)
    clamped = select_nodes(_get(mesh_cfg, "clamp", "bottom"), nodes, surface, "clamp", normals)
    loadable = select_nodes(_get(mesh_cfg, "loadable", "top"), nodes, surface, "loadable", normals) & surface
    t = np.full(len(nodes), NODE_FREE, dtype=np.int8)
    t[loadable] = NODE_SURFACE
    t[clamped] = NODE_CLAMPED
    if not clamped.any():
        raise ConfigError(f"scene.mesh.clamp = {_get(mesh_cfg, 'clamp')!r}: selects no node")
    if not loadable.any() or (t == NODE_SURFACE).sum() == 0:
        raise ConfigError(f"scene.mesh.loadable = {_get(mesh_cfg, 'loadable')!r}: selects no free surface node")
    return t


def _magnitudes(value) -> float | tuple[float, ...]:
    """``scene.loads.magnitude``: a force [N] or a non-empty list of them, every one finite."""
    many = not isinstance(value, (int, float, str)) and hasattr(value, "__iter__")
    try:
        values = [float(x) for x in value] if many else [float(value)]
    except (TypeError, ValueError):
        values = []
    if not values or not all(np.isfinite(values)):
        raise ConfigError(f"scene.loads.magnitude = {value!r}: expected a force [N] or a list of forces")
    return tuple(values) if many else values[0]


class LoadCase(NamedTuple):
    """One load case of ``generate``: where it presses and with what."""

    point: np.ndarray       # (3,) [m] the load point
    load_nodes: np.ndarray  # (K,) the loadable nodes sharing the force
    force: np.ndarray       # (N, 3) [N] the nodal force at full magnitude
    point_index: int        # the loadable node (its place in the seeded order) pressed or nearest: the split group


def loadable_faces(nodes: np.ndarray, tets: np.ndarray, node_type: np.ndarray) -> np.ndarray:
    """(F, 3) the outward boundary triangles whose three nodes are loadable: the loadable surface."""
    faces = boundary_faces_outward(nodes, tets)
    return faces[np.all(node_type[faces] == NODE_SURFACE, axis=1)]


def _loaded_nodes(point: np.ndarray, nodes: np.ndarray, candidates: np.ndarray, radius: float) -> tuple[np.ndarray, int]:
    """(the loadable nodes within ``radius`` of ``point`` and the nearest one, sorted; the nearest)."""
    dist = np.linalg.norm(nodes[candidates] - point, axis=1)
    nearest = int(candidates[np.argmin(dist)])
    within = candidates[dist <= radius] if radius > 0 else candidates[:0]
    return np.union1d(within, [nearest]).astype(np.int64), nearest


def between_node_points(nodes: np.ndarray, node_type: np.ndarray, faces: np.ndarray, loads: LoadSpec) -> np.ndarray:
    """(B, 3) [m] the ``loads.between_nodes`` load points between the loadable nodes: seeded
    (``loads.seed``), uniform over the area of the loadable triangles ``faces`` (F, 3); a point whose
    loaded nodes are those of a node case or of an earlier point is drawn again."""
    count = loads.between_nodes
    if count == 0:
        return np.zeros((0, 3))
    if faces is None or len(faces) == 0:
        raise ConfigError("scene.loads.between_nodes: the loadable surface has no triangle to draw points on")
    candidates = np.flatnonzero(node_type == NODE_SURFACE)
    seen = {tuple(_loaded_nodes(nodes[c], nodes, candidates, loads.radius)[0]) for c in candidates}
    a, b, c = (nodes[faces[:, i]] for i in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng([loads.seed, 1])
    points: list[np.ndarray] = []
    for _ in range(200 * count + 1000):
        if len(points) == count:
            break
        f = int(rng.choice(len(faces), p=area / area.sum()))
        r1, r2 = rng.random(2)
        s = np.sqrt(r1)                                           # uniform on the triangle
        point = (1 - s) * a[f] + s * (1 - r2) * b[f] + s * r2 * c[f]
        key = tuple(_loaded_nodes(point, nodes, candidates, loads.radius)[0])
        if key not in seen:
            seen.add(key)
            points.append(point)
    if len(points) < count:
        raise ConfigError(f"scene.loads.between_nodes = {count}: only {len(points)} load points between the nodes "
                          f"load other nodes than every earlier case (scene.loads.radius = {loads.radius} m); "
                          "lower it or refine scene.mesh.cell_size")
    return np.array(points)


def load_case(k: int, nodes: np.ndarray, node_type: np.ndarray, normals: np.ndarray,
              loads: LoadSpec, between: np.ndarray | None = None) -> LoadCase:
    """Load case k (module docstring). With P loadable nodes and R magnitudes, cases k < P R
    press the (k mod P)-th node of one seeded order with the (k // P)-th magnitude, so cases
    0..P-1 press P distinct points (``check_load_cases``); the next ``loads.between_nodes`` times R
    press the points ``between`` (B, 3) [m] of :func:`between_node_points`, drawn once by the caller."""
    candidates = np.flatnonzero(node_type == NODE_SURFACE)
    check_load_cases(loads, len(candidates))
    P, R = len(candidates), len(loads.magnitudes)
    n_cases = (P + loads.between_nodes) * R
    if not 0 <= k < n_cases:
        raise ConfigError(f"load case {k}: expected 0 <= k < {n_cases} (the loadable nodes and the points "
                          "between them, times the magnitudes)")
    order = np.random.default_rng(loads.seed).permutation(candidates)
    if k < P * R:
        round_, index = divmod(k, P)
        point = nodes[int(order[index])].copy()
    else:
        if between is None or len(between) != loads.between_nodes:
            raise ValueError(f"load case {k}: needs the {loads.between_nodes} points between the nodes "
                             "(between_node_points)")
        round_, j = divmod(k - P * R, loads.between_nodes)
        point = between[j]
    load_nodes, nearest = _loaded_nodes(point, nodes, candidates, loads.radius)
    force = np.zeros_like(nodes)
    force[load_nodes] = loads.magnitudes[round_] / len(load_nodes) * -normals[nearest]
    return LoadCase(point, load_nodes, force, int(np.flatnonzero(order == nearest)[0]))


def check_load_cases(loads: LoadSpec, n_loadable: int) -> None:
    """ConfigError unless the load cases fit: each magnitude presses every point at most once."""
    rounds, points = len(loads.magnitudes), n_loadable + loads.between_nodes
    if loads.n_trajectories > points * rounds:
        raise ConfigError(
            f"scene.loads.n_trajectories = {loads.n_trajectories}: at most {points * rounds} ({n_loadable} "
            f"loadable nodes of scene.mesh.loadable and {loads.between_nodes} points between them "
            f"(scene.loads.between_nodes), each pressed once per magnitude of scene.loads.magnitude, "
            f"{rounds} here): refine scene.mesh.cell_size, widen scene.mesh.loadable, list more magnitudes "
            "or add points between the nodes")


def ramp(t: float, dt: float, ramp_steps: int, shape: str = "linear") -> float:
    """Load factor in [0, 1] over ramp_steps * dt, then held: linear, or smooth (3s² − 2s³)."""
    s = float(min(1.0, max(0.0, t / (ramp_steps * dt))))
    return s * s * (3.0 - 2.0 * s) if shape == "smooth" else s


def dataset_mesh(nodes: np.ndarray, cells: np.ndarray, node_type: np.ndarray) -> Mesh:
    return Mesh(nodes=nodes, tets=cells[:, :4], node_type=node_type)
