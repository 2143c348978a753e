"""The stress readout (``model.stress_readout``): a linear stencil of the displacements, fitted by
least squares, exact on a stress that is such a stencil; TorchScript; clear errors."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from thermognn.core.errors import DataError
from thermognn.train.model import TIGNN
from thermognn.train.stress_readout import (fit_stress_readout, mesh_symmetries, outside_modes, readout_spec,
                                            stencils, stress_action, with_stress_readout)

LAM, MU, H = 2.0e5, 1.0e5, 0.01                # Lamé constants [Pa], grid spacing [m]


def _grid(nx=7, ny=4, nz=4):
    """A structured grid of nx x ny x nz nodes (spacing H) and its grid-line edges (both ways)."""
    idx = np.array([(i, j, k) for i in range(nx) for j in range(ny) for k in range(nz)])
    number = {tuple(p): n for n, p in enumerate(idx)}
    edges = [(number[tuple(p)], number[tuple(p + d)]) for p in idx for d in np.eye(3, dtype=int)
             if tuple(p + d) in number]
    e = torch.tensor(edges).T
    return torch.tensor(idx * H, dtype=torch.float64), torch.cat([e, e.flip(0)], 1), idx


def _linear_elastic_stress(u, idx):
    """σ = λ tr(ε) I + 2 μ ε [Pa] (s11 s22 s33 s12 s13 s23) of the nodal displacement u [N, 3], with
    ε from the grid's finite differences (central inside, one-sided at faces): a 1-hop stencil."""
    shape = tuple(idx.max(0) + 1)
    g = np.zeros(shape + (3,))
    g[tuple(idx.T)] = u
    grad = np.stack([np.gradient(g, H, axis=a) for a in range(3)], -1)[tuple(idx.T)]  # [N, 3, 3] du_i/dx_a
    eps = 0.5 * (grad + grad.transpose(0, 2, 1))
    s = LAM * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 2 * MU * eps
    return np.stack([s[:, 0, 0], s[:, 1, 1], s[:, 2, 2], s[:, 0, 1], s[:, 0, 2], s[:, 1, 2]], 1)


def _snapshots(ref, idx, count, seed):
    """States z [count, N, 12]: random smooth displacements, zero velocity, their linear stress."""
    rng = np.random.default_rng(seed)
    X = ref.numpy()
    z = np.zeros((count, len(X), 12))
    for s in range(count):
        a, k = rng.normal(size=(3, 4)) * 1e-3, rng.normal(size=(4, 3)) * 30
        u = np.stack([np.sin(X @ k[m]) for m in range(4)], 1) @ a.T          # [N, 3] smooth fields
        z[s, :, :3], z[s, :, 6:] = X + u, _linear_elastic_stress(u, idx)
    return torch.tensor(z)


def test_readout_recovers_a_linear_stencil_stress_on_unseen_fields():
    """Fitted on some displacement fields, the readout gives a stencil stress of other fields
    to the ridge (4e-8 here), face, edge and corner nodes included; u = 0 gives σ = 0."""
    ref, ei, idx = _grid()
    train = _snapshots(ref, idx, 60, seed=0)
    readout, fit = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1)
    assert fit["fit_error"] < 1e-9
    # 7 x 4 x 4 grid, one hop: 3 x 3 x 3 = 27 classes of neighbourhood shape
    assert fit["classes"] == 27 and fit["weights"] == readout.fitted_weights() > 0
    test = _snapshots(ref, idx, 5, seed=1).double()
    for z in test:
        sigma = readout.double()(z[:, :3] - ref)
        assert torch.allclose(sigma, z[:, 6:], rtol=0, atol=1e-6 * z[:, 6:].abs().max())   # the ridge: 4e-8
    assert torch.equal(readout(torch.zeros_like(ref)), torch.zeros(len(ref), 6, dtype=torch.float64))


def test_a_relative_fit_minimises_the_snapshots_squared_relative_errors():
    """``relative``: each snapshot weighed by 1 / |σ| of it. On a stress the stencil reads exactly
    both fits are exact; on one it cannot (a quadratic term, the larger the louder), over snapshots
    whose stress spans two decades, the weighted least squares give the least sum of squared relative
    errors per snapshot, the plain ones the least sum of squared errors, 1 / |σ|^0.5 a mean relative
    error between them, and at the rest state σ = 0; a power outside [0, 1] is refused."""
    ref, ei, idx = _grid()
    z = _snapshots(ref, idx, 60, seed=0)
    cols = list(range(6, 12))
    for relative in (False, True):
        assert fit_stress_readout(ref, ei, [z], cols, hops=1, relative=relative)[1]["fit_error"] < 1e-8   # the ridge
    amplitude = torch.logspace(-2, 0, len(z), dtype=torch.float64)[:, None, None]          # [S, 1, 1]
    u = (z[:, :, :3] - ref) * amplitude                                                      # [S, N, 3]
    bent = z.clone()
    bent[:, :, :3] = ref + u
    bent[:, :, 6:] = z[:, :, 6:] * amplitude + 3e9 * u[:, :, :1] * u[:, :, 1:2]               # [S, N, 6]
    plain, fit_plain = fit_stress_readout(ref, ei, [bent], cols, hops=1)
    weighed, fit_weighed = fit_stress_readout(ref, ei, [bent], cols, hops=1, relative=True)
    assert fit_weighed["relative"] == 1.0 and fit_plain["relative"] == 0.0
    half = fit_stress_readout(ref, ei, [bent], cols, hops=1, relative=0.5)[1]      # 1 / |σ|^0.5: between them
    assert half["relative"] == 0.5 and fit_weighed["fit_error"] < half["fit_error"] < fit_plain["fit_error"]
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_relative = 2, expected true, false or the power"):
        fit_stress_readout(ref, ei, [bent], cols, hops=1, relative=2, source="d.h5")

    def squared_errors(readout):
        e = readout.double()(u) - bent[:, :, 6:]                                             # [S, N, 6]
        norms = bent[:, :, 6:].flatten(1).norm(dim=1)
        return float((e.flatten(1).norm(dim=1) ** 2).sum()), float(((e.flatten(1).norm(dim=1) / norms) ** 2).sum())
    (abs_plain, rel_plain), (abs_weighed, rel_weighed) = squared_errors(plain), squared_errors(weighed)
    assert rel_plain > 0 and abs_weighed > 0
    assert rel_weighed < 0.9 * rel_plain and abs_plain < abs_weighed
    assert fit_weighed["fit_error"] < fit_plain["fit_error"]       # the mean relative error it reports
    assert torch.equal(weighed(torch.zeros_like(ref)), torch.zeros(len(ref), 6, dtype=torch.float64))


