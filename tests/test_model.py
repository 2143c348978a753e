"""TIGNN structure: skew L, PSD M, degeneracy, energy conservation, TorchScript."""

import pytest
import torch

from thermognn.train.model import (TIGNN, degeneracy_loss, edge_feature_count, poisson_apply, psd,
                                   raw_edge_features, skew)


def _graph(n=20, n_edges=80, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    src = torch.randint(0, n, (n_edges,), generator=g)
    dst = (src + 1 + torch.randint(0, n - 1, (n_edges,), generator=g)) % n  # no self loops
    edge_index = torch.cat([torch.stack([src, dst]), torch.stack([dst, src])], 1)
    ref = torch.rand(n, 3, generator=g, dtype=dtype) * 0.04
    z = torch.randn(n, 12, generator=g, dtype=dtype)
    z[:, :3] = ref + 1e-3 * z[:, :3]
    f = torch.randn(n, 3, generator=g, dtype=dtype)
    node_type = torch.randint(0, 3, (n,), generator=g)
    return z, f, edge_index, node_type, ref


def _model(hamiltonian=False, port=False, **kw):
    torch.manual_seed(0)
    return TIGNN(12, [3, 4, 5], hidden=16, mlp_layers=2, message_passing=2, hamiltonian=hamiltonian,
                 port=port, **kw).double()


def test_L_skew_and_M_symmetric_psd():
    z, f, ei, nt, ref = _graph()
    _, L, M, _, _, _ = _model().rates(z, f, ei, nt, ref, False)
    assert L.shape == (20, 12, 12) and M.shape == (20, 12, 12)
    assert torch.allclose(L, -L.transpose(1, 2), atol=1e-14)
    assert torch.allclose(M, M.transpose(1, 2), atol=1e-12)
    eig = torch.linalg.eigvalsh(M)
    assert eig.min() >= -1e-10 * eig.abs().max()


def test_degeneracy_zero_for_constructed_case():
    # L = [a]_x (cross product with a) annihilates dS/dz = a; M = m m^T with m's columns orthogonal to dE/dz
    a = torch.tensor([[0.3, -1.2, 0.7]], dtype=torch.float64)
    ax = torch.tensor([[[0.0, -0.7, -1.2], [0.7, 0.0, -0.3], [1.2, 0.3, 0.0]]], dtype=torch.float64)
    L = skew(0.5 * ax)  # = ax, already skew
    grad_e = torch.tensor([[1.0, 2.0, -1.0]], dtype=torch.float64)
    u = torch.tensor([[2.0, -1.0, 0.0]], dtype=torch.float64)   # u . grad_e = 0
    w = torch.linalg.cross(u, grad_e)                              # w . grad_e = 0
    m = torch.stack([u[0], w[0], torch.zeros(3, dtype=torch.float64)], 1).unsqueeze(0)
    M = psd(m)
    no_edges = (L[:0], torch.zeros(2, 0, dtype=torch.long))                  # node blocks only
    assert float(degeneracy_loss(L, M, grad_e, a, *no_edges)) < 1e-24
    assert float(degeneracy_loss(L, M, a, grad_e, *no_edges)) > 1e-3  # swapped: not degenerate


def test_graph_coupled_poisson_operator_is_skew():
    """poisson_apply with edge blocks: <a, L b> = -<b, L a> for any a, b, so g . L g = 0."""
    z, f, ei, nt, ref = _graph(seed=8)
    g = torch.Generator().manual_seed(8)
    n, d = z.shape
    L = skew(torch.randn(n, d, d, generator=g, dtype=torch.float64))
    A = torch.randn(ei.shape[1], d, d, generator=g, dtype=torch.float64)
    a, b = torch.randn(n, d, generator=g, dtype=torch.float64), torch.randn(n, d, generator=g, dtype=torch.float64)
    ab, ba = (a * poisson_apply(L, A, ei, b)).sum(), (b * poisson_apply(L, A, ei, a)).sum()
    assert abs(float(ab + ba)) < 1e-12 * float(ab.abs())
    # the coupling acts across edges: node i's rate depends on a neighbour's gradient
    e0 = poisson_apply(L, A, ei, a)
    a2 = a.clone()
    a2[int(ei[0, 0])] += 1.0
    assert not torch.allclose(poisson_apply(L, A, ei, a2)[int(ei[1, 0])], e0[int(ei[1, 0])])
    assert torch.equal(poisson_apply(L, A[:0], ei, a), torch.bmm(L, a.unsqueeze(-1)).squeeze(-1))


def _with_stats(model, seed=1):
    """Non-uniform normalisation statistics (as after training): the columns' state and rate
    scales differ, which is where a GENERIC structure applied in the wrong coordinates breaks."""
    g = torch.Generator().manual_seed(seed)
    d = model.dim
    model.set_stats({"z_mean": 0.1 * torch.randn(d, generator=g, dtype=torch.float64),
                     "z_std": torch.logspace(-3, 1, d, dtype=torch.float64),
                     "dzdt_std": torch.logspace(0, -2, d, dtype=torch.float64)})
    return model


def _physical_rates(model, z, f, ei, nt, ref):
    """dz/dt [N, D] in SI units, dE/dz and dS/dz [N, D] by autograd through the normalisation."""
    r = model.rates(z, f, ei, nt, ref, False)[0].detach()
    zz = z.clone().requires_grad_(True)
    e, s_ = model.energy_entropy(zz, ei, nt, ref, f)
    g_e = torch.autograd.grad(e, zz, retain_graph=True)[0]
    g_s = torch.autograd.grad(s_, zz)[0] if s_.requires_grad else torch.zeros_like(g_e)
    return r * model.dzdt_std, g_e, g_s


@pytest.mark.parametrize("edge_operators", [False, True])
def test_hamiltonian_conserves_energy_in_physical_units(edge_operators):
    # dE/dt = dE/dz . dz/dt = 0 to round-off (no port term), with non-uniform statistics
    z, f, ei, nt, ref = _graph()
    model = _with_stats(_model(hamiltonian=True, balanced=True, edge_operators=edge_operators,
                               velocity_edges=edge_operators))
    dzdt, g_e, _ = _physical_rates(model, z, f, ei, nt, ref)
    terms = g_e * dzdt
    assert abs(float(terms.sum())) < 1e-12 * float(terms.abs().sum())
    energy, de_dt, power = model.energy_power(z, f, ei, nt, ref)
    assert abs(float(de_dt)) < 1e-12 * float(terms.abs().sum()) and float(power) == 0.0
    _, L, M, _, _, deg = model.rates(z, f, ei, nt, ref, False)
    assert float(M.abs().max()) == 0.0 and float(deg) == 0.0
    # the same operator applied to dE/dzn and rescaled per column (balanced=False) is not conservative
    legacy = _with_stats(_model(hamiltonian=True, balanced=False))
    dzdt, g_e, _ = _physical_rates(legacy, z, f, ei, nt, ref)
    assert abs(float((g_e * dzdt).sum())) > 1e-3 * float((g_e * dzdt).abs().sum())


def test_port_power_is_the_only_energy_input():
    z, f, ei, nt, ref = _graph(seed=4)
    model = _with_stats(_model(hamiltonian=True, port=True, balanced=True))
    _, de_dt, power = model.energy_power(z, f, ei, nt, ref)
    assert abs(float(power)) > 0.0
    assert abs(float(de_dt - power)) < 1e-10 * abs(float(power))


@pytest.mark.parametrize("edge_operators", [False, True])
def test_generic_entropy_production_non_negative(edge_operators):
    z, f, ei, nt, ref = _graph(seed=3)
    model = _with_stats(_model(balanced=True, edge_operators=edge_operators))
    _, _, M, _, g_s, deg = model.rates(z, f, ei, nt, ref, False)
    production = torch.einsum("ni,nij,nj->n", g_s, M, g_s)
    assert float(production.min()) >= -1e-12 * float(production.abs().max())
    assert float(deg) > 0.0  # an untrained model is not degenerate: the loss has something to do
    # in physical units: the M part of dz/dt produces dS/dt = sum_i g_s . M g_s >= 0
    _, _, dS_dz = _physical_rates(model, z, f, ei, nt, ref)
    m_part = torch.bmm(M, g_s.unsqueeze(-1)).squeeze(-1) * model.free_entries(nt, z) / model.balance() * model.dzdt_std
    assert torch.allclose((dS_dz * m_part).sum(), production.sum(), rtol=1e-9)


def _energy_error(model, z, f, ei, nt, ref, steps=20, dt=0.02):
    """Sum over a rollout (load held) of |E_{n+1} - E_n - dt P((z_n + z_{n+1}) / 2)|: the energy
    change the port's power P does not account for."""
    dt_t = torch.tensor(dt, dtype=z.dtype)
    err = 0.0
    for _ in range(steps):
        z1 = model.step(z, f, ei, nt, ref, dt_t).detach()
        e0, e1 = model.energy_power(z, f, ei, nt, ref)[0], model.energy_power(z1, f, ei, nt, ref)[0]
        power = model.energy_power(0.5 * (z + z1), f, ei, nt, ref)[2]
        err += abs(float(e1 - e0 - dt * power))
        z = z1
    return err


def test_midpoint_integrator_conserves_energy_far_better_than_euler():
    z, f, ei, _, ref = _graph(seed=5)
    nt = torch.zeros(z.shape[0], dtype=torch.int64)          # no clamped nodes: no imposed jumps
    errors = {}
    for integrator in ("euler", "midpoint"):
        # free motion (no port): the continuous dynamics conserve E exactly, the integrators do not
        model = _with_stats(_model(hamiltonian=True, port=False, balanced=True, integrator=integrator,
                                   implicit_iterations=8))
        errors[integrator] = _energy_error(model, z, f, ei, nt, ref)
    assert errors["midpoint"] < 1e-3 * errors["euler"], errors


def test_midpoint_training_evaluates_the_rate_between_snapshots():
    model = _model(integrator="midpoint")
    z, z_next = torch.zeros(3, 12, dtype=torch.float64), torch.ones(3, 12, dtype=torch.float64)
    assert torch.equal(model.rate_state(z, z_next), 0.5 * z_next)
    assert torch.equal(_model().rate_state(z, z_next), z)
    with pytest.raises(ValueError, match="integrator 'rk4'"):
        _model(integrator="rk4")


@pytest.mark.parametrize("hamiltonian", [False, True])
@pytest.mark.parametrize("shared,aggregation", [(False, "sum"), (True, "mean")])
def test_scripted_matches_eager(hamiltonian, shared, aggregation):
    z, f, ei, nt, ref = _graph(seed=1)
    model = _with_stats(_model(hamiltonian=hamiltonian, port=True, shared_weights=shared, aggregation=aggregation,
                               balanced=True, integrator="midpoint" if shared else "euler", velocity_edges=shared,
                               edge_operators=shared, exact_kinematics=shared and not hamiltonian))
    scripted = torch.jit.script(model)
    dt = torch.tensor(0.01, dtype=torch.float64)
    a = model.step(z, f, ei, nt, ref, dt)
    b = scripted.step(z, f, ei, nt, ref, dt)
    assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    ea, sa = model.energy_entropy(z, ei, nt, ref, f)
    eb, sb = scripted.energy_entropy(z, ei, nt, ref, f)
    assert torch.allclose(ea, eb) and torch.allclose(sa, sb)


@pytest.mark.parametrize("integrator", ["euler", "midpoint"])
def test_exact_kinematics_take_positions_from_velocities(integrator):
    """q_{n+1} = q_n + dt (v_n + v_{n+1}) / 2 on free nodes; the rest of the state as without it."""
    z, f, ei, nt, ref = _graph(seed=6)
    dt = torch.tensor(0.01, dtype=torch.float64)
    learned = _with_stats(_model(port=True, balanced=True, integrator=integrator, implicit_iterations=0))
    exact = _with_stats(_model(port=True, balanced=True, integrator=integrator, implicit_iterations=0,
                               exact_kinematics=True))
    a, b = learned.step(z, f, ei, nt, ref, dt), exact.step(z, f, ei, nt, ref, dt)
    free = nt != 1
    assert torch.allclose(b[free, :3], z[free, :3] + 0.5 * dt * (z[free, 3:6] + b[free, 3:6]), rtol=1e-14)
    assert not torch.allclose(a[free, :3], b[free, :3])          # the network's dq/dt is not v
    assert torch.equal(a[:, 3:], b[:, 3:]) and torch.equal(b[~free, :3], ref[~free])


def test_kinematics_option_follows_the_scene():
    from omegaconf import OmegaConf

    from thermognn.core.errors import ConfigError
    from thermognn.train.model import hyperparameters

    hp = lambda kin, vel, ham: hyperparameters(OmegaConf.create({"kinematics": kin}), 12, vel, ham)["exact_kinematics"]  # noqa: E731
    assert hp("auto", [3, 4, 5], False) and not hp("auto", [3, 4, 5], True) and not hp("auto", [], False)
    assert hp("exact", [3, 4, 5], True) and not hp("learned", [3, 4, 5], False)
    with pytest.raises(ConfigError, match="kinematics = exact needs the velocity"):
        hp("exact", [], False)
    with pytest.raises(ConfigError, match="model.kinematics = 'rigid', expected auto | exact | learned"):
        hp("rigid", [3, 4, 5], False)
    for key in ("aggregation", "integrator"):                        # one-line errors, not tracebacks
        with pytest.raises(ConfigError, match=f"model.{key} = 'max'"):
            hyperparameters(OmegaConf.create({key: "max"}), 12, [3, 4, 5], False)


def test_clamped_nodes_imposed():
    z, f, ei, nt, ref = _graph(seed=2)
    model = _model(port=True)
    out = model.step(z, f, ei, nt, ref, torch.tensor(0.01, dtype=torch.float64))
    clamped = nt == 1
    assert clamped.any()
    assert torch.equal(out[clamped, :3], ref[clamped])
    assert torch.equal(out[clamped, 3:6], torch.zeros_like(out[clamped, 3:6]))


def test_galilean_invariance():
    """A rigid translation of q (and X) changes nothing but q itself."""
    z, f, ei, nt, ref = _graph(seed=4)
    model = _model(port=True)
    shift = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64)
    # normalisation centres q: shift the mean with it so the normalised q moves rigidly too
    d1 = model.rates(z, f, ei, nt, ref, False)[0]
    z2 = z.clone()
    z2[:, :3] += shift
    model.z_mean[:3] += shift
    d2 = model.rates(z2, f, ei, nt, ref + shift, False)[0]
    assert torch.allclose(d1, d2, atol=1e-10)


