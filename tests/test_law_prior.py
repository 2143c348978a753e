"""thermognn/train/law_prior.py: the data's own hyperelastic laws in torch, against the numpy
laws of ``thermognn.core.hyperelastic`` (the FE's, without dolfinx). The prior's step against the
FE solid is in tests/test_fe_modes.py (it needs dolfinx's data)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from thermognn.core.hyperelastic import NeoHookean, Ogden  # noqa: E402
from thermognn.train.law_prior import (HyperelasticNewmarkPrior, cofactor, learned_tangent,  # noqa: E402
                                       neo_hookean_pk2, neo_hookean_tangent, ogden_isochoric_pk2,
                                       ogden_tangent, ogden_volumetric_pk2)
from thermognn.train.learned_law import CONVEX, StrainEnergy  # noqa: E402
from thermognn.train.mat3 import det3, det_inverse3, inverse3  # noqa: E402


def _gradients() -> np.ndarray:
    """Deformation gradients [52, 3, 3]: 50 random ones near I, I itself (all stretches
    coincide) and a uniaxial stretch (two coincide), where Cardano's eigenvalues degenerate."""
    F = np.eye(3) + 0.1 * np.random.default_rng(0).standard_normal((50, 3, 3))
    return np.concatenate([F, np.eye(3)[None], np.diag([1.1, 0.95, 0.95])[None]])