def test_stencils_are_the_nodes_within_hops_and_shapes_repeat():
    ref, ei, idx = _grid()
    near, classes = stencils(ref.numpy(), ei.numpy(), 2)
    middle = np.flatnonzero((idx == [3, 1, 1]).all(1))[0]
    assert len(near[middle]) == 25 - 2                      # L1 distance <= 2 on the grid: 25, 2 beyond its faces
    # nodes at the same place relative to the boundary share their shape; others do not
    a, b = (np.flatnonzero((idx == p).all(1))[0] for p in ([3, 0, 0], [4, 0, 0]))
    c = np.flatnonzero((idx == [0, 0, 0]).all(1))[0]
    assert classes[a] == classes[b] != classes[c]
    assert all(np.abs(idx[j] - idx[c]).sum() <= 2 for j in near[c])


def test_mesh_symmetries_are_the_reflections_and_swaps_that_keep_the_mesh():
    """A 7 x 4 x 4 grid: mirrors in x, y, z and the y-z swap (16); its x = 0 face clamped, 8 (no
    x mirror); each maps nodes onto nodes about the box's centre, the identity first."""
    ref, ei, idx = _grid()
    X, e = ref.numpy(), ei.numpy()
    assert len(mesh_symmetries(X, e)) == 16
    clamped = (idx[:, 0] == 0).astype(np.int64)
    found = mesh_symmetries(X, e, clamped)
    assert len(found) == 8 and np.array_equal(found[0][0], np.eye(3))
    c = 0.5 * (X.min(0) + X.max(0))
    for R, p in found:
        assert R[0, 0] == 1 and np.allclose(X[p], c + (X - c) @ R.T) and np.array_equal(clamped[p], clamped)
    swap = np.array([[1.0, 0, 0], [0, 0, 1], [0, 1, 0]])
    sigma = np.array([1.0, 2, 3, 4, 5, 6])                               # s11 s22 s33 s12 s13 s23
    assert np.allclose(stress_action(swap) @ sigma, [1, 3, 2, 5, 4, 6])
    assert np.allclose(stress_action(np.diag([1.0, -1, 1])) @ sigma, [1, 2, 3, -4, 5, -6])


def test_a_symmetric_readout_is_equivariant_with_fewer_weights():
    """``symmetric``: fitted in every mirror frame, the weights of mirror-image shapes are mirror
    images, so the readout of a mirrored displacement is the mirrored stress, for any field, to
    round-off; it still recovers the (equivariant) stencil stress, from 864 independent weights
    instead of 2430 (one shape per orbit: a corner, an edge and an interior node of the square
    cross-section, at the two end faces and in between)."""
    ref, ei, idx = _grid()
    nt = torch.from_numpy((idx[:, 0] == 0).astype(np.int64))
    train = _snapshots(ref, idx, 60, seed=0)
    plain, _ = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1)
    readout, fit = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1, symmetric=True, node_type=nt)
    assert fit["symmetries"] == 8 and fit["weights"] == readout.fitted_weights() < plain.fitted_weights()
    # 1-hop stencil sizes of (corner, edge, interior) cross-section nodes: 5, 6, 7 inside, 4, 5, 6 at an end
    assert fit["classes"] == 27 and fit["weights"] == 3 * 6 * (5 + 6 + 7 + 2 * (4 + 5 + 6)) == 864
    assert plain.fitted_weights() == 3 * 6 * (4 * 5 + 4 * 6 + 7 + 2 * (4 * 4 + 4 * 5 + 6)) == 2430
    u = torch.randn(len(ref), 3, dtype=torch.float64) * 1e-3             # any field, smooth or not
    for R, p in mesh_symmetries(ref.numpy(), ei.numpy(), nt.numpy()):
        mirrored_u = torch.empty_like(u)
        mirrored_u[torch.from_numpy(p)] = u @ torch.from_numpy(R).T
        expected = torch.empty(len(ref), 6, dtype=torch.float64)
        expected[torch.from_numpy(p)] = readout(u) @ torch.from_numpy(stress_action(R)).T
        assert torch.allclose(readout(mirrored_u), expected, rtol=0, atol=1e-9 * expected.abs().max())
    for z in _snapshots(ref, idx, 3, seed=1):
        assert torch.allclose(readout(z[:, :3] - ref), z[:, 6:], rtol=0, atol=1e-6 * z[:, 6:].abs().max())
    spec = readout_spec(readout, 1)
    assert TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, stress_readout=spec).readout.fitted_weights() == fit["weights"]
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_symmetric needs the 6 stress components"):
        fit_stress_readout(ref, ei, [train[..., :9]], [6, 7, 8], hops=1, source="d.h5", symmetric=True)