def test_velocity_edges_carry_the_stretch_rate_and_ignore_a_uniform_velocity():
    """[dv, dv . dq/|dq|]: the stretch rate is d|dq|/dt, and a rigid velocity v0 changes nothing."""
    g = torch.Generator().manual_seed(7)
    dq, dx, dv = (torch.randn(50, 3, generator=g, dtype=torch.float64) for _ in range(3))
    feats = raw_edge_features(dq, dx, dv, True, True)
    assert feats.shape == (50, edge_feature_count(True, True)) == (50, 16)
    h = 1e-7
    stretch_rate = ((dq + h * dv).norm(dim=1) - (dq - h * dv).norm(dim=1)) / (2 * h)
    assert torch.allclose(feats[:, 15], stretch_rate, rtol=1e-6, atol=1e-9)
    z, f, ei, nt, ref = _graph(seed=6)
    model = _model(port=True, velocity_edges=True)
    z2 = z.clone()
    z2[:, 3:6] += torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
    e1, e2 = model.edge_features(z, ref, ei), model.edge_features(z2, ref, ei)
    assert torch.allclose(e1, e2, rtol=0, atol=1e-12)
    z2[:, 3:6] += 0.1 * z[:, 3:6]                                    # a non-uniform velocity change
    e3 = model.edge_features(z2, ref, ei)
    assert torch.equal(e3[:, :12], e1[:, :12]) and not torch.allclose(e3[:, 12:], e1[:, 12:])
    assert _model(port=True).edge_features(z, ref, ei).shape[1] == 12
    with pytest.raises(ValueError, match="velocity_edges needs the velocity"):
        TIGNN(9, [], velocity_edges=True)


