"""Tetrahedral meshes: our own gmsh geometries (meshes/*.geo) and external files via meshio.

Every path ends in plain arrays (points (N, 3) [m], tets (T, 4)) and then in
``dolfinx.mesh.create_mesh`` with a P1 tetrahedral coordinate element (gmshio is avoided: it
crashed on the SOFA liver mesh).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from thermognn.core.config import project_path
from thermognn.core.errors import ConfigError, DataError


def gmsh_geo_to_arrays(geo: str | os.PathLike, params: dict[str, float] | None = None,
                       seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mesh a .geo script in 3D with gmsh; ``params`` override its ``DefineConstant`` values.

    Returns points (N, 3) [m] and tets (T, 4) (0-based, unused points removed).
    """
    import gmsh

    geo = Path(geo)
    if not geo.is_file():
        raise ConfigError(f"scene.mesh.geometry: mesh file {geo} not found")
    lines = [f"{k} = {float(v)!r};" for k, v in (params or {}).items()]
    lines.append(f'Include "{geo.resolve()}";')
    with tempfile.TemporaryDirectory() as tmp:
        wrapper = Path(tmp) / "wrapper.geo"
        wrapper.write_text("\n".join(lines) + "\n")
        gmsh.initialize(["-noenv"], readConfigFiles=False)
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.option.setNumber("General.Verbosity", 0)
            gmsh.option.setNumber("Mesh.RandomSeed", seed)
            gmsh.open(str(wrapper))
            gmsh.model.mesh.generate(3)
            tags, coords, _ = gmsh.model.mesh.getNodes()
            etypes, _, enodes = gmsh.model.mesh.getElements(dim=3)
        except Exception as exc:
            raise DataError(f"{geo}: gmsh failed ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") \
                from None
        finally:
            gmsh.finalize()
    if 4 not in list(etypes):
        raise DataError(f"{geo}: gmsh produced no linear tetrahedra")
    conn = np.asarray(enodes[list(etypes).index(4)], dtype=np.int64).reshape(-1, 4)
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    points = np.asarray(coords, dtype=float).reshape(-1, 3)
    return compact(points, index[conn])


def meshio_to_arrays(path: str | os.PathLike, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Read the tetrahedra of any meshio-readable file; coordinates multiplied by ``scale`` [m/unit]."""
    import meshio

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"scene.mesh.file: mesh file {path} not found")
    try:
        m = meshio.read(path)
    except Exception as exc:
        raise DataError(f"{path}: meshio could not read it ({type(exc).__name__})") from None
    tets = [c.data for c in m.cells if c.type == "tetra"]
    if not tets:
        raise DataError(f"{path}: no tetrahedra (expected a volume mesh)")
    return compact(np.asarray(m.points, dtype=float)[:, :3] * scale, np.concatenate(tets).astype(np.int64))


def compact(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop points no tet uses; renumber. points (N, 3), tets (T, 4)."""
    used = np.unique(tets)
    new = np.full(len(points), -1, dtype=np.int64)
    new[used] = np.arange(len(used))
    return points[used].copy(), new[tets]


def to_dolfinx(points: np.ndarray, tets: np.ndarray):
    """A serial dolfinx mesh of P1 tetrahedra from arrays."""
    import ufl
    from dolfinx import mesh as dmesh
    from mpi4py import MPI

    domain = ufl.Mesh(ufl.VectorElement("Lagrange", ufl.tetrahedron, 1))
    return dmesh.create_mesh(MPI.COMM_SELF, tets.astype(np.int64), points.astype(np.float64), domain)


def load_scene_mesh(mesh_cfg, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points and tets for a scene's ``mesh`` config node.

    Either ``geometry`` (a .geo script; parameters from ``size`` [Lx, Ly, Lz] and ``cell_size``
    for the block, or a ``params`` mapping) or ``file`` (meshio-readable, with ``scale`` [m/unit]
    and optional ``center: true`` to move the bounding-box centre of the base to the origin).
    """
    geometry = mesh_cfg.get("geometry", None)
    file = mesh_cfg.get("file", None)
    if geometry:
        params: dict[str, float] = {}
        if mesh_cfg.get("size", None) is not None:
            size = [float(x) for x in mesh_cfg["size"]]
            if len(size) != 3 or min(size) <= 0:
                raise ConfigError(f"scene.mesh.size = {size}: expected three positive lengths [m]")
            params.update(Lx=size[0], Ly=size[1], Lz=size[2])
        if mesh_cfg.get("cell_size", None) is not None:
            params["h"] = float(mesh_cfg["cell_size"])
        for k, v in (mesh_cfg.get("params", None) or {}).items():
            params[str(k)] = float(v)
        return gmsh_geo_to_arrays(project_path(str(geometry)), params, seed=seed)
    if file:
        points, tets = meshio_to_arrays(project_path(str(file)), float(mesh_cfg.get("scale", 1.0)))
        if mesh_cfg.get("center", False):
            lo, hi = points.min(0), points.max(0)
            points = points - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        return points, tets
    raise ConfigError("scene.mesh: expected 'geometry' (a .geo file) or 'file' (a meshio-readable mesh)")