def _modal_snapshots(ref, idx, count, seed, fields=4):
    """States z [count, N, 12] whose displacements are random combinations of ``fields`` fixed
    smooth fields, zero on the face x = 0 (their span: ``fields`` dimensions), and their stress."""
    rng = np.random.default_rng(123)
    X = ref.numpy()
    k = rng.normal(size=(fields, 3)) * 30
    base = [(X[:, :1] / X[:, 0].max()) * np.sin((X @ k[m])[:, None] + rng.normal(size=3)) * 1e-3
            for m in range(fields)]                                                  # [N, 3] each
    rng = np.random.default_rng(seed)
    z = np.zeros((count, len(X), 12))
    for s in range(count):
        u = sum(c * b for c, b in zip(rng.normal(size=fields), base))
        z[s, :, :3], z[s, :, 6:] = X + u, _linear_elastic_stress(u, idx)
    return torch.tensor(z)


def test_a_readout_on_displacement_modes_ignores_error_outside_the_training_span():
    """``modes`` (``model.stress_readout_modes``): u is projected onto the span of the training
    displacements' leading principal fields before the stencil reads it. Fields in that span read
    as without it; a perturbation orthogonal to it changes nothing (without it, the stencil
    amplifies it); mirror-symmetric, the span is closed under the mesh's frames, a degenerate pair
    is not split, and the basis counts r x the moving components per orbit; scripted it reads the
    same; a checkpoint's spec rebuilds it."""
    ref, ei, idx = _grid()
    train = _modal_snapshots(ref, idx, 30, seed=0)
    plain, _ = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1)
    readout, fit = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1, modes=4)
    basis = readout.modes.double()                                            # [3 N, 4]
    assert fit["modes"] == 4 and torch.allclose(basis.T @ basis, torch.eye(4, dtype=torch.float64), atol=1e-6)
    moving = 3 * int((idx[:, 0] > 0).sum())                                   # the face x = 0 never moves
    assert readout.mode_values == 4 * moving and fit["weights"] == plain.fitted_weights() + 4 * moving
    test = _modal_snapshots(ref, idx, 3, seed=1)
    noise = torch.randn(len(ref) * 3, dtype=torch.float64) * 1e-4
    noise = (noise - basis @ (basis.T @ noise)).reshape(-1, 3)                 # orthogonal to the span
    for z in test:
        u, sigma = z[:, :3] - ref, z[:, 6:]
        tol = 1e-5 * sigma.abs().max()
        assert torch.allclose(readout(u), sigma, rtol=0, atol=tol)
        assert torch.allclose(readout(u + noise), sigma, rtol=0, atol=tol)
        assert not torch.allclose(plain(u + noise), sigma, rtol=0, atol=100 * tol)
    scripted = torch.jit.script(readout)
    assert torch.allclose(scripted(test[0, :, :3] - ref), readout(test[0, :, :3] - ref), rtol=1e-12, atol=0)
    assert outside_modes(readout, test[:, :, :3] - ref) < 1e-6                  # test fields in the span
    assert outside_modes(readout, noise[None]) == pytest.approx(1.0, abs=1e-6)   # noise all outside it
    assert outside_modes(plain, test[:, :, :3] - ref) == 0.0                     # no modes
    model = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, stress_readout=readout_spec(readout, 1))
    model.readout.load_state_dict(readout.state_dict())
    assert model.readout.fitted_weights() == fit["weights"]
    nt = torch.from_numpy((idx[:, 0] == 0).astype(np.int64))
    tied, fit_t = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1, symmetric=True, node_type=nt, modes=5)
    r = fit_t["modes"]
    assert r >= 5
    B = tied.modes.double()
    for R, p in mesh_symmetries(ref.numpy(), ei.numpy(), nt.numpy()):          # the span is closed under the frames
        image = torch.empty_like(B.reshape(len(ref), 3, r))
        image[torch.from_numpy(p)] = torch.einsum("ab,nbr->nar", torch.from_numpy(R), B.reshape(len(ref), 3, r))
        image = image.reshape(-1, r)
        assert torch.allclose(B @ (B.T @ image), image, atol=1e-6)
    # a 4 x 4 cross-section: (48 components + 4 + 4 fixed by the two diagonal reflections) / 8 = 7 orbits a layer
    assert tied.mode_values == r * 7 * 6
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_modes = 5000, expected between 1 and"):
        fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1, source="d.h5", modes=5000)


def _side_loads(ref, idx, count, seed):
    """Point loads f [count, N, 3] (N) on a random half of the side faces' nodes (one boundary
    coordinate in y or z, x inside) and the traction stress they add there, sym(f n) / A [Pa]
    (n the outward normal, A = H^2): equivariant under the grid's reflections and swaps."""
    rng = np.random.default_rng(seed)
    hi = idx.max(0)
    on_y, on_z = (idx[:, 1] % hi[1] == 0), (idx[:, 2] % hi[2] == 0)
    side = np.flatnonzero((on_y ^ on_z) & (idx[:, 0] > 0) & (idx[:, 0] < hi[0]))
    normal = np.zeros((len(idx), 3))
    normal[on_y, 1] = np.where(idx[on_y, 1] == 0, -1.0, 1.0)
    normal[on_z, 2] = np.where(idx[on_z, 2] == 0, -1.0, 1.0)
    f, extra = np.zeros((count, len(idx), 3)), np.zeros((count, len(idx), 6))
    for s in range(count):
        loaded = rng.choice(side, len(side) // 2, replace=False)
        f[s, loaded] = rng.normal(size=(len(loaded), 3)) * 1e3
        t = 0.5 * (f[s][:, :, None] * normal[:, None, :] + normal[:, :, None] * f[s][:, None, :]) / H ** 2
        extra[s] = np.stack([t[:, a, b] for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))], 1)
    return torch.tensor(f), torch.tensor(extra)