def test_quasi_static_layout_without_velocity():
    """z = (q, sigma), D = 9: only q is imposed on clamped nodes."""
    z, f, ei, nt, ref = _graph(seed=5)
    z = torch.cat([z[:, :3], z[:, 6:]], 1)
    torch.manual_seed(0)
    model = TIGNN(9, [], hidden=8, mlp_layers=1, message_passing=1).double()
    out = torch.jit.script(model).step(z, f, ei, nt, ref, torch.tensor(0.01, dtype=torch.float64))
    clamped = nt == 1
    assert out.shape == (20, 9) and torch.equal(out[clamped, :3], ref[clamped])
    assert not torch.equal(out[clamped, 3:], z[clamped, 3:])  # stress still evolves on clamped nodes


def test_grown_model_computes_what_its_source_did_then_learns():
    """load_grown: a checkpoint's weights in the same network with more processor blocks (train.init
    with a larger model.message_passing). The new blocks start as the identity, so the grown model's
    rates equal the source's to round-off; its new blocks are open to training (their closing
    LayerNorms get gradients); any other difference of weights is refused."""
    from thermognn.train.model import grown_blocks, load_grown

    z, f, ei, nt, ref = _graph(seed=5)
    src = _with_stats(_model(port=True))
    with torch.no_grad():                       # trained LayerNorms are not at their initial 1, 0
        for p in src.parameters():
            p.add_(0.1 * torch.randn_like(p))
    hp_src = {"message_passing": 2, "shared_weights": False}
    hp = {"message_passing": 4, "shared_weights": False}
    assert grown_blocks(hp_src, hp) == 2
    assert grown_blocks(hp, hp_src) == 0 and grown_blocks(hp_src, hp_src) == 0
    assert grown_blocks(hp_src, {**hp, "shared_weights": True}) == 0
    torch.manual_seed(1)
    grown = TIGNN(12, [3, 4, 5], hidden=16, mlp_layers=2, message_passing=4, port=True).double()
    load_grown(grown, src.state_dict(), 2)
    r_src = src.rates(z, f, ei, nt, ref, False)[0]
    r_grown = grown.rates(z, f, ei, nt, ref, True)[0]     # as in training: differentiable
    assert torch.allclose(r_grown, r_src, rtol=0, atol=1e-12 * float(r_src.abs().max()))
    r_grown.pow(2).sum().backward()
    assert float(grown.blocks[3].node_mlp.net[-1].weight.grad.abs().sum()) > 0
    wider = TIGNN(12, [3, 4, 5], hidden=24, mlp_layers=2, message_passing=4, port=True).double()
    with pytest.raises((ValueError, RuntimeError)):
        load_grown(wider, src.state_dict(), 2)


