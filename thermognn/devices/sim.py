"""A virtual haptic device: the tool follows a scripted path relative to the body.

Paths (option ``path``), placed on the model's reference bounding box (``attach_scene``), all
starting ``clearance`` above the body's top surface under the tool and pressing ``depth`` into it:
that surface is the highest surface triangle over the tool's (x, y) once ``attach_surface`` has
given the surface (serve does; beyond its outline, or given nodes only, the highest surface node
within ``SURFACE_REACH``; under the liver's palpate points it lies 3.4-55.9 mm below the box's top),
else the box's top face (z = max):

    press     up and down at the centre of the top face, period ``period`` [s]
    palpate   one press per point of a 3x3 grid over the top face
    drag      press to depth, then slide along x and back

Positions are in the model frame (``scene_frame = True``); velocity by central difference of
the path. Limits mirror a Geomagic Touch unless overridden (``max_force`` etc. options).
"""

from __future__ import annotations

import math
import time

import numpy as np

from thermognn.core.errors import DeviceError

from .base import Device, DeviceReading, DeviceSpecs

PATHS = ("press", "palpate", "drag")
#: surface heights are looked up on a grid of this many cells a side over the bounding box
SURFACE_GRID = 64
#: a surface node counts under the tool within this fraction of the box's larger horizontal side
SURFACE_REACH = 0.03