def test_a_load_aware_readout_reads_a_surface_loads_traction():
    """``load_hops`` (``model.stress_readout_load``): the applied loads near each node enter the
    readout, σ = W u + V f. A stencil stress plus the traction of point loads on the side faces is
    recovered on unseen fields and loads, which the displacements alone cannot; mirror-symmetric,
    it is equivariant in u and f together, and it counts only load weights some snapshot loads; a load
    reach beyond the displacements' tells more shapes apart."""
    ref, ei, idx = _grid()
    nt = torch.from_numpy((idx[:, 0] == 0).astype(np.int64))
    z, (f, extra) = _snapshots(ref, idx, 80, seed=0), _side_loads(ref, idx, 80, seed=0)
    z[:, :, 6:] += extra
    blind, blind_fit = fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1)
    assert blind_fit["fit_error"] > 0.05                                       # the displacements cannot read a load
    readout, fit = fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1, forces=[f], load_hops=1)
    assert fit["load_hops"] == 1 and fit["fit_error"] < 1e-9 and readout.load_width == 7
    zt, (ft, extra_t) = _snapshots(ref, idx, 4, seed=1), _side_loads(ref, idx, 4, seed=1)
    zt[:, :, 6:] += extra_t
    for zs, fs in zip(zt, ft):
        assert torch.allclose(readout(zs[:, :3] - ref, fs), zs[:, 6:], rtol=0, atol=1e-6 * zs[:, 6:].abs().max())
    assert torch.equal(readout(torch.zeros_like(ref)), torch.zeros(len(ref), 6, dtype=torch.float64))
    # load weights: per class, the load columns some snapshot loads (side-face nodes and their neighbours)
    assert blind.fitted_weights() < fit["weights"] < blind.fitted_weights() + 6 * 3 * 7 * fit["classes"]
    tied, fit_t = fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1, symmetric=True, node_type=nt,
                                     forces=[f], load_hops=1)
    assert fit_t["weights"] < fit["weights"]
    u, load = torch.randn(len(ref), 3, dtype=torch.float64) * 1e-3, ft[0]
    for R, p in mesh_symmetries(ref.numpy(), ei.numpy(), nt.numpy()):
        Rt, pt = torch.from_numpy(R), torch.from_numpy(p)
        mu, mf, expected = torch.empty_like(u), torch.empty_like(load), torch.empty(len(ref), 6, dtype=torch.float64)
        mu[pt], mf[pt] = u @ Rt.T, load @ Rt.T
        expected[pt] = tied(u, load) @ torch.from_numpy(stress_action(R)).T
        assert torch.allclose(tied(mu, mf), expected, rtol=0, atol=1e-9 * expected.abs().max())
    model = TIGNN(12, [3, 4, 5], hidden=8, message_passing=1, stress_readout=readout_spec(readout, 1, 1))
    model.readout.load_state_dict(readout.state_dict())
    state = zt[0].clone()
    assert torch.allclose(model.read_stress(state, ref, ft[0])[:, 6:], zt[0, :, 6:], atol=1e-6 * zt[0, :, 6:].abs().max())
    wide, fit_w = fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1, forces=[f], load_hops=2)
    assert fit_w["classes"] > fit["classes"] and fit_w["fit_error"] < 1e-9     # beyond hops: more shapes
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_load = -1, expected the loads' reach"):
        fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1, source="d.h5", forces=[f], load_hops=-1)


def test_a_readout_reads_a_batch_of_fields_as_each_alone():
    """Leading dimensions of u and f are a batch of fields (a training window's B states, a
    rollout's snapshots): each reads as it does alone, with loads and modes, eager and scripted."""
    ref, ei, idx = _grid()
    z, (f, extra) = _modal_snapshots(ref, idx, 40, seed=0), _side_loads(ref, idx, 40, seed=0)
    z[:, :, 6:] += extra
    readout, _ = fit_stress_readout(ref, ei, [z], list(range(6, 12)), hops=1, forces=[f], load_hops=1, modes=4)
    u = z[:6, :, :3] - ref                                                    # [6, N, 3]
    alone = torch.stack([readout(u[s], f[s]) for s in range(6)])              # [6, N, 6]
    assert torch.allclose(readout(u, f[:6]), alone, rtol=0, atol=1e-12 * alone.abs().max())
    paired = readout(u.reshape(2, 3, -1, 3), f[:6].reshape(2, 3, -1, 3))       # [2, 3, N, 6]
    assert paired.shape == (2, 3, len(ref), 6) and torch.allclose(paired.reshape(6, -1, 6), alone, rtol=0,
                                                                   atol=1e-12 * alone.abs().max())
    unloaded = torch.stack([readout(u[s]) for s in range(6)])
    assert torch.allclose(readout(u), unloaded, rtol=0, atol=1e-12 * unloaded.abs().max())
    scripted = torch.jit.script(readout)
    assert torch.allclose(scripted(u, f[:6]), alone, rtol=0, atol=1e-12 * alone.abs().max())


