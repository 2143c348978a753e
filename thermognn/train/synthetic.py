"""A tiny analytic dataset for tests and benchmarks (no FE solver needed).

A box of n_x x n_y x n_z nodes (each cube split into 6 tetrahedra), clamped at z = 0, loaded on
its top face. The motion is affine in the height Z: two decoupled linear oscillators, axial
compression a(t) and shear b(t), driven by a load F = (F_x, 0, F_z) switched on at t = dt::

    u(X, t) = (b(t) Z / H, 0, a(t) Z / H)       a'' + 2 zeta w_a a' + w_a^2 a = F_z / m
                                                b'' + 2 zeta w_b b' + w_b^2 b = F_x / m

    sigma_33 = E a / H,  sigma_13 = G b / H  (uniform), the other stress components 0.

The oscillators are integrated exactly (zeta = 0) or with many RK4 substeps (zeta > 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from thermognn.core.io import versions_json
from thermognn.core.schema import NODE_CLAMPED, NODE_FREE, NODE_SURFACE, DatasetWriter, Mesh, Trajectory
from thermognn.core.state import state_layout


def box_mesh(nx: int = 3, ny: int = 3, nz: int = 3, size=(0.04, 0.04, 0.02)) -> Mesh:
    """Structured tetrahedral box [0, Lx] x [0, Ly] x [0, Lz] [m]; bottom clamped, top loadable."""
    xs, ys, zs = (np.linspace(0.0, L, n) for L, n in zip(size, (nx, ny, nz)))
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    nodes = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    idx = np.arange(nx * ny * nz).reshape(nx, ny, nz)
    kuhn = [(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)]
    tets = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            for k in range(nz - 1):
                # vertex v = (dx, dy, dz) bits; Kuhn simplices share the diagonal 0-7
                c = [idx[i + (v & 1), j + (v >> 1 & 1), k + (v >> 2 & 1)] for v in range(8)]
                tets += [[c[a] for a in t] for t in kuhn]
    node_type = np.full(len(nodes), NODE_FREE, np.int8)
    node_type[np.isclose(nodes[:, 2], size[2])] = NODE_SURFACE
    node_type[np.isclose(nodes[:, 2], 0.0)] = NODE_CLAMPED
    return Mesh(nodes, np.asarray(tets, np.int64), node_type)


def _oscillate(F: float, w: float, zeta: float, m: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacement and velocity of x'' + 2 zeta w x' + w^2 x = F/m, x(0) = x'(0) = 0, load on for t > 0."""
    if zeta == 0.0:
        return F / (m * w**2) * (1 - np.cos(w * t)), F / (m * w) * np.sin(w * t)
    x, v, out_x, out_v = 0.0, 0.0, [0.0], [0.0]
    acc = lambda x_, v_: F / m - 2 * zeta * w * v_ - w**2 * x_  # noqa: E731
    for k in range(1, len(t)):
        h = (t[k] - t[k - 1]) / 200
        for _ in range(200):
            k1x, k1v = v, acc(x, v)
            k2x, k2v = v + h / 2 * k1v, acc(x + h / 2 * k1x, v + h / 2 * k1v)
            k3x, k3v = v + h / 2 * k2v, acc(x + h / 2 * k2x, v + h / 2 * k2v)
            k4x, k4v = v + h * k3v, acc(x + h * k3x, v + h * k3v)
            x, v = x + h / 6 * (k1x + 2 * k2x + 2 * k3x + k4x), v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        out_x.append(x)
        out_v.append(v)
    return np.asarray(out_x), np.asarray(out_v)


def write_oscillator_dataset(path, n_trajectories: int = 6, steps: int = 10, dt: float = 0.01,
                             shape=(3, 3, 3), viscous: bool = False, seed: int = 0,
                             force_scale: float = 1.0, with_tets: bool = True) -> Path:
    """Write the analytic box dataset (schema v1). effects: elastic, inertia (+ viscous: damped).
    ``with_tets=False`` stores graph edges and no tetrahedra (like imported datasets)."""
    mesh = box_mesh(*shape)
    if not with_tets:
        mesh = Mesh(mesh.nodes, np.zeros((0, 4), np.int64), mesh.node_type, graph_edges=mesh.edges())
    H = float(mesh.nodes[:, 2].max())
    effects = ["elastic", "viscous", "inertia"] if viscous else ["elastic", "inertia"]
    layout = state_layout(effects)
    D = layout.dim
    rng = np.random.default_rng(seed)
    top = np.flatnonzero(mesh.node_type == NODE_SURFACE)
    mass, w_a, w_b, zeta = 0.01, 2 * np.pi * 4.0, 2 * np.pi * 2.5, (0.3 if viscous else 0.0)  # kg, rad/s
    E_mod, G_mod = 6.0e4, 2.0e4  # [Pa]
    t = np.arange(steps + 1) * dt
    config = f"synthetic: oscillator\nshape: {list(shape)}\nviscous: {viscous}\nseed: {seed}\n"
    with DatasetWriter(path, mesh, layout, dt, config, versions_json(), "synthetic", effects) as w:
        for k in range(n_trajectories):
            Fz, Fx = -force_scale * rng.uniform(0.2, 1.0), force_scale * rng.uniform(-0.5, 0.5)  # [N]
            a, va = _oscillate(Fz, w_a, zeta, mass, t)
            b, vb = _oscillate(Fx, w_b, zeta, mass, t)
            zeta_h = mesh.nodes[:, 2] / H                                    # [N]
            z = np.zeros((steps + 1, len(mesh.nodes), D))
            z[:, :, 0:3] = mesh.nodes[None]
            z[:, :, 0] += b[:, None] * zeta_h[None]
            z[:, :, 2] += a[:, None] * zeta_h[None]
            z[:, :, 3] = vb[:, None] * zeta_h[None]
            z[:, :, 5] = va[:, None] * zeta_h[None]
            z[:, :, 6 + 2] = E_mod * a[:, None] / H                          # sigma_33
            z[:, :, 6 + 4] = G_mod * b[:, None] / H                          # sigma_13
            force = np.zeros((steps + 1, len(mesh.nodes), 3))
            force[1:, top, 0] = Fx / len(top)
            force[1:, top, 2] = Fz / len(top)
            w.write(Trajectory(name=f"traj{k}", time=t, z=z, force=force, load_nodes=top,
                               load_point=mesh.nodes[top].mean(0)))
    return Path(path)