def test_sparse_matrix_is_the_dense_product_to_any_order_and_scripted(tmp_path):
    """SparseMatrix (the linear prior's FE operators): x Aᵀ of the dense A, with renumbered
    columns, its first and second derivatives those of the dense product, and the same after a
    TorchScript round trip."""
    scipy_sparse = pytest.importorskip("scipy.sparse")
    from thermognn.train.prior import SparseMatrix

    A = scipy_sparse.random(7, 5, density=0.4, format="csr", random_state=1)                # [m, k]
    columns = [8, 0, 3, 5, 1]                                                                # k of 9 inputs
    dense = torch.zeros(7, 9, dtype=torch.float64)
    dense[:, columns] = torch.as_tensor(A.toarray())
    op = SparseMatrix(A, columns=columns)
    x = torch.randn(3, 9, dtype=torch.float64, requires_grad=True)
    assert torch.allclose(op(x), x @ dense.T, rtol=0, atol=1e-14)
    assert torch.autograd.gradcheck(op, (x,)) and torch.autograd.gradgradcheck(lambda y: op(y) ** 2, (x,))
    assert not op.state_dict()                                                               # rebuilt, not saved
    path = tmp_path / "op.pt"
    torch.jit.save(torch.jit.script(op), str(path))
    assert torch.equal(torch.jit.load(str(path))(x.detach()), op(x.detach()))
    assert SparseMatrix(torch.zeros(0, 4).numpy())(torch.ones(2, 4, dtype=torch.float64)).shape == (2, 0)