def test_the_readout_check_holds_load_groups_out_with_their_mirror_images():
    """``held_out_loads_check`` (``train.readout_folds``): trajectories are grouped by their loaded
    nodes up to the mesh's mirrors (a load and its mirror image in one group, so a symmetric fit never
    sees the held-out load's image); each fold is read by a readout fitted to the others. A stencil
    law is read on held-out loads as on the fitted ones; one load group cannot be checked."""
    from thermognn.train.stress_readout import held_out_loads_check, load_folds, load_groups

    ref, ei, idx = _grid()
    nt = torch.from_numpy((idx[:, 0] == 0).astype(np.int64))
    graph = SimpleNamespace(ref_pos=ref, edge_index=ei, node_type=nt)
    symmetries = mesh_symmetries(ref.numpy(), ei.numpy(), nt.numpy())
    R, p = symmetries[1]
    top = [int(n) for n in np.flatnonzero((idx[:, 1] == 3) & (idx[:, 2] == 1) & (idx[:, 0] > 0))]   # 6 nodes
    trajs = [_snapshots(ref, idx, 8, seed=k) for k in range(len(top) + 1)]

    def point_load(node):
        f = torch.zeros(8, len(ref), 3, dtype=torch.float64)
        f[1:, node, 1] = -1.0
        return f

    forces = [point_load(n) for n in top] + [point_load(int(p[top[0]]))]       # the last: the first's image
    groups = load_groups(forces, symmetries)
    assert groups[-1] == groups[0] and len(set(groups[:-1].tolist())) == len(top)
    alone = load_groups(forces, symmetries[:1])                                 # the identity only: its own
    assert len(set(alone.tolist())) == len(top) + 1
    check = held_out_loads_check(graph, trajs, trajs, forces, list(range(6, 12)), hops=1, folds=3,
                                 symmetric=True, load_hops=1)
    assert check["folds"] == 3 and check["groups"] == len(top)
    assert check["per_snapshot"] < 1e-5 and check["whole"] < 1e-5 and check["in_sample_per_snapshot"] < 1e-5
    assert check["worst_group_per_snapshot"] >= check["per_snapshot"]
    assert any(np.allclose(check["worst_group_load_point"], ref[n].numpy()) for n in top)    # a loaded node
    from thermognn.train.loop import held_out_sentence
    assert "worst held out: the group loaded at (" in held_out_sentence(check)
    one = held_out_loads_check(graph, trajs[:2], trajs[:2], forces[:1] * 2, list(range(6, 12)), hops=1,
                               folds=3, symmetric=True)
    assert one["folds"] == 0 and "1 load group(s)" in one["reason"]
    # the fold readouts of one pass (each fold's normal equations taken out of the whole's) are the
    # readouts fitted without the fold; here the stress also carries the loads' traction
    loaded = [z.clone() for z in trajs]
    for z, f in zip(loaded, forces):
        z[:, :, 7] += f[:, :, 1] / H ** 2
    fold_of, group_of = load_folds(graph, forces, 3, symmetric=True)
    assert list(group_of) == list(groups) and sorted(set(fold_of.tolist())) == [0, 1, 2]
    whole, report = fit_stress_readout(ref, ei, loaded, list(range(6, 12)), hops=1, symmetric=True, node_type=nt,
                                       forces=forces, load_hops=1, held_out=fold_of)
    for j, fold_readout in enumerate(report["held_out_readouts"]):
        kept = [i for i in range(len(loaded)) if fold_of[i] != j]
        alone, _ = fit_stress_readout(ref, ei, [loaded[i] for i in kept], list(range(6, 12)), hops=1, symmetric=True,
                                      node_type=nt, forces=[forces[i] for i in kept], load_hops=1)
        for i in range(len(loaded)):
            u, f = loaded[i][:, :, :3] - ref, forces[i]
            expected = alone(u, f)
            assert torch.allclose(fold_readout(u, f), expected, rtol=0, atol=1e-8 * expected.abs().max())
    assert not torch.allclose(report["held_out_readouts"][0].weight, whole.weight)


