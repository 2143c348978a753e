"""Material laws against closed forms: real dolfinx solves of a homogeneous unit cube (P1 tets)."""

import numpy as np
import pytest

pytest.importorskip("dolfinx")

from thermognn.core.errors import ConfigError  # noqa: E402
from thermognn.generate import cases  # noqa: E402
from thermognn.generate.materials import Material, PronyTerm, material_from_config  # noqa: E402

NEO_HOOKEAN = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
OGDEN_LIVER = Material("ogden", {"mu": [2.0e3], "alpha": [16.19], "D": [1.0e-4]})


def test_neo_hookean_uniaxial_stretch_matches_closed_form():
    """λ = 1.5, lateral faces traction-free: Cauchy σ11 and 2nd Piola–Kirchhoff S11 within 1e-6
    relative of the closed form, σ22 = σ33 ≈ 0."""
    r = cases.uniaxial(NEO_HOOKEAN, 1.5)
    assert r.rel_error <= 1e-6, r
    assert abs(r.S11_fe - r.S11_exact) <= 1e-6 * abs(r.S11_exact)   # 2nd Piola–Kirchhoff output
    assert abs(r.lateral_fe - r.lateral_exact) <= 1e-8
    assert r.max_lateral_stress <= 1e-6 * abs(r.sigma11_exact)


@pytest.mark.parametrize("stretch", [1.2, 0.7])  # 0.7: the 30 % compression hard case
def test_ogden_alpha_16_uniaxial_matches_closed_form(stretch):
    """Ogden α = 16.19 (liver), tension and 30 % compression: σ11 within 1e-6 relative, no NaN."""
    r = cases.uniaxial(OGDEN_LIVER, stretch, n_steps=6)
    assert np.isfinite(r.sigma11_fe)
    assert r.rel_error <= 1e-6, r
    assert abs(r.lateral_fe - r.lateral_exact) <= 1e-8
    assert r.max_lateral_stress <= 1e-6 * abs(r.sigma11_exact)


def test_ogden_small_strain_modulus_and_rest_state():
    """Where all stretches coincide (F = I) the regularised eigenvalues give zero stress, and the
    small-strain uniaxial response has Young's modulus 9Kμ/(3K+μ) within 1e-3 (μ = Σ μi)."""
    mat = Material("ogden", {"mu": [1.0e4], "alpha": [16.19], "D": [1.0e-5]})
    r = cases.uniaxial(mat, 1.0 + 1e-5, n_steps=1)
    E = 9 * mat.bulk_modulus * mat.shear_modulus / (3 * mat.bulk_modulus + mat.shear_modulus)
    assert abs(r.sigma11_fe / 1e-5 - E) / E < 1e-3
    assert r.rel_error <= 1e-6


OGDEN_TWO_TERMS = Material("ogden", {"mu": [3.0e3, -0.5e3], "alpha": [2.5, -2.0], "D": [2.0e-5, 1.0e-3]})


@pytest.mark.parametrize("mat", [OGDEN_LIVER, OGDEN_TWO_TERMS], ids=["ogden1", "ogden2"])
@pytest.mark.parametrize("stretches", [(1.1, 1.1, 1.1), (0.9, 1.1, 1.1), (1.2, 0.9, 1.05)],
                         ids=["hydrostatic", "equibiaxial", "triaxial"])
def test_ogden_prescribed_homogeneous_deformation(mat, stretches):
    """F = diag(λ1, λ2, λ3) prescribed: all three, two or no stretches coincide (where the closed-form
    eigenvalues degenerate). Principal Cauchy stresses within 1e-6 relative (of max |σ|), shear ~ 0.
    The two-term law also exercises the (J − 1)^4 volumetric term."""
    sig, exact = cases.homogeneous_stress(mat, stretches)
    scale = np.abs(exact).max()
    assert np.all(np.isfinite(sig))
    assert np.abs(sig[:, :3] - exact).max() <= 1e-6 * scale
    assert np.abs(sig[:, 3:]).max() <= 1e-6 * scale


def test_prony_relaxation_follows_g_R():
    """Step stretch (applied over the first dt = τ/50, then held) of a neo-Hookean + Prony
    (bunny: ḡ = 0.3, τ = 0.1 s) cube: the deviatoric stress relaxes as g_R(t) within 1 % over 5 τ."""
    elastic = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5})
    visco = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}, prony=(PronyTerm(0.3, 0.1),))
    times, dev, g_R = cases.relaxation(visco, stretch=1.1, dt=0.002)
    _, dev_el, _ = cases.relaxation(Material("neo_hookean", elastic.params, prony=(PronyTerm(1e-12, 0.1),)),
                                   stretch=1.1, dt=0.5, t_end=0.5)
    assert times[-1] == pytest.approx(0.5)
    ratio = dev[1:] / dev_el[-1]
    assert np.max(np.abs(ratio - g_R[1:])) <= 0.01
    assert ratio[-1] == pytest.approx(1 - 0.3 * (1 - np.exp(-5)), abs=0.01)


def test_two_term_prony_liver_relaxation():
    """Liver Prony series (ḡ = 0.56057, 0.40585; τ = 6.36173, 0.73348 s): within 1 % of g_R over
    5 τ of the short term (dt = τ2/50)."""
    prony = (PronyTerm(0.56057, 6.36173), PronyTerm(0.40585, 0.73348))
    visco = Material("neo_hookean", {"C10": 1.0e4, "D1": 1.0e-5}, prony=prony)
    times, dev, g_R = cases.relaxation(visco, stretch=1.05, dt=0.73348 / 50, t_end=5 * 0.73348)
    _, dev_el, _ = cases.relaxation(Material("neo_hookean", visco.params, prony=(PronyTerm(1e-12, 1.0),)),
                                   stretch=1.05, dt=1.0, t_end=1.0)
    assert np.max(np.abs(dev[1:] / dev_el[-1] - g_R[1:])) <= 0.01


@pytest.mark.parametrize("bad", [
    {"law": "mooney"},
    {"law": "neo_hookean", "C10": -1.0, "D1": 1e-5},
    {"law": "ogden", "mu": [1.0], "alpha": [2.0, 3.0], "D": [1.0]},
    {"law": "neo_hookean", "C10": 1.0, "D1": 1e-5, "prony": [{"g": 1.2, "tau": 0.1}]},
])
def test_bad_material_is_one_line_config_error(bad):
    with pytest.raises(ConfigError) as e:
        material_from_config(bad)
    assert "\n" not in str(e.value) and "scene.material" in str(e.value)