def test_ogden_stress_is_the_derivative_of_the_fe_laws_regularised_eigenvalues():
    """The chain rule written out in ``ogden_isochoric_pk2`` is the derivative the numpy law takes
    by complex steps of the same regularised expression (as UFL differentiates it), to round-off,
    at random F, at F = I and at a uniaxial stretch (two terms, one of negative α); the volumetric
    stress too, and the neo-Hookean closed form."""
    F = _gradients()
    Ft = torch.as_tensor(F)
    C = Ft.transpose(-1, -2) @ Ft
    mu, alpha, d = [2000.0, -500.0], [16.19, -3.0], [1e-4, 1e-3]
    s_iso, s_vol = Ogden(mu, alpha, d).pk2(F)
    t_iso, t_vol = ogden_isochoric_pk2(C, mu, alpha).numpy(), ogden_volumetric_pk2(Ft, C, d).numpy()
    scale = np.abs(s_iso).max()
    assert np.abs(t_iso - s_iso).max() < 1e-12 * scale and np.abs(t_vol - s_vol).max() < 1e-12 * np.abs(s_vol).max()
    assert np.abs(t_iso[-2]).max() < 1e-12 * scale                       # no isochoric stress at rest
    n_iso, n_vol = NeoHookean(1e4, 1e-5).pk2(F)
    t_iso, t_vol = (x.numpy() for x in neo_hookean_pk2(Ft, 1e4, 1e-5))
    assert np.abs(t_iso - n_iso).max() < 1e-12 * np.abs(n_iso).max() and np.abs(t_vol - n_vol).max() < 1e-9
    B = torch.randn(4, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(cofactor(B), torch.linalg.det(B)[:, None, None] * torch.linalg.inv(B).transpose(-1, -2))


def test_ogden_stress_is_smooth_for_autograd_where_stretches_coincide():
    """Back-propagation through the Ogden stress (a rollout's loss through the law prior) is
    finite at F = I and at a uniaxial stretch, and matches central differences elsewhere."""
    F = torch.as_tensor(_gradients()[[0, -2, -1]]).requires_grad_()
    S = ogden_isochoric_pk2(F.transpose(-1, -2) @ F, [2000.0], [16.19])
    (grad,) = torch.autograd.grad((S * S).sum(), F)
    assert torch.isfinite(grad).all()
    with torch.no_grad():
        E = torch.zeros(3, 3, 3, dtype=torch.float64)
        E[0, 1, 2] = 1e-6

        def f(G):
            return (ogden_isochoric_pk2(G.transpose(-1, -2) @ G, [2000.0], [16.19]) ** 2).sum()
        assert float((f(F + E) - f(F - E)) / 2e-6) == pytest.approx(float(grad[0, 1, 2]), rel=1e-5)


def test_the_neo_hookean_tangent_is_the_derivative_of_its_stress_and_the_numpy_laws():
    """``neo_hookean_tangent``'s closed form is ∂P/∂F of P = F (w_vol S_vol + w_iso S_iso + extra)
    as autograd takes it, to round-off, at random F, at F = I and at a uniaxial stretch, with a
    relaxing step's weights and history stress; and the numpy law's ``pk1_tangent``."""
    F = torch.as_tensor(_gradients())                                               # [52, 3, 3]
    extra = 50.0 * torch.randn(52, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    extra = extra + extra.transpose(-1, -2)
    c10, d1, w_iso, w_vol = 1e4, 1e-5, 0.7, 1.3

    def pk1(G):
        s_iso, s_vol = neo_hookean_pk2(G, c10, d1)
        return G @ (w_vol * s_vol + w_iso * s_iso + extra)
    jac = torch.autograd.functional.jacobian(pk1, F)                               # [52, 3, 3, 52, 3, 3]
    cells = torch.arange(52)
    auto = jac[cells, :, :, cells]                                                  # [52, 3, 3, 3, 3]
    A = neo_hookean_tangent(F, c10, d1, w_iso, w_vol, extra)
    assert float((A - auto).abs().max()) < 1e-12 * float(auto.abs().max())
    law = NeoHookean(c10, d1)
    _, A_np = law.pk1_tangent(F.numpy(), 1.0, extra.numpy())                        # [52, i, j, k, l]
    A1 = neo_hookean_tangent(F, c10, d1, 1.0, 1.0, extra).numpy()
    assert np.abs(A1 - A_np).max() < 1e-12 * np.abs(A_np).max()


def test_the_law_prior_names_a_law_it_does_not_step():
    """It steps the laws ``law_from_config`` reads (whose own errors name the scene's law,
    tests/test_fe_modes.py); anything else is refused by name."""
    with pytest.raises(ValueError, match="the law prior steps a NeoHookean, Ogden or learned law, not 'mooney'"):
        HyperelasticNewmarkPrior(None, 0, 1e-3, None, None, 0.0, 0.0, "mooney")


def test_the_law_prior_fits_only_trajectories_the_fe_stepped_once_a_step():
    """Where the FE cut its steps the data's step is not one Newmark step of Δt and the law prior's
    exact remainders are not round-off: ``law_fit_trajectories`` leaves such trajectories out of
    the fit and names them with the size of their G against their loads."""
    from types import SimpleNamespace

    from thermognn.core.errors import DataError
    from thermognn.train.hybrid import LAW_STEP_TOL, law_fit_trajectories

    free = torch.tensor([True, True, False])
    force = torch.ones(4, 3, 3)
    trajs = [SimpleNamespace(name=f"traj_{i}", force=force) for i in range(3)]
    G = [torch.full((4, 3, 3), 1e-12), torch.full((4, 3, 3), 0.3), torch.zeros(4, 3, 3)]
    H = [torch.zeros(4, 3, 6)] * 3
    kept, G_kept, H_kept, cut = law_fit_trajectories(trajs, G, H, free)
    assert [t.name for t in kept] == ["traj_0", "traj_2"] and len(G_kept) == len(H_kept) == 2
    assert [n for n, _ in cut] == ["traj_1"] and cut[0][1] == pytest.approx(0.3) and cut[0][1] > LAW_STEP_TOL
    with pytest.raises(DataError, match="every training trajectory's FE cut its steps"):
        law_fit_trajectories(trajs[1:2], G[1:2], H[1:2], free)


def test_the_ogden_tangent_is_the_derivative_of_its_stress_and_the_numpy_laws():
    """``ogden_tangent``'s closed form (the regularised eigenvalues' chain rule differentiated line
    by line) is ∂P/∂F of P = F (w_vol S_vol + w_iso S_iso + extra) as autograd takes it, to
    round-off, at random F, at F = I and at a uniaxial stretch, with two terms (one of negative α),
    two volumetric terms, a relaxing step's weights and a history stress; and the numpy law's
    central differences to their truncation error."""
    F = torch.as_tensor(_gradients())                                               # [52, 3, 3]
    extra = 50.0 * torch.randn(52, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    extra = extra + extra.transpose(-1, -2)
    mu, alpha, d, w_iso, w_vol = [2000.0, -500.0], [16.19, -3.0], [1e-4, 1e-3], 0.7, 1.3

    def pk1(G):
        C = G.transpose(-1, -2) @ G
        return G @ (w_vol * ogden_volumetric_pk2(G, C, d) + w_iso * ogden_isochoric_pk2(C, mu, alpha) + extra)
    jac = torch.autograd.functional.jacobian(pk1, F)                               # [52, 3, 3, 52, 3, 3]
    cells = torch.arange(52)
    auto = jac[cells, :, :, cells]                                                  # [52, 3, 3, 3, 3]
    A = ogden_tangent(F, mu, alpha, d, w_iso, w_vol, extra)
    scale = float(auto.abs().max())
    assert float((A - auto).abs().max()) < 1e-13 * scale
    assert float((A[-2:] - auto[-2:]).abs().max()) < 1e-13 * scale                # F = I, uniaxial
    _, A_np = Ogden(mu, alpha, d).pk1_tangent(F.numpy(), 1.0, extra.numpy())        # [52, i, j, k, l]
    A1 = ogden_tangent(F, mu, alpha, d, 1.0, 1.0, extra).numpy()
    assert np.abs(A1 - A_np).max() < 1e-8 * np.abs(A_np).max()
    assert ogden_tangent(F[:2].reshape(1, 2, 3, 3), mu, alpha, d, w_iso, w_vol, None).shape == (1, 2, 3, 3, 3, 3)


def _learned(seed: int = 4) -> StrainEnergy:
    """A learned law with every weight non-zero (its hidden layers' outputs made large)."""
    law = StrainEnergy((5, 3), mu=1e4, kappa=3e4, scales=(0.2, 0.3, 0.05), seed=seed)
    law.iso_out.mul_(100.0)
    law.vol_out.mul_(100.0)
    law.iso_linear.copy_(torch.tensor([0.4, -0.1], dtype=torch.float64))
    law.vol_quadratic.fill_(0.02)
    return law


def test_closed_form_determinants_and_inverses_are_lapacks():
    """``mat3``'s cofactor determinant and adjugate inverse of stacks of 3×3 matrices equal
    LAPACK's to round-off (random F near I, I, a uniaxial stretch, far from I, a batch [2, 26]),
    in TorchScript too, pass autograd as det's own gradient (cof F), and give a singular matrix a
    zero determinant and a non-finite inverse instead of raising."""
    F = torch.as_tensor(_gradients())
    F = torch.cat([F, 3.0 * torch.randn(8, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))])
    for A in (F, F.reshape(2, -1, 3, 3)):
        det, inv = det_inverse3(A)
        assert float((det - torch.linalg.det(A)).abs().max()) < 1e-13 * float(A.abs().amax() ** 3)
        assert float(((inv - torch.linalg.inv(A)) / torch.linalg.inv(A).abs().amax((-2, -1), keepdim=True)).abs().max()) < 1e-11
        assert torch.equal(det3(A), det) and torch.equal(inverse3(A), inv)
        scripted = torch.jit.script(det_inverse3)(A)
        assert torch.equal(scripted[0], det) and torch.equal(scripted[1], inv)
    Fg = F.clone().requires_grad_()
    (grad,) = torch.autograd.grad(det3(Fg).sum(), Fg)
    assert float((grad - cofactor(F)).abs().max()) < 1e-12 * float(cofactor(F).abs().max())
    singular = torch.tensor([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]], dtype=torch.float64)
    det, inv = det_inverse3(singular)
    assert float(det) == 0.0 and not bool(torch.isfinite(inv).all())


def test_the_learned_law_stress_is_its_energys_derivative_and_vanishes_at_rest():
    """``StrainEnergy.pk2``'s closed form is 2 ∂Ψ/∂C of its own energy as autograd takes it, to
    round-off, at random F and a uniaxial stretch; at rest (C = I) S = 0 whatever the weights."""
    law = _learned()
    F = torch.as_tensor(_gradients())
    C = (F.transpose(-1, -2) @ F).requires_grad_()
    (grad,) = torch.autograd.grad(law.energy(C).sum(), C)
    S_iso, S_vol = law.pk2(C.detach())
    auto = grad + grad.transpose(-1, -2)
    assert float((S_iso + S_vol - auto).abs().max()) < 1e-12 * float(auto.abs().max())
    assert float(S_iso[-2].abs().max()) < 1e-9 and float(S_vol[-2].abs().max()) < 1e-9      # F = I
    # the step's pk2 (coefficients gathered per cell) is the fit's stress of ``geometry``, to round-off
    for fast, fit in zip((S_iso, S_vol), law.stress(*law.geometry(C.detach()))):
        assert float((fast - fit).abs().max()) < 1e-13 * float(fit.abs().max())
    assert float(law.energy(torch.eye(3, dtype=torch.float64)).abs()) < 1e-9


def test_the_learned_law_holds_the_neo_hookean_law_and_its_tangent():
    """With its hidden outputs zero and its linear weights C10 s1 / μ_s and 2 s3² / (D1 κ_s) the
    learned law is the neo-Hookean law (stress to round-off), and its tangent (``learned_tangent``)
    the neo-Hookean closed form's to round-off, with a relaxing step's weights and history stress;
    for any weights it is autograd's derivative of its stress to round-off."""
    F = torch.as_tensor(_gradients())
    extra = 50.0 * torch.randn(52, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    extra = extra + extra.transpose(-1, -2)
    c10, d1 = 1e4, 1e-5
    law = StrainEnergy((4, 2), mu=2e4, kappa=2e5, scales=(0.2, 0.3, 0.05))
    law.iso_out.zero_()
    law.vol_out.zero_()
    law.iso_linear[0] = c10 * 0.2 / 2e4
    law.vol_quadratic[0] = 2.0 * 0.05**2 / (d1 * 2e5)
    C = F.transpose(-1, -2) @ F
    for mine, theirs in zip(law.pk2(C), neo_hookean_pk2(F, c10, d1)):
        assert float((mine - theirs).abs().max()) < 1e-12 * float(theirs.abs().max())
    A, B = learned_tangent(law, F, 0.7, 1.3, extra), neo_hookean_tangent(F, c10, d1, 0.7, 1.3, extra)
    assert float((A - B).abs().max()) < 1e-12 * float(B.abs().max())
    law = _learned()

    def pk1(G):
        s_iso, s_vol = law.pk2(G.transpose(-1, -2) @ G)
        return G @ (1.3 * s_vol + 0.7 * s_iso + extra)
    jac = torch.autograd.functional.jacobian(pk1, F)
    cells = torch.arange(52)
    auto = jac[cells, :, :, cells]                                                  # [52, 3, 3, 3, 3]
    A = learned_tangent(law, F, 0.7, 1.3, extra)
    assert float((A - auto).abs().max()) < 1e-12 * float(auto.abs().max())
    assert float((A[-2:] - auto[-2:]).abs().max()) < 1e-12 * float(auto.abs().max())      # F = I, uniaxial


def test_the_learned_law_refuses_a_shape_it_cannot_have():
    with pytest.raises(ValueError, match=r"the learned law's hidden units: \(0, 3\), expected two integers >= 1"):
        StrainEnergy((0, 3))


def test_learned_prony_terms_relax_as_the_linear_solids_own():
    """``PronySeries.terms`` gives the law prior's relaxation constants as ``LinearSolid.relaxation``
    does for the same (ḡ_i, τ_i), with every ḡ_i positive and g∞ = 1 − Σ ḡ_i > 0 whatever its logits."""
    from thermognn.core.linear import LinearSolid
    from thermognn.train.learned_law import PronySeries

    series = PronySeries(2, 0.6)
    with torch.no_grad():
        series.logits.copy_(torch.tensor([-1.0, 2.0, 0.5], dtype=torch.float64))
    values = series.values()
    assert all(g > 0 for g, _ in values) and sum(g for g, _ in values) < 1.0
    solid = LinearSolid.__new__(LinearSolid)
    solid.prony, solid.stiffness_iso = tuple(values), object()
    expected = torch.tensor(solid.relaxation(0.02), dtype=torch.float64)            # [T, 3]
    got = torch.stack(series.terms(0.02), 1)
    assert torch.allclose(got, expected, rtol=1e-12, atol=0.0)
    assert [t for _, t in values] == pytest.approx([3.0, 0.3])                      # the start: 5 and 1/2 durations


def test_the_convex_learned_family_cannot_soften():
    """With the convex family's weights (``CONVEX``: the hidden outputs a, the volumetric k0 and e)
    positive, the energy's Hessian in the isochoric invariants is positive semi-definite and U'' > 0
    everywhere, far beyond the fitted states too (second derivatives autograd's of the first);
    with those weights free in sign (the default family) the same law softens somewhere."""
    gen = torch.Generator().manual_seed(3)
    I1b = 3.0 + 20.0 * torch.rand(400, dtype=torch.float64, generator=gen)    # far beyond s1, s2 = 0.2, 0.3
    I2b = 3.0 + 20.0 * torch.rand(400, dtype=torch.float64, generator=gen)
    J = 0.2 + 3.0 * torch.rand(400, dtype=torch.float64, generator=gen)       # and s3 = 0.05

    def hessians(law):
        p11, p12, p22, ddU = law.energy_second_derivatives(I1b, I2b, J)
        x = torch.stack([I1b, I2b, J], -1).requires_grad_()
        psi1, psi2, dU = law.energy_derivatives(x[:, 0], x[:, 1], x[:, 2])
        d1, d2, d3 = (torch.autograd.grad(y.sum(), x, retain_graph=True)[0] for y in (psi1, psi2, dU))
        for mine, auto in ((p11, d1[:, 0]), (p12, d1[:, 1]), (p12, d2[:, 0]), (p22, d2[:, 1]), (ddU, d3[:, 2])):
            assert float((mine - auto).abs().max()) <= 1e-10 * float(auto.abs().max())
        return torch.minimum(p11, p22), p11 * p22 - p12 * p12, ddU

    free = _learned()
    lowest, det, ddU = hessians(free)
    assert bool((lowest < 0).any() | (det < 0).any())
    convex = _learned()
    with torch.no_grad():
        for name in CONVEX:
            getattr(convex, name).abs_().add_(1e-3)
    lowest, det, ddU = hessians(convex)
    assert bool((lowest >= 0).all()) and bool((det >= -1e-12 * lowest.abs().max() ** 2).all()) and bool((ddU > 0).all())


def test_the_learned_laws_acoustic_values_are_its_stress_derivative_and_tell_ellipticity():
    """``acoustic_values``: (m ⊗ n) : A : (m ⊗ n) is the derivative of P = F S along m ⊗ n, dotted
    with it (central differences of ``pk2``, to 1e-6); a neo-Hookean law (C10 = μ_s: shear modulus
    2 μ_s) is 2 μ_s at rest, its smallest value, and elliptic over twice its box; Mooney–Rivlin with
    C01 = −2 C10 (shear modulus at rest 2 (C10 + C01) < 0) is not, anywhere; the penalty is zero for
    the first, positive for the second, and L-BFGS on the penalty alone makes the second elliptic."""
    from thermognn.train.learned_law import (acoustic_values, direction_pairs, ellipticity, ellipticity_penalty,
                                             principal_deformations)

    law = _learned()
    F = torch.as_tensor(_gradients())[:8]                                          # [8, 3, 3]
    m, n = direction_pairs(8, per=12)
    q = acoustic_values(law, F, m, n)                                              # [8, 12]
    D = m.unsqueeze(-1) * n.unsqueeze(-2)                                          # [8, 12, 3, 3]
    h = 1e-6

    def first(G):
        S_iso, S_vol = law.pk2(G.transpose(-1, -2) @ G)
        return G @ (S_iso + S_vol)

    Fk = F.unsqueeze(1)
    fd = ((first(Fk + h * D) - first(Fk - h * D)) / (2 * h) * D).sum((-2, -1))
    assert float((q - fd).abs().max()) < 1e-6 * float(fd.abs().max())

    neo = StrainEnergy((2, 2), mu=1e4, kappa=3e4, scales=(0.2, 0.3, 0.05))
    with torch.no_grad():
        neo.iso_out.zero_()
        neo.vol_out.zero_()
        neo.iso_linear.copy_(torch.tensor([0.2, 0.0], dtype=torch.float64))     # Ψ_iso = μ_s (Ī1 − 3)
        neo.vol_quadratic.fill_(0.05)
    assert ellipticity(neo, 1e-6, 64)["min"] == pytest.approx(2.0, rel=1e-6)
    wide = ellipticity(neo, 2.0)
    assert wide["fraction"] == 0.0 and 0.0 < wide["min"] < 2.0
    F2 = principal_deformations(neo.scales.tolist(), 2.0, 256)
    assert F2.shape == (256, 3, 3) and bool((torch.linalg.det(F2) > 0).all())
    pairs = direction_pairs(256)
    assert float(ellipticity_penalty(neo, F2, *pairs)) == 0.0

    mooney = StrainEnergy((2, 2), mu=1e4, kappa=3e4, scales=(0.2, 0.3, 0.05))
    with torch.no_grad():
        mooney.iso_out.zero_()
        mooney.vol_out.zero_()
        mooney.iso_linear.copy_(torch.tensor([0.2, -0.6], dtype=torch.float64))  # C01 = −2 C10
        mooney.vol_quadratic.fill_(0.05)
    assert ellipticity(mooney, 1e-6, 64)["min"] < 0 and ellipticity(mooney, 1.0)["fraction"] == 1.0
    assert float(ellipticity_penalty(mooney, F2, *pairs)) > 0.0
    mooney.iso_linear.requires_grad_(True)
    opt = torch.optim.LBFGS([mooney.iso_linear], max_iter=50, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = ellipticity_penalty(mooney, F2, *pairs)
        loss.backward()
        return loss

    opt.step(closure)
    mooney.iso_linear.requires_grad_(False)
    assert ellipticity(mooney, 2.0)["fraction"] == 0.0


def test_the_learned_laws_guard_is_nothing_within_its_states_and_stiffens_beyond():
    """``StrainEnergy.settle_guard``: within twice the fitted box (|x1|, |x2|, |y| <= ``GUARD_MARGIN``
    = 2, the training states' largest invariants) the guarded law is the law, to the bit; beyond it the stress is
    still 2 ∂Ψ/∂C of its (guarded) energy and the tangent autograd's derivative of that stress, to
    round-off; a law that softens beyond its states (free weights whose energy falls as Ī2 grows)
    rises there once guarded; and loading a state_dict (which holds no guard) settles it anew."""
    law = _learned()
    with torch.no_grad():                              # soften beyond the box: Ψ falls as Ī2 grows
        law.iso_linear.copy_(torch.tensor([0.4, -3.0], dtype=torch.float64))
    guarded = _learned()
    guarded.load_state_dict(law.state_dict())
    assert "guard" not in law.state_dict() and float(law.guard.abs().max()) == 0.0
    assert bool((guarded.guard > 0).all())
    law.settle_guard()
    assert torch.equal(law.guard, guarded.guard)
    law.guard.zero_()
    # within twice the box (scales 0.2, 0.3, 0.05), beyond the box itself too
    within = torch.eye(3, dtype=torch.float64) + 0.015 * torch.randn(40, 3, 3, dtype=torch.float64,
                                                                      generator=torch.Generator().manual_seed(1))
    C = within.transpose(-1, -2) @ within
    I1b, I2b, J, _ = law.invariants(C)
    assert bool(((I1b - 3) < 0.4).all() & ((I2b - 3) < 0.6).all() & ((J - 1).abs() < 0.1).all())
    assert bool(((J - 1).abs() > 0.05).any())
    for a, b in zip(law.pk2(C), guarded.pk2(C)):
        assert torch.equal(a, b)
    assert torch.equal(law.energy(C), guarded.energy(C))
    # beyond it: the guarded stress is its energy's derivative, its tangent the stress's
    F = torch.as_tensor(_gradients()[:50]) + 0.5 * torch.eye(3, dtype=torch.float64) * torch.tensor([1.0, -0.4, 0.0])
    C = (F.transpose(-1, -2) @ F).requires_grad_()
    I1b, I2b, J, _ = guarded.invariants(C.detach())
    assert bool(((I1b - 3) > 0.4).any() & ((I2b - 3) > 0.6).any() & ((J - 1).abs() > 0.1).any())
    (grad,) = torch.autograd.grad(guarded.energy(C).sum(), C)
    S_iso, S_vol = guarded.pk2(C.detach())
    auto = grad + grad.transpose(-1, -2)
    assert float((S_iso + S_vol - auto).abs().max()) < 1e-9 * float(auto.abs().max())

    def pk1(G):
        s_iso, s_vol = guarded.pk2(G.transpose(-1, -2) @ G)
        return G @ (1.3 * s_vol + 0.7 * s_iso)
    jac = torch.autograd.functional.jacobian(pk1, F)
    cells = torch.arange(F.shape[0])
    auto = jac[cells, :, :, cells]
    A = learned_tangent(guarded, F, 0.7, 1.3, None)
    assert float((A - auto).abs().max()) < 1e-9 * float(auto.abs().max())
    # along Ī2 beyond the box the unguarded law's energy falls without bound, the guarded one's rises
    I1b = torch.full((6,), 3.1, dtype=torch.float64)
    I2b = 3.0 + 0.3 * torch.tensor([2.0, 4.0, 8.0, 16.0, 32.0, 64.0], dtype=torch.float64)
    ones = torch.ones(6, dtype=torch.float64)
    assert bool((law.energy_derivatives(I1b, I2b, ones)[1] < 0).all())
    psi2 = guarded.energy_derivatives(I1b, I2b, ones)[1]
    assert float(psi2[-1]) > 0 and bool((psi2[1:] >= psi2[:-1]).all())
    for J in (1.0 - 0.05 * torch.tensor([2.0, 5.0, 10.0, 18.0], dtype=torch.float64),      # and beyond
              1.0 + 0.05 * torch.tensor([2.0, 5.0, 10.0, 20.0], dtype=torch.float64)):     # |J − 1| = 2 s3
        dU = guarded.energy_derivatives(3.0 * torch.ones(4, dtype=torch.float64),
                                        3.0 * torch.ones(4, dtype=torch.float64), J)[2]
        away = torch.sign(J - 1.0)                                                           # U' grows away from 1
        assert bool((dU * away > 0).all()) and bool(((dU[1:] - dU[:-1]) * away[1:] > 0).all())


def test_a_newton_update_cut_short_to_spare_a_cell_is_not_convergence():
    """``whole_move``: what a step's convergence is judged by. An update ``admissible`` took whole
    is judged by what it moved, to the bit (base − du − base, as before session 90); one it
    shortened, or cut to nothing because every halving still crushed a cell, by the whole update,
    so the step is not taken as converged where its residual is not small."""
    gen = torch.Generator().manual_seed(2)
    base = torch.randn(2, 12, dtype=torch.float64, generator=gen)
    du = 1e-3 * torch.randn(2, 12, dtype=torch.float64, generator=gen)
    prior = HyperelasticNewmarkPrior.__new__(HyperelasticNewmarkPrior)
    taken = torch.stack([base[0] - du[0], base[1]])                # sample 1: cut to nothing
    move = HyperelasticNewmarkPrior.whole_move(prior, base, du, taken)
    assert torch.equal(move[0], taken[0] - base[0]) and torch.equal(move[1], du[1])
    half = torch.stack([base[0] - 0.5 * du[0], base[1] - du[1]])    # sample 0: halved
    move = HyperelasticNewmarkPrior.whole_move(prior, base, du, half)
    assert torch.equal(move[0], du[0]) and torch.equal(move[1], half[1] - base[1])


def test_the_learned_laws_fit_picks_the_widest_trajectories_first():
    """widest_first (``train.law_fit_pick=widest``): the trajectories reaching the largest
    |Ī1 − 3|, |Ī2 − 3|, |J − 1| are always among the k picked (each once), the rest evenly through
    the others, in the list's order; k at least the list's length keeps it all."""
    from thermognn.train.learned_law import widest_first

    names = [f"traj_{i}" for i in range(20)]
    extents = torch.full((20, 3), 0.1, dtype=torch.float64)                  # [n, (Ī1, Ī2, J)]
    extents[13, 0], extents[13, 1], extents[7, 2] = 0.7, 0.5, 0.3             # traj_13 widest twice
    picked = widest_first(names, extents, 4)
    assert len(picked) == 4 and {"traj_13", "traj_7"} <= set(picked) and picked == sorted(picked, key=names.index)
    assert set(picked) - {"traj_13", "traj_7"} == {"traj_0", "traj_19"}       # the others' ends
    assert widest_first(names, extents, 1) == ["traj_13"]
    assert widest_first(names[:3], extents[:3], 8) == names[:3]


def test_the_law_priors_strain_energy_is_the_potential_of_its_stresses():
    """``HyperelasticNewmarkPrior.strain_energy_density`` (what ``evaluate`` reports the law's energy
    by) is the potential of ``pk2``'s stresses for each law it steps: ∂Ψ_iso/∂F = F S_iso and
    ∂Ψ_vol/∂F = F S_vol by autograd, to round-off, at random F, F = I and a uniaxial stretch (Ogden
    through the FE's regularised eigenvalues, two terms, one of negative α); Ψ = 0 at rest (Ogden: to
    its regularisation's 1e-9 Pa), and
    Ogden's isochoric energy is the numpy law's."""
    from types import SimpleNamespace

    F = torch.as_tensor(_gradients())
    laws = {"neo_hookean": SimpleNamespace(learned=False, ogden=False, c10=1e4, d1=1e-5),
            "ogden": SimpleNamespace(learned=False, ogden=True, ogden_mu=[2000.0, -500.0], ogden_alpha=[16.19, -3.0],
                                     ogden_d=[1e-4, 1e-3]),
            "learned": SimpleNamespace(learned=True, ogden=False, learned_law=_learned())}
    for name, prior in laws.items():
        prior.pk2 = lambda F, p=prior: HyperelasticNewmarkPrior.pk2(p, F)
        G = F.clone().requires_grad_()
        iso, vol = HyperelasticNewmarkPrior.strain_energy_density(prior, G)
        S_iso, S_vol = prior.pk2(F)
        for psi, S in ((iso, S_iso), (vol, S_vol)):
            (grad,) = torch.autograd.grad(psi.sum(), G, retain_graph=True)
            P = F @ S
            assert float((grad - P).abs().max()) < 1e-9 * float(P.abs().max()), name
        rest = HyperelasticNewmarkPrior.strain_energy_density(prior, torch.eye(3, dtype=torch.float64))
        assert abs(float(rest[0])) < 1e-8 and abs(float(rest[1])) < 1e-8, name     # (moduli 1e3-1e4 Pa)
    ogden = Ogden([2000.0, -500.0], [16.19, -3.0], [1e-4, 1e-3])
    C = (F.transpose(-1, -2) @ F)
    numpy_iso = ogden.isochoric_energy(C.numpy())
    iso = HyperelasticNewmarkPrior.strain_energy_density(laws["ogden"], F)[0].numpy()
    assert np.abs(iso - numpy_iso).max() < 1e-12 * np.abs(numpy_iso).max()