def test_each_shape_chooses_the_ridge_that_reads_held_out_load_groups_best():
    """``ridge`` (``model.stress_readout_ridge``) as a list: each neighbourhood shape takes the ridge
    whose weights, fitted without a fold of load groups, read that fold's rows with the least squared
    error summed over the folds; fold k's readout takes the one the other folds chose; the whole
    readout is the single-ridge fit with each shape's choice. Checked against fits with one ridge
    each, on a stress no stencil reads exactly (so the choice varies)."""
    from thermognn.train.stress_readout import load_folds

    ref, ei, idx = _grid()
    graph = SimpleNamespace(ref_pos=ref, edge_index=ei, node_type=torch.zeros(len(ref), dtype=torch.long))
    top = [int(n) for n in np.flatnonzero((idx[:, 1] == 3) & (idx[:, 2] == 1))]          # 7 load points
    trajs, forces = [], []
    for k, node in enumerate(top):
        z = _snapshots(ref, idx, 14, seed=k)
        z[:, :, 6:] += 4e8 * (z[:, :, :3] - ref).pow(2).repeat(1, 1, 2)                # not a stencil's
        f = torch.zeros(14, len(ref), 3, dtype=torch.float64)
        f[1:, node, 1] = -1.0
        trajs.append(z)
        forces.append(f)
    fold_of, _ = load_folds(graph, forces, 3)
    ridges = [0.0, 1e-6, 1e-3]
    cols = list(range(6, 12))
    readout, report = fit_stress_readout(ref, ei, trajs, cols, hops=2, held_out=fold_of, ridge=ridges)
    single = [fit_stress_readout(ref, ei, trajs, cols, hops=2, held_out=fold_of, ridge=r) for r in ridges]
    classes = readout.node_class.numpy()
    sse = np.zeros((len(ridges), 3, int(classes.max()) + 1))     # [ridge, fold, shape]
    for r, (_, rep) in enumerate(single):
        for i, z in enumerate(trajs):
            j = int(fold_of[i])
            with torch.no_grad():
                err = ((rep["held_out_readouts"][j](z[:, :, :3] - ref) - z[:, :, 6:]) ** 2).sum((0, 2)).numpy()
            np.add.at(sse[r, j], classes, err)
    best = sse.sum(1).argmin(0)                                                           # [shape]
    assert np.array_equal(report["ridge"], np.array(ridges)[best]) and len(set(best.tolist())) > 1
    from thermognn.train.loop import held_out_sentence
    from thermognn.train.stress_readout import ridge_counts
    counts = ridge_counts(report["ridge"])
    assert sum(c for _, c in counts) == len(best) and [v for v, _ in counts] == sorted({ridges[b] for b in best})
    check = {"folds": 3, "groups": 7, "per_snapshot": 0.1, "whole": 0.1, "in_sample_per_snapshot": 0.1,
             "in_sample_whole": 0.1, "worst_group_per_snapshot": 0.2, "worst_group_load_point": [0, 0, 0],
             "ridge": counts}
    assert f"0.001 for {counts[-1][1]} shape" in held_out_sentence(check)
    # the check also reads every shape at the first ridge alone: the single-ridge check's figures
    from thermognn.train.stress_readout import held_out_loads_check
    chose = held_out_loads_check(graph, trajs, trajs, forces, cols, hops=2, folds=3, ridge=ridges)
    alone = held_out_loads_check(graph, trajs, trajs, forces, cols, hops=2, folds=3, ridge=ridges[0])
    assert "first_ridge" not in alone and chose["first_ridge"]["ridge"] == ridges[0]
    assert math.isclose(chose["first_ridge"]["per_snapshot"], alone["per_snapshot"], rel_tol=1e-9)
    assert math.isclose(chose["first_ridge"]["in_sample_per_snapshot"], alone["in_sample_per_snapshot"], rel_tol=1e-9)
    assert chose["per_snapshot"] != alone["per_snapshot"]
    assert "; every shape at ridge 0 instead: held out " in held_out_sentence(chose)
    # train's path: the readout fitted to rollouts (here the true states) keeps both in its check
    from thermognn.core.state import StateLayout
    from thermognn.train.stress_readout import fit_readout_to_rollouts
    data = SimpleNamespace(graph=graph, layout=StateLayout((("q", 3), ("v", 3), ("sigma", 6))), path="d.h5", dt=0.1)
    _, fit = fit_readout_to_rollouts(torch.nn.Module(), data, [SimpleNamespace(z=z, force=f) for z, f in zip(trajs, forces)],
                                     2, roll=lambda m, t: t.z, folds=3, ridge=ridges)
    assert fit["held_out_loads"]["first_ridge"] == chose["first_ridge"]
    assert fit["held_out_loads"]["per_snapshot"] == chose["per_snapshot"]
    for c in range(len(best)):
        w = single[best[c]][0].weight[c]
        assert torch.allclose(readout.weight[c], w, rtol=0, atol=1e-9 * w.abs().max())
        for j in range(3):
            other = (sse.sum(1) - sse[:, j])[:, c].argmin()                                 # the other folds' choice
            w = single[other][1]["held_out_readouts"][j].weight[c]
            assert torch.allclose(report["held_out_readouts"][j].weight[c], w, rtol=0, atol=1e-9 * w.abs().max())
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_ridge = \[0\.0, 0\.001\]: choosing among"):
        fit_stress_readout(ref, ei, trajs, cols, hops=2, source="d.h5", ridge=[0.0, 1e-3])
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout_ridge = \[-1\.0\], expected one ridge >= 0"):
        fit_stress_readout(ref, ei, trajs, cols, hops=2, source="d.h5", ridge=-1.0)


def test_a_model_with_a_readout_reports_the_stress_off_its_positions_and_scripts():
    """TIGNN with ``stress_readout``: its steps are the network's (the state keeps its own σ), a
    rollout reports σ = readout(q - X) at every snapshot; the scripted model reads the same; a
    checkpoint's weights round-trip, and a model without a readout keeps none in its weights."""
    from types import SimpleNamespace

    from thermognn.train.rollout import rollout

    ref, ei, idx = _grid(5, 3, 3)
    train = _snapshots(ref, idx, 40, seed=2)
    readout, _ = fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=1)
    torch.manual_seed(0)
    plain = TIGNN(12, [3, 4, 5], hidden=16, message_passing=2, exact_kinematics=True).double()
    ckpt = {"hparams": {"dim": 12, "velocity_columns": [3, 4, 5], "hidden": 16, "message_passing": 2,
                        "exact_kinematics": True}, "state_dict": plain.state_dict()}
    ckpt = with_stress_readout(ckpt, readout, 1)
    assert ckpt["hparams"]["stress_readout"] == readout_spec(readout, 1)
    model = TIGNN(**ckpt["hparams"]).double()
    model.load_state_dict(ckpt["state_dict"])
    nt = torch.zeros(len(ref), dtype=torch.long)
    nt[idx[:, 0] == 0] = 1                                              # clamped face
    f = torch.zeros(3, len(ref), 3, dtype=torch.float64)
    f[1:, :, 2] = 1.0
    graph = SimpleNamespace(edge_index=ei, node_type=nt, ref_pos=ref)
    z0, dt = train[7].clone(), torch.tensor(1e-3, dtype=torch.float64)
    assert torch.equal(model.step(z0, f[1], ei, nt, ref, dt), plain.step(z0, f[1], ei, nt, ref, dt))
    reported, own = rollout(model, graph, z0, f, 1e-3), rollout(plain, graph, z0, f, 1e-3)
    assert torch.equal(reported[:, :, :6], own[:, :, :6])                 # q, v: the network's
    for z in reported:
        assert torch.allclose(z[:, 6:], model.readout(z[:, :3] - ref), rtol=1e-12, atol=0)
    assert not torch.allclose(reported[1:, :, 6:], own[1:, :, 6:])
    # the step the benchmarks time is the rollout's first step as reported (from the imposed start): σ read
    # off with a readout, the network's without
    start = model.impose(z0, nt, ref)
    assert torch.allclose(model.reported_step(start, f[1], ei, nt, ref, dt), reported[1], rtol=1e-12, atol=1e-9)
    assert torch.allclose(plain.reported_step(start, f[1], ei, nt, ref, dt), own[1], rtol=1e-12, atol=1e-9)
    scripted = torch.jit.script(model)
    assert torch.allclose(scripted.read_stress(reported[2], ref), reported[2], rtol=1e-12, atol=1e-12)
    assert set(plain.state_dict()) == {k for k in ckpt["state_dict"] if not k.startswith("readout.")}