class SimDevice(Device):
    """Scripted virtual tool (a real plugin: same interface, limits and timing as hardware)."""

    scene_frame = True

    def __init__(self, path: str = "press", period: float = 2.0, depth: float | None = None,
                 clearance: float | None = None, max_force: float = 3.3,
                 max_continuous_force: float = 0.88, max_stiffness: float = 1000.0,
                 max_force_rate: float = 100.0, **options) -> None:
        super().__init__(**options)
        if path not in PATHS:
            raise DeviceError(f"serve.path: unknown sim path '{path}', expected one of {list(PATHS)}")
        if period <= 0:
            raise DeviceError(f"sim device: period = {period}, expected > 0 s")
        self.path = path
        self.period = float(period)        # [s]
        self._depth = depth                # [m] below the undeformed top face (None: 20 % of height)
        self._clearance = clearance        # [m] above it at rest (None: 10 % of height)
        self.specs = DeviceSpecs("sim", float(max_force), float(max_continuous_force), float(max_stiffness),
                                 (0.16, 0.12, 0.07), 1000.0, float(max_force_rate))
        self.lo = np.array([-0.02, -0.02, 0.0])
        self.hi = np.array([0.02, 0.02, 0.02])
        self.tool_radius = 0.003
        self._top: np.ndarray | None = None      # [SURFACE_GRID, SURFACE_GRID] m: the surface's top z
        self.last_force = np.zeros(3)
        self._t0 = 0.0
        self._x = np.zeros(3)

    def attach_scene(self, lo, hi, tool_radius: float) -> None:
        self.lo = np.asarray(lo, dtype=float).copy()
        self.hi = np.asarray(hi, dtype=float).copy()
        self.tool_radius = float(tool_radius)

    def attach_surface(self, points, faces=None) -> None:
        """Tabulate the top of the body's surface (nodes ``points`` [M, 3] m, triangles ``faces``
        [F, 3] of indices into them, or None) over the bounding box: per grid cell, the highest
        triangle over the cell's centre (a vertical line from above meets it first); where no
        triangle is (beyond the body's outline, or without faces), the highest node within the
        reach of the centre, or the nearest node's height where none is. The triangles matter on a
        closed body whose top face is meshed coarser than its bottom: there the nodes near a cell
        in plan may all be the bottom face's."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(pts) == 0:
            self._top = None
            return
        tris = np.zeros((0, 3), dtype=np.int64) if faces is None else np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        ext = np.maximum(self.hi[:2] - self.lo[:2], 1e-12)
        centres = [self.lo[k] + (np.arange(SURFACE_GRID) + 0.5) * ext[k] / SURFACE_GRID for k in (0, 1)]
        reach = SURFACE_REACH * float(ext.max())
        a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]                      # [F, 3] m each
        ab, ac = b - a, c - a
        area = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]                                 # [F] 2 x plan area
        upright = np.abs(area) > 1e-12 * float(ext.max()) ** 2      # (vertical triangles cover no point)
        a, ab, ac, area = a[upright], ab[upright], ac[upright], area[upright]
        py = centres[1][:, None]                                                         # [G, 1] m
        top = np.empty((SURFACE_GRID, SURFACE_GRID))
        dy2 = (centres[1][:, None] - pts[:, 1]) ** 2                                     # [G, M] m²
        for i, x in enumerate(centres[0]):                   # a row at a time: [G, M], not [G, G, M]
            wb = ((x - a[:, 0]) * ac[:, 1] - (py - a[:, 1]) * ac[:, 0]) / area           # [G, F] barycentric
            wc = (ab[:, 0] * (py - a[:, 1]) - ab[:, 1] * (x - a[:, 0])) / area
            over = (wb >= -1e-9) & (wc >= -1e-9) & (wb + wc <= 1.0 + 1e-9)
            z_tri = np.where(over, a[:, 2] + wb * ab[:, 2] + wc * ac[:, 2], -np.inf)
            d2 = (x - pts[:, 0]) ** 2 + dy2
            near = np.where(d2 <= reach * reach, pts[:, 2], -np.inf).max(axis=-1)
            by_nodes = np.where(np.isfinite(near), near, pts[np.argmin(d2, axis=-1), 2])
            highest = z_tri.max(axis=-1) if len(a) else np.full(SURFACE_GRID, -np.inf)
            top[i] = np.where(np.isfinite(highest), highest, by_nodes)
        self._top = top

    def surface_top(self, x: float, y: float) -> float:
        """z [m] of the body's top surface under (x, y) (the box's top without a surface)."""
        if self._top is None:
            return float(self.hi[2])
        ext = np.maximum(self.hi[:2] - self.lo[:2], 1e-12)
        i = min(max(int((x - self.lo[0]) / ext[0] * SURFACE_GRID), 0), SURFACE_GRID - 1)
        j = min(max(int((y - self.lo[1]) / ext[1] * SURFACE_GRID), 0), SURFACE_GRID - 1)
        return float(self._top[i, j])

    # geometry of the path -----------------------------------------------------------------
    @property
    def depth(self) -> float:
        return self._depth if self._depth is not None else 0.2 * float(self.hi[2] - self.lo[2])

    @property
    def clearance(self) -> float:
        return self._clearance if self._clearance is not None else 0.1 * float(self.hi[2] - self.lo[2])

    def position_at(self, t: float, out: np.ndarray | None = None) -> np.ndarray:
        """Tool centre [3] m at time ``t`` [s] after open."""
        out = np.empty(3) if out is None else out
        c = 0.5 * (self.lo + self.hi)
        ext = self.hi - self.lo
        z_rest = self.hi[2] + self.tool_radius + self.clearance
        travel = self.clearance + self.depth
        T = self.period
        x, y = c[0], c[1]
        if self.path == "press":
            s = 0.5 * (1.0 - math.cos(2.0 * math.pi * t / T))
        elif self.path == "palpate":
            k = int(t // T) % 9
            x = c[0] + 0.3 * ext[0] * (k % 3 - 1)
            y = c[1] + 0.3 * ext[1] * (k // 3 - 1)
            s = 0.5 * (1.0 - math.cos(2.0 * math.pi * t / T))
        else:  # drag: descend in T/2, then slide +-30 % of the length along x
            if t < 0.5 * T:
                s = 0.5 * (1.0 - math.cos(2.0 * math.pi * t / T))
            else:
                s = 1.0
                x = c[0] + 0.3 * ext[0] * math.sin(2.0 * math.pi * (t - 0.5 * T) / (2.0 * T))
        if self._top is not None:          # the surface under the tool, not the box's top face
            z_rest = self.surface_top(x, y) + self.tool_radius + self.clearance
        out[0], out[1], out[2] = x, y, z_rest - travel * s
        return out

    # device interface ----------------------------------------------------------------------
    def _open(self) -> None:
        self._t0 = time.perf_counter()

    def _read(self) -> DeviceReading:
        now = time.perf_counter()
        t = now - self._t0
        r = self.reading
        r.t = now
        self.position_at(t, r.position)
        h = 5e-4
        self.position_at(t + h, self._x)
        np.subtract(self._x, r.position, out=r.velocity)
        r.velocity /= h
        return r

    def _set_force(self, force: np.ndarray) -> None:
        self.last_force[:] = force