def test_readout_errors_name_the_problem():
    ref, ei, idx = _grid()
    train = _snapshots(ref, idx, 60, seed=0)
    with pytest.raises(DataError, match="stress_readout = 0"):
        fit_stress_readout(ref, ei, [train], list(range(6, 12)), hops=0, source="d.h5")
    with pytest.raises(DataError, match=r"d\.h5: model\.stress_readout = 3: .* equations for .* weights"):
        fit_stress_readout(ref, ei, [train[:2]], list(range(6, 12)), hops=3, source="d.h5")
    stressed = train.clone()
    stressed[0, :, :3] = ref
    stressed[0, :, 6:] = 1.0                                             # stress at u = 0
    with pytest.raises(DataError, match="not zero where the displacement is"):
        fit_stress_readout(ref, ei, [stressed], list(range(6, 12)), hops=1, source="d.h5")


def test_train_fits_the_readout_to_its_rollouts_and_export_keeps_it(tmp_path):
    """``model.stress_readout``: after training, the readout is fitted to the best model's training
    rollouts and saved with it; evaluate-style rollouts report its stress; export scripts it; a
    fine-tune from that checkpoint starts (the readout is refitted); bad uses are refused."""
    from thermognn.core.config import load_config
    from thermognn.core.errors import ConfigError
    from thermognn.export import export
    from thermognn.train import evaluate, train
    from thermognn.train.checkpoint import load_checkpoint, model_from_checkpoint
    from thermognn.train.synthetic import write_oscillator_dataset

    write_oscillator_dataset(tmp_path / "few.h5", n_trajectories=6, steps=8)
    with pytest.raises(DataError, match=r"few\.h5: model\.stress_readout = 1: 1 node\(s\) .* 36 equations for 45"):
        train(load_config([f"out={tmp_path / 'few'}", "model.stress_readout=1", f"paths.dataset={tmp_path / 'few.h5'}"]))
    assert not (tmp_path / "few" / "model.ckpt").exists()              # refused before training
    write_oscillator_dataset(tmp_path / "dataset.h5", n_trajectories=12, steps=8)
    small = ["train.threads=1", "model.hidden=16", "model.message_passing=2", "train.batch_size=4",
             "train.val_every=1", "train.tensorboard=false", "model.kinematics=exact"]
    cfg = load_config([f"out={tmp_path}", *small, "train.epochs=2", "model.stress_readout=1"])
    ckpt = load_checkpoint(train(cfg))
    spec = ckpt["hparams"]["stress_readout"]
    assert spec["hops"] == 1 and spec["columns"] == [6, 7, 8, 9, 10, 11]
    # every trajectory of this dataset loads the same nodes: no load group to hold out (train.readout_folds)
    assert ckpt["stress_readout_check"]["folds"] == 0 and "1 load group(s)" in ckpt["stress_readout_check"]["reason"]
    model = model_from_checkpoint(ckpt)
    assert model.use_readout and model.readout.fitted_weights() > 0
    scripted = torch.jit.load(str(export(cfg)))
    z = ckpt["state_dict"]["z_mean"] + torch.randn(model.readout.nodes, 12) * 1e-3
    assert torch.allclose(scripted.report(z), model.read_stress(z, scripted.reference_positions))
    assert not torch.allclose(scripted.report(z)[:, 6:], z[:, 6:])
    again = load_config([f"out={tmp_path / 'ft'}", *small, "train.epochs=1", "model.stress_readout=1",
                         f"train.init={tmp_path / 'model.ckpt'}", f"paths.dataset={tmp_path / 'dataset.h5'}"])
    assert load_checkpoint(train(again))["hparams"]["stress_readout"]["hops"] == 1
    mirrored = load_config([f"out={tmp_path / 'sym'}", *small, "train.epochs=1", "model.stress_readout=1",
                            "model.stress_readout_symmetric=true", "model.stress_readout_load=1",
                            "model.stress_readout_modes=3",
                            f"train.init={tmp_path / 'model.ckpt'}", f"paths.dataset={tmp_path / 'dataset.h5'}"])
    ckpt = load_checkpoint(train(mirrored))
    spec = ckpt["hparams"]["stress_readout"]
    assert 0 < spec["independent"] and spec["load_hops"] == 1 and spec["load_width"] > 0
    assert spec["modes"] >= 3 and spec["mode_values"] > 0 and ckpt["state_dict"]["readout.modes"].shape[1] == spec["modes"]
    loaded = model_from_checkpoint(ckpt)
    scripted = torch.jit.load(str(export(mirrored)))
    f = torch.randn(loaded.readout.nodes, 3, dtype=z.dtype)
    assert torch.allclose(scripted.report(z, f), loaded.read_stress(z, scripted.reference_positions, f))
    res = evaluate(mirrored)                       # says how far the test displacements lie outside the modes
    assert 0.0 <= res["readout_modes_miss"] < 1.0 and "readout_modes_miss_train" in res
    summary = (tmp_path / "sym" / "eval" / "summary.md").read_text()
    assert "displacement modes" in summary and f"+ {loaded.readout.fitted_weights()} of the stress readout = " in summary
    refit = load_config([f"out={tmp_path / 'refit'}", *small, "train.epochs=0", "model.stress_readout=2",
                         "model.stress_readout_symmetric=true", "model.stress_readout_relative=true",
                         f"train.init={tmp_path / 'model.ckpt'}",
                         f"paths.dataset={tmp_path / 'dataset.h5'}"])
    refitted = load_checkpoint(train(refit))                       # no training: the readout alone, anew
    init = load_checkpoint(tmp_path / "model.ckpt")
    assert refitted["epoch"] == 0 and refitted["hparams"]["stress_readout"]["hops"] == 2
    assert all(torch.equal(v, init["state_dict"][k]) for k, v in refitted["state_dict"].items() if not k.startswith("readout."))
    assert not (tmp_path / "refit" / "metrics.csv").exists()
    from thermognn.train.data import load_data                      # its validation error: the read-off stress's
    from thermognn.train.rollout import validation_error
    data = load_data(tmp_path / "dataset.h5", [0.7, 0.15, 0.15], 0, torch.float32, keep_split=refitted["split"])
    read = model_from_checkpoint(refitted)
    val = validation_error(read, data.graph, data.of("val"), data.layout, data.dt)
    assert math.isclose(refitted["val_error"], val, rel_tol=1e-6)
    assert read.use_readout and not math.isclose(val, validation_error(model_from_checkpoint(init), data.graph,
                                                                      data.of("val"), data.layout, data.dt), rel_tol=1e-3)
    with pytest.raises(ConfigError, match=r"train.readout_folds = 1, expected 0 \(off\) or the number of folds"):
        train(load_config([f"out={tmp_path / 'f1'}", "model.stress_readout=1", "train.readout_folds=1",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(DataError, match=r"dataset\.h5: model\.stress_readout_ridge = \[0\.0, 1e-06\]: .* load 1 group"):
        train(load_config([f"out={tmp_path / 'r1'}", "model.stress_readout=1", "model.stress_readout_ridge=[0,1e-6]",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match=r"stress_readout_ridge = \[0, 1e-06\]: .* train.readout_folds >= 2 \(it is 0\)"):
        train(load_config([f"out={tmp_path / 'r2'}", "model.stress_readout=1", "model.stress_readout_ridge=[0,1e-6]",
                           "train.readout_folds=0", f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    for bad in ("-1", "[]", "abc"):
        with pytest.raises(ConfigError, match=r"model.stress_readout_ridge = .*, expected a ridge >= 0"):
            train(load_config([f"out={tmp_path / 'r3'}", "model.stress_readout=1", f"model.stress_readout_ridge={bad}",
                               f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    for given in ("1e-06", "auto"):
        with pytest.raises(ConfigError, match=rf"model.stress_readout_ridge = '?{given}'?: .* set model.stress_readout"):
            train(load_config([f"out={tmp_path / 'r4'}", f"model.stress_readout_ridge={given}",
                               f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match=r"train.epochs = 0, expected >= 1 \(or 0 with train.init and model.stress_readout"):
        train(load_config([f"out={tmp_path / 'e0'}", "train.epochs=0", "model.stress_readout=1",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match=r"model.stress_readout_load = 2: .* expected 0 \(off\) or hops >= 1 with model.stress_readout set"):
        train(load_config([f"out={tmp_path / 'nl'}", "model.stress_readout_load=2",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match=r"model.stress_readout_modes = 4: .* expected 0 \(off\) or >= 1 with model.stress_readout set"):
        train(load_config([f"out={tmp_path / 'nm'}", "model.stress_readout_modes=4",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    for given, shown in (("true", "True"), ("1.5", "1.5"), ("abc", "'abc'")):
        with pytest.raises(ConfigError, match=rf"model.stress_readout_relative = {shown}: .* expected true \(p = 1\), "
                                              r"false or p in \[0, 1\] \(other than 0 only with model.stress_readout set\)"):
            train(load_config([f"out={tmp_path / 'nr'}", f"model.stress_readout_relative={given}",
                               f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match="model.stress_readout_symmetric = true: .* set model.stress_readout"):
        train(load_config([f"out={tmp_path / 'ns'}", "model.stress_readout_symmetric=true",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))
    with pytest.raises(ConfigError, match="model.stress_readout: .* model.prior=linear"):
        train(load_config([f"out={tmp_path / 'lp'}", "model=linear_prior", "model.stress_readout=1",
                           f"paths.dataset={tmp_path / 'dataset.h5'}"]))


def test_evaluate_finds_test_cases_that_mirror_training_ones():
    """``repeated_cases``: a test trajectory that is a training one seen in a mirror of the mesh (the
    TIGNN beam's reference split: all 6) is named with its twin; a new load case is not."""
    from thermognn.train.evaluation import repeated_cases, repeated_sentence

    ref, ei, idx = _grid()
    X, clamped = ref.numpy(), (idx[:, 0] == 0).astype(np.int64)
    R, perm = mesh_symmetries(X, ei.numpy(), clamped)[3]                 # a reflection or swap, not the identity
    train = [SimpleNamespace(name=f"case_{k}", z=_snapshots(ref, idx, 5, seed=k)) for k in range(3)]
    twin = train[1].z.clone()
    twin[:, perm, :3] = ref[perm] + (train[1].z[:, :, :3] - ref) @ torch.from_numpy(R).T
    test = [SimpleNamespace(name="mirrored", z=twin), SimpleNamespace(name="new", z=_snapshots(ref, idx, 5, seed=9))]
    found = repeated_cases(X, ei.numpy(), clamped, slice(0, 3), test, train)
    assert [(a, b) for a, b, _ in found] == [("mirrored", "case_1")] and found[0][2] < 1e-12
    assert repeated_sentence(found, 2).startswith("1 of 2 test trajectories repeat a training one")
    assert repeated_cases(X, ei.numpy(), clamped, slice(0, 3), test[1:], train) == []
