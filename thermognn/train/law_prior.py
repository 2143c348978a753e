"""The data's own hyperelastic law as a learned model's prior: the FE step itself, in torch, with
a fixed Newton budget (``model.prior_law``).

``thermognn.core.hyperelastic.HyperelasticSolid`` is the scene's solid on P1 cells in numpy: its
law (neo-Hookean or Ogden), the FE's Prony history per cell, the stored mass, Rayleigh damping and
Newmark rule, each step k Newton iterations from the predictor u0 + Δt v0 (docs/accuracy.md,
session 49: one iteration a step is within 1 % on the liver, two on the bunny, four on the shell).
:class:`HyperelasticNewmarkPrior` is that step in torch, so that ``train``, ``export`` and ``serve``
step it without dolfinx, with the remainders of :class:`thermognn.train.prior.NewmarkPrior`'s
contract: with G the internal-force remainder and H the stress's, a step solves, over the free DOFs,

    R(u1) = M a1 + αM M v1 + c (f_el(u1) − f_el(u0)) + f_int(u1; h0) − f1 − f_body
            − (1 + c) G1 + c G0 = 0,        c = βK / Δt                                   [N]

by k Newton iterations (each one linear solve of the exact tangent; the data's step when
converged and G = 0), and σ = σ_law(u) + H. f_el is the unrelaxed elastic force Σ_e V_e F S Grad φ
with S = S_iso + S_vol, f_int the relaxed one with S = S_vol + g∞ S_iso + Σ ḡ_i h_i (module
docstring of ``thermognn.core.hyperelastic``). With G = H = 0 and the budget spent it is the
budgeted FE model ``evaluate`` reports as "linearly implicit FE"; a network learns what the budget
leaves (G, H) on top of it.

The stresses are closed-form torch expressions (autograd of any order passes, TorchScript
compiles them): the neo-Hookean law's, and the Ogden law's isochoric stress as the exact
derivative of the FE's regularised trigonometric eigenvalues of C̄
(``thermognn.generate.materials.regularised_eigenvalues``), written out by the chain rule
(:func:`ogden_isochoric_pk2`; tests/test_law_prior.py checks it against the numpy law's
complex-step derivative). The tangent ∂P/∂F per cell is in closed form too: the neo-Hookean
law's (:func:`neo_hookean_tangent`) and Ogden's, the chain rule's differential line by line
(:func:`ogden_isochoric`, :func:`ogden_tangent`; the numpy laws take central differences). It is
held fixed in back-propagation: a rollout's gradients pass through each
iteration's residual and linear solve, not through its matrix (exact for a converged step's
dependence on the load and the remainders).

Two things make the step cheaper or safer without changing a step of the data (docs/accuracy.md,
session 51): a model step's two prior steps from the same start share the first iteration's start
and tangent factors (``first_iteration``), and an update that would crush or invert a cell
(J below min(0.05, half its start's)) is halved until it does not (``admissible``), so loads far
beyond the data's (a haptic tool's contact) give finite states. With ``tangent = "kept"``
(``model.prior_tangent``) a step taken without a gradient iterates with one tangent's factors kept
between iterations and steps, formed afresh only where they no longer contract
(``kept_iterations``; docs/model.md, "A kept tangent").
"""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from thermognn.core.hyperelastic import NeoHookean, Ogden
from thermognn.core.linear import LinearSolid

from .learned_law import StrainEnergy
from .mat3 import det3, det_inverse3, inverse3

from .prior import (BAND_MAX_SHARE, DISSECTION_MAX_SHARE, CorotatedNewmarkPrior, FactoredSolve, SparseSolve, _matrix,
                    _voigt, band_factor, band_layout, band_solve, dissection_factor, dissection_layout,
                    dissection_solve, lu_factor_each, lu_solves, sparse_factors)

#: the FE's regularisation of the deviatoric norm (``thermognn.generate.materials.EIGEN_EPS``)
EIGEN_EPS = 1.0e-6
#: the smallest cell volume ratio J a Newton update may leave (or half the smallest one it starts
#: from, if less): below it the update is halved (``admissible``), so that a sudden load (a haptic
#: tool's contact) cannot turn a cell inside out in one iteration; the data's cells stay far above
J_FLOOR = 0.05
#: halvings of an update at most
MAX_HALVINGS = 12
#: ``line_search``: an update shortened to s of itself is taken where it lowers the residual norm
#: by at least this share times s (Armijo's condition on ‖R‖)
LINE_SEARCH_DECREASE = 1.0e-4
#: ``line_search``: a step's Newton iterations start from its start u0 instead of the FE's predictor
#: u0 + Δt v0 where the residual there is below this share of the predictor's (a fast node's Δt v0
#: that crushes a cell: after the sim press's release, session 90)
REST_START_RATIO = 0.1
#: ``budget_loads``: the largest miss of a step's end it leaves, relative to the largest displacement
BUDGET_RTOL = 1.0e-10
#: ``budget_loads``: load corrections at most
BUDGET_CORRECTIONS = 30
#: ``max_iterations``: a step past its ``iterations`` stops once a Newton update moves no DOF by
#: more than this share of the step's largest displacement (the default of ``newton_rtol``,
#: ``model.prior_newton_rtol``; the data's FE: residual rtol 1e-8)
NEWTON_RTOL = 1.0e-8
#: ... or by less than this [m] (a body at rest, where the displacement gives no scale)
NEWTON_ATOL = 1.0e-14
#: ``step_cuts``: the FE's own floor of a cut step (``thermognn.generate.solid``'s
#: ``min_step_fraction`` 1/16): a step is halved at most this many times
MAX_STEP_CUTS = 4
#: ``substeps``: a step taken as at most 2^this sub-steps (the data's ``scene.time.substeps``)
MAX_SUBSTEP_LEVEL = 4
#: ... so these are the sub-steps a step can be taken as
SUBSTEPS = tuple(2 ** k for k in range(MAX_SUBSTEP_LEVEL + 1))
#: ``budget_loads``: corrections in a row that do not lower the miss before it gives up (the
#: shell's snap-through at 2 iterations a step: no load lands the step, docs/accuracy.md session 69)
BUDGET_STALLED = 3
#: ``set_hht``: HHT's α at most −1/3 (the range where it is unconditionally stable)
MAX_HHT = 1.0 / 3.0


def hht_applies(beta: float, gamma: float, beta_k: float) -> bool:
    """Whether HHT's dissipation (``set_hht``) modifies data stepped by Newmark's (β, γ) with
    stiffness-proportional Rayleigh damping βK [s]: only the undamped average-acceleration rule
    (β 1/4, γ 1/2, βK 0) is (``thermognn.train.checkpoint.served_law_hht`` asks it of a dataset)."""
    return beta == 0.25 and gamma == 0.5 and beta_k == 0.0


#: ``set_rule`` values: the data's Newmark rule (with ``set_hht``'s dissipation where set), or the
#: trapezoid with its step potential's discrete gradient (Simpson's rule)
RULES = ("newmark", "energy")
#: ``tangent`` values: a tangent formed at every Newton iteration, or one kept between iterations
#: and steps (chord iterations) and formed afresh only where it no longer contracts
TANGENTS = ("fresh", "kept")
#: ``tangent = "kept"``: an update with the kept tangent must leave a residual norm of at most this
#: share of the one it started from, else the tangent is formed afresh there and the update redone
#: (an update with a tangent formed where it starts is Newton's, and always taken)
KEPT_CONTRACTION = 0.5
#: ``anderson`` > 0: the most earlier chord updates an update is mixed with (Anderson's method on the
#: chord's fixed-point map; ``kept_iterations``), and the share of its start's residual norm such a
#: mixed update must leave before the tangent is formed afresh: the mixing converges where a plain
#: chord contracts slowly, so a tangent is formed less often (the liver's body under the sim press,
#: docs/accuracy.md session 102: 62 tangents formed in 150 steps where plain chords formed 158)
MAX_ANDERSON = 4
ANDERSON_CONTRACTION = 0.7


def _eye(F: Tensor) -> Tensor:
    return torch.eye(3, dtype=F.dtype, device=F.device)


def cofactor(B: Tensor) -> Tensor:
    """The cofactor matrix cof B = ∂ det B / ∂B [..., 3, 3] (= det B B⁻ᵀ where B is invertible;
    defined where it is not, as at F = I, where B = dev C̄ = 0)."""
    r0, r1, r2 = B[..., 0, :], B[..., 1, :], B[..., 2, :]
    return torch.stack([torch.linalg.cross(r1, r2), torch.linalg.cross(r2, r0), torch.linalg.cross(r0, r1)], -2)


def cofactor_differential(B: Tensor, dB: Tensor) -> Tensor:
    """d cof B [D, ..., 3, 3] along directions dB [D, ..., 3, 3] of B [..., 3, 3] (cof B's rows are
    cross products of B's other two rows, so each row's differential is two cross products)."""
    r0, r1, r2 = B[..., 0, :], B[..., 1, :], B[..., 2, :]
    d0, d1, d2 = dB[..., 0, :], dB[..., 1, :], dB[..., 2, :]
    r0, r1, r2 = r0.expand(d0.shape), r1.expand(d0.shape), r2.expand(d0.shape)
    return torch.stack([torch.linalg.cross(d1, r2) + torch.linalg.cross(r1, d2),
                        torch.linalg.cross(d2, r0) + torch.linalg.cross(r2, d0),
                        torch.linalg.cross(d0, r1) + torch.linalg.cross(r0, d1)], -2)


def neo_hookean_pk2(F: Tensor, c10: float, d1: float) -> Tuple[Tensor, Tensor]:
    """(S_iso, S_vol) [..., 3, 3] Pa of Ψ = C10 (J^(-2/3) I1 − 3) + (J − 1)²/D1 at deformation
    gradients F [..., 3, 3]: S_iso = 2 C10 J^(-2/3) (I − I1/3 C⁻¹), S_vol = (2/D1)(J − 1) J C⁻¹."""
    C = F.transpose(-1, -2) @ F
    Ci = inverse3(C)
    J = det3(F)[..., None, None]
    I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    s_iso = 2.0 * c10 * J.pow(-2.0 / 3.0) * (_eye(F) - I1 / 3.0 * Ci)
    return s_iso, 2.0 / d1 * (J - 1.0) * J * Ci


def ogden_isochoric_pk2(C: Tensor, mu: List[float], alpha: List[float], eps: float = EIGEN_EPS) -> Tensor:
    """S_iso = 2 ∂Ψ_iso/∂C [..., 3, 3] Pa of the Ogden law Ψ_iso = Σ_i 2 μ_i/α_i² (Σ_a λ̄_a^α_i − 3)
    with the FE's regularised eigenvalues λ̄_a² of C̄ = J^(-2/3) C (C [..., 3, 3]):
    :func:`ogden_isochoric` without directions."""
    return ogden_isochoric(C, mu, alpha, eps, None)[0]


def ogden_isochoric(C: Tensor, mu: List[float], alpha: List[float], eps: float,
                    dC: Optional[Tensor]) -> Tuple[Tensor, Optional[Tensor]]:
    """(S_iso [..., 3, 3] Pa, its derivatives dS_iso [D, ..., 3, 3] Pa along the D directions dC
    [D, ..., 3, 3] of C, or None without them) of the Ogden law
    Ψ_iso = Σ_i 2 μ_i/α_i² (Σ_a λ̄_a^α_i − 3) with the FE's regularised eigenvalues λ̄_a² of
    C̄ = J^(-2/3) C (C [..., 3, 3]):

        m = tr C̄ / 3,  B = C̄ − m I,  p = sqrt(B:B/6 + ε²),  r = det B / (2 p³) (clipped to [−1, 1]),
        φ = arccos(r)/3,  λ̄_k² = m + 2 p cos(φ + 2πk/3)

    differentiated by the chain rule: ∂Ψ/∂λ̄_k² = Σ_i μ_i/α_i λ̄_k^(α_i − 2); through m (I/3), p
    (B/(6p)), r (cof B/(2p³) and −3r/p through p) and φ (−1/(3 sqrt(1 − r²)), zero where r is
    clipped, as the FE's max/min is flat there); then ∂Ψ/∂C = a (Ψ_C̄ − (Ψ_C̄ : C)/3 C⁻¹),
    a = J^(-2/3). The derivatives (the tangent's, as UFL differentiates the FE's form twice) take
    the differential of each line of that chain in turn, ``d`` before its name."""
    eye = _eye(C)
    detC, Ci = det_inverse3(C)
    a = detC.pow(-1.0 / 3.0)[..., None, None]                                      # J^(-2/3)
    Cb = a * C
    m = Cb.diagonal(dim1=-2, dim2=-1).sum(-1) / 3.0                                   # [...]
    B = Cb - m[..., None, None] * eye
    p = torch.sqrt((B * B).sum((-2, -1)) / 6.0 + eps * eps)                          # [...]
    cof_B = cofactor(B)
    r = (B * cof_B).sum((-2, -1)) / 3.0 / (2.0 * p**3)                               # det B = B : cof B / 3
    inside = (r > -1.0) & (r < 1.0)
    rc = torch.clamp(r, -1.0, 1.0)
    phi = torch.acos(rc) / 3.0
    psi_m = torch.zeros_like(m)
    psi_p = torch.zeros_like(m)
    psi_phi = torch.zeros_like(m)
    thetas: List[Tensor] = []
    l2s: List[Tensor] = []
    ds: List[Tensor] = []
    for k in range(3):
        theta = phi + 2.0 * math.pi * k / 3.0
        l2 = m + 2.0 * p * torch.cos(theta)                                           # λ̄_k²
        d = torch.zeros_like(m)
        for mu_i, alpha_i in zip(mu, alpha):
            d = d + mu_i / alpha_i * l2.pow(alpha_i / 2.0 - 1.0)                      # ∂Ψ/∂λ̄_k²
        psi_m = psi_m + d
        psi_p = psi_p + 2.0 * d * torch.cos(theta)
        psi_phi = psi_phi - 2.0 * p * d * torch.sin(theta)
        thetas.append(theta)
        l2s.append(l2)
        ds.append(d)
    one_r2 = torch.clamp(1.0 - rc * rc, min=1e-300)
    dphi_dr = torch.where(inside, -1.0 / (3.0 * torch.sqrt(one_r2)), torch.zeros_like(rc))
    psi_r = psi_phi * dphi_dr
    psi_pr = psi_p - 3.0 * psi_r * rc / p                                              # r's own p
    psi_B = (psi_pr / (6.0 * p))[..., None, None] * B + (psi_r / (2.0 * p**3))[..., None, None] * cof_B
    tr_B = psi_B.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    psi_Cb = (psi_m / 3.0)[..., None, None] * eye + psi_B - tr_B / 3.0 * eye          # I/3 Ψ_m + dev Ψ_B
    inner = (psi_Cb * C).sum((-2, -1))[..., None, None]
    S = 2.0 * a * (psi_Cb - inner / 3.0 * Ci)
    if dC is None:
        return S, None
    # the differentials along dC [D, ..., 3, 3]; scalars [D, ...], matrices [D, ..., 3, 3]
    dCi = -Ci @ dC @ Ci
    da = -a / 3.0 * (Ci.transpose(-1, -2) * dC).sum((-2, -1))[..., None, None]       # d det C = det C Ci : dCᵀ
    dCb = da * C + a * dC
    dm = dCb.diagonal(dim1=-2, dim2=-1).sum(-1) / 3.0
    dB = dCb - dm[..., None, None] * eye
    dp = (B * dB).sum((-2, -1)) / (6.0 * p)
    dcof_B = cofactor_differential(B, dB)
    dr = torch.where(inside, (cof_B * dB).sum((-2, -1)) / (2.0 * p**3) - 3.0 * r * dp / p, torch.zeros_like(dp))
    dphi = dphi_dr * dr
    # d(dφ/dr)/dr = −r / (3 (1 − r²)^(3/2)) inside, 0 where clipped
    ddphi_dr = torch.where(inside, -rc / (3.0 * one_r2 * torch.sqrt(one_r2)), torch.zeros_like(rc)) * dr
    dpsi_m = torch.zeros_like(dm)
    dpsi_p = torch.zeros_like(dm)
    dpsi_phi = torch.zeros_like(dm)
    for k in range(3):
        cos_t, sin_t, l2, d = torch.cos(thetas[k]), torch.sin(thetas[k]), l2s[k], ds[k]
        dl2 = dm + 2.0 * dp * cos_t - 2.0 * p * sin_t * dphi
        dd = torch.zeros_like(dl2)
        for mu_i, alpha_i in zip(mu, alpha):
            dd = dd + mu_i / alpha_i * (alpha_i / 2.0 - 1.0) * l2.pow(alpha_i / 2.0 - 2.0) * dl2
        dpsi_m = dpsi_m + dd
        dpsi_p = dpsi_p + 2.0 * (dd * cos_t - d * sin_t * dphi)
        dpsi_phi = dpsi_phi - 2.0 * (dp * d * sin_t + p * dd * sin_t + p * d * cos_t * dphi)
    dpsi_r = dpsi_phi * dphi_dr + psi_phi * ddphi_dr
    dpsi_pr = dpsi_p - 3.0 * (dpsi_r * rc + psi_r * dr - psi_r * rc * dp / p) / p
    dpsi_B = ((dpsi_pr / (6.0 * p) - psi_pr * dp / (6.0 * p * p))[..., None, None] * B
              + (psi_pr / (6.0 * p))[..., None, None] * dB
              + (dpsi_r / (2.0 * p**3) - 1.5 * psi_r * dp / p**4)[..., None, None] * cof_B
              + (psi_r / (2.0 * p**3))[..., None, None] * dcof_B)
    dtr_B = dpsi_B.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
    dpsi_Cb = (dpsi_m / 3.0)[..., None, None] * eye + dpsi_B - dtr_B / 3.0 * eye
    dinner = (dpsi_Cb * C + psi_Cb * dC).sum((-2, -1))[..., None, None]
    dS = 2.0 * da * (psi_Cb - inner / 3.0 * Ci) + 2.0 * a * (dpsi_Cb - dinner / 3.0 * Ci - inner / 3.0 * dCi)
    return S, dS


def ogden_isochoric_energy(C: Tensor, mu: List[float], alpha: List[float], eps: float = EIGEN_EPS) -> Tensor:
    """Ψ_iso = Σ_i 2 μ_i/α_i² (Σ_a λ̄_a^α_i − 3) [...] J/m³ of C [..., 3, 3], with the FE's regularised
    eigenvalues of C̄ (:func:`ogden_isochoric`'s first lines): the energy whose 2 ∂/∂C is its S_iso."""
    a = det3(C).pow(-1.0 / 3.0)[..., None, None]                                   # J^(-2/3)
    Cb = a * C
    m = Cb.diagonal(dim1=-2, dim2=-1).sum(-1) / 3.0
    B = Cb - m[..., None, None] * _eye(C)
    p = torch.sqrt((B * B).sum((-2, -1)) / 6.0 + eps * eps)
    r = torch.clamp((B * cofactor(B)).sum((-2, -1)) / 3.0 / (2.0 * p**3), -1.0, 1.0)
    phi = torch.acos(r) / 3.0
    psi = torch.zeros_like(m)
    for i in range(len(mu)):
        stretches = torch.zeros_like(m)
        for k in range(3):
            stretches = stretches + (m + 2.0 * p * torch.cos(phi + 2.0 * math.pi * k / 3.0)).pow(alpha[i] / 2.0)
        psi = psi + 2.0 * mu[i] / (alpha[i] * alpha[i]) * (stretches - 3.0)
    return psi


def ogden_volumetric_energy(J: Tensor, d: List[float]) -> Tensor:
    """U = Σ_i (J − 1)^(2i)/D_i [...] J/m³ (i from 1) of volume ratios J [...]."""
    U = torch.zeros_like(J)
    for i in range(len(d)):
        U = U + (J - 1.0).pow(2 * (i + 1)) / d[i]
    return U


def ogden_volumetric_pk2(F: Tensor, C: Tensor, d: List[float]) -> Tensor:
    """S_vol = U'(J) J C⁻¹ [..., 3, 3] Pa of U = Σ_i (J − 1)^(2i)/D_i (i from 1)."""
    J = det3(F)[..., None, None]
    dU = torch.zeros_like(J)
    for i, di in enumerate(d):
        dU = dU + 2.0 * (i + 1) * (J - 1.0).pow(2 * i + 1) / di
    return dU * J * inverse3(C)


def neo_hookean_tangent(F: Tensor, c10: float, d1: float, w_iso: float, w_vol: float,
                        extra: Optional[Tensor]) -> Tensor:
    """∂P/∂F [..., 3, 3, 3, 3] Pa (P_ij by F_kl) of P = F (w_vol S_vol + w_iso S_iso + extra) with
    the neo-Hookean law (:func:`neo_hookean_pk2`) at deformation gradients F [..., 3, 3], in closed
    form (the numpy law's ``NeoHookean.pk1_tangent``, as UFL differentiates the FE's form). With
    G = F⁻ᵀ, a = J^(-2/3), I1 = F : F, k = 2/D1 and ``extra`` [..., 3, 3] Pa a stress constant in F:

        F S_iso = 2 C10 a (F − I1/3 G),  F S_vol = k (J − 1) J G,
        ∂G_ij/∂F_kl = −G_il G_kj,  ∂J/∂F_kl = J G_kl,  ∂a/∂F_kl = −2/3 a G_kl,  ∂I1/∂F_kl = 2 F_kl,

        ∂P_ij/∂F_kl = w_iso 2 C10 a (δ_ik δ_jl − 2/3 G_kl (F_ij − I1/3 G_ij) − 2/3 G_ij F_kl
                                     + I1/3 G_il G_kj)
                      + w_vol k ((2J − 1) J G_ij G_kl − (J − 1) J G_il G_kj) + δ_ik extra_lj."""
    eye = _eye(F)
    detF, Fi = det_inverse3(F)
    G = Fi.transpose(-1, -2)                                                           # F⁻ᵀ
    J = detF[..., None, None, None, None]
    I1 = (F * F).sum((-2, -1))[..., None, None, None, None]
    a = J.pow(-2.0 / 3.0)
    k = 2.0 / d1
    Gij_Gkl = G[..., :, :, None, None] * G[..., None, None, :, :]                       # [..., i, j, k, l]
    Gil_Gkj = G[..., :, None, None, :] * G.transpose(-1, -2)[..., None, :, :, None]    # G_il G_kj
    dik_djl = eye[:, None, :, None] * eye[None, :, None, :]
    iso = dik_djl - 2.0 / 3.0 * (G[..., None, None, :, :] * F[..., :, :, None, None]
                                 + G[..., :, :, None, None] * F[..., None, None, :, :]) \
        + 2.0 / 9.0 * I1 * Gij_Gkl + I1 / 3.0 * Gil_Gkj
    A = (w_iso * 2.0 * c10) * a * iso + (w_vol * k) * ((2.0 * J - 1.0) * J * Gij_Gkl - (J - 1.0) * J * Gil_Gkj)
    if extra is not None:
        A = A + eye[:, None, :, None] * extra.transpose(-1, -2)[..., None, :, None, :]
    return A


def symmetric_index() -> Tuple[List[int], List[int]]:
    """(rows, columns) of a symmetric 3×3 matrix's six entries: the diagonal, then above it."""
    return [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]


def symmetric_directions(like: Tensor) -> Tensor:
    """The unit directions of symmetric 3×3 matrices [6, 3, 3], as ``like``: E_cc, then
    E_cd + E_dc (c < d), in ``symmetric_index``'s order (a symmetric C = Σ C_cd E_(cd) over them)."""
    rows, columns = symmetric_index()
    E = like.new_zeros(6, 3, 3)
    for n in range(6):
        E[n, rows[n], columns[n]] = 1.0
        E[n, columns[n], rows[n]] = 1.0
    return E


def ogden_tangent(F: Tensor, mu: List[float], alpha: List[float], d: List[float], w_iso: float, w_vol: float,
                  extra: Optional[Tensor], eps: float = EIGEN_EPS) -> Tensor:
    """∂P/∂F [..., 3, 3, 3, 3] Pa (P_ij by F_kl) of P = F (w_vol S_vol + w_iso S_iso + extra) with
    the Ogden law (:func:`ogden_isochoric`, :func:`ogden_volumetric_pk2`) at deformation gradients
    F [..., 3, 3], in closed form (``extra`` [..., 3, 3] Pa a stress constant in F). S's
    derivatives along C's six symmetric directions E (``symmetric_directions``) give, with
    dC = E_klᵀ F + Fᵀ E_kl for F's direction E_kl (entries δ_cl F_kd + F_kc δ_dl),

        ∂P_ij/∂F_kl = δ_ik S_lj + Σ_(c≤d) (δ_cl F_kd + F_kc δ_dl) (F ∂S/∂E_cd)_ij,
        ∂S_vol/∂E = (U'' J + U') dJ C⁻¹ − U' J C⁻¹ E C⁻¹,  dJ = J/2 C⁻¹ : E."""
    C = F.transpose(-1, -2) @ F
    E = symmetric_directions(F).reshape([6] + [1] * (F.dim() - 2) + [3, 3])               # [6, ..., 3, 3]
    S_iso, dS_iso = ogden_isochoric(C, mu, alpha, eps, E)
    assert dS_iso is not None
    Ci = inverse3(C)
    J = det3(F)[..., None, None]
    dU = torch.zeros_like(J)                                                           # U'(J) Pa
    ddU = torch.zeros_like(J)                                                          # U''(J) Pa
    for i, di in enumerate(d):
        dU = dU + 2.0 * (i + 1) * (J - 1.0).pow(2 * i + 1) / di
        ddU = ddU + 2.0 * (i + 1) * (2 * i + 1) * (J - 1.0).pow(2 * i) / di
    S_vol = dU * J * Ci
    dJ = 0.5 * J * (Ci * E).sum((-2, -1))[..., None, None]                            # [6, ..., 1, 1]
    dS_vol = (ddU * J + dU) * dJ * Ci - dU * J * (Ci @ E @ Ci)
    S = w_vol * S_vol + w_iso * S_iso
    if extra is not None:
        S = S + extra
    return pk1_tangent(F, S, w_vol * dS_vol + w_iso * dS_iso)


def pk1_tangent(F: Tensor, S: Tensor, dS: Tensor) -> Tensor:
    """∂P/∂F [..., 3, 3, 3, 3] Pa (P_ij by F_kl) of P = F S at F [..., 3, 3], from S [..., 3, 3] Pa
    and its derivatives dS [6, ..., 3, 3] Pa along C's six symmetric directions
    (``symmetric_directions``; :func:`ogden_tangent`'s formula, for any law of C)."""
    FdS = (F @ dS).movedim(0, -1)                                                      # [..., i, j, 6]
    eye = _eye(F)
    index = symmetric_index()
    rows, columns = torch.tensor(index[0], device=F.device), torch.tensor(index[1], device=F.device)
    # dC's coefficients [..., k, l, 6]: δ_cl F_kd + F_kc δ_dl
    coefficient = (F.index_select(-1, columns)[..., :, None, :] * eye.index_select(0, rows).transpose(0, 1)
                   + F.index_select(-1, rows)[..., :, None, :] * eye.index_select(0, columns).transpose(0, 1))
    A = torch.einsum("...ijn,...kln->...ijkl", FdS, coefficient)
    return A + eye[:, None, :, None] * S.transpose(-1, -2)[..., None, :, None, :]


def learned_tangent(law: StrainEnergy, F: Tensor, w_iso: float, w_vol: float, extra: Optional[Tensor]) -> Tensor:
    """∂P/∂F [..., 3, 3, 3, 3] Pa of P = F (w_vol S_vol + w_iso S_iso + extra) with the learned law
    ``law`` (:class:`thermognn.train.learned_law.StrainEnergy`) at F [..., 3, 3]: its stress in
    closed form, and its derivatives along C's directions (``pk2_differentials``, which gives both)."""
    C = F.transpose(-1, -2) @ F
    E = symmetric_directions(F).reshape([6] + [1] * (F.dim() - 2) + [3, 3])               # [6, ..., 3, 3]
    S_iso, S_vol, dS_iso, dS_vol = law.pk2_differentials(C, E)
    S = w_vol * S_vol + w_iso * S_iso
    if extra is not None:
        S = S + extra
    return pk1_tangent(F, S, w_vol * dS_vol + w_iso * dS_iso)


class HyperelasticNewmarkPrior(CorotatedNewmarkPrior):
    """The scene's hyperelastic FE step with ``iterations`` Newton iterations (module docstring)
    over the n free DOFs of an N-node P1 mesh (X [N, 3] m, tets [T, 4]); the law ``law``
    (``thermognn.core.hyperelastic``'s ``NeoHookean`` or ``Ogden``, as ``law_from_config`` reads
    the dataset's ``scene.material``), the mass, Rayleigh damping, Newmark β, γ and the Prony terms of ``linear``
    (the dataset's ``/linear``; a viscous solid relaxes always, as its FE does).

    It keeps :class:`CorotatedNewmarkPrior`'s cell bookkeeping and solves (sparse LU on the CPU;
    on a GPU and in TorchScript dense and batched, or block-tridiagonal where the reordered mesh is
    thin, or by one level of nested dissection where that is cheaper than dense: ``set_band``)
    and its per-cell internal variables: per Prony term i and cell e the FE's history h_i,e (S_iso
    seen through exp(−t/τ_i), Voigt, Pa), packed into nodal columns ``prony_cells_i`` of a carried
    state. lam, mu [Pa] (the moduli at rest) only size the base class's unused linear cell
    stiffness."""

    __jit_ignored_attributes__ = ["_start_memo", "_kept_lus"]
    # constants of the scripted step: TorchScript resolves a branch on a constant as it compiles, so
    # a scripted step holds its own law's, rule's and tangent's code alone (a neo-Hookean step:
    # 34,563 graph nodes inlined instead of 233,563, and the graph executor's one-off optimisation
    # of it 10 s instead of 162 s here; docs/accuracy.md, session 100). Set before scripting (the
    # constructors, ``set_rule``).
    __constants__ = ["ogden", "learned", "energy_rule", "kept_tangent", "n_terms"]

    def __init__(self, linear: LinearSolid, n_nodes: int, dt: float, X: np.ndarray, tets: np.ndarray,
                 lam: float, mu: float, law: NeoHookean | Ogden | StrainEnergy, iterations: int = 1,
                 max_iterations: Optional[int] = None, newton_rtol: Optional[float] = None,
                 step_cuts: int = 0, tangent: str = "fresh", line_search: int = 0, hht: float = 0.0,
                 rule: str = "newmark", substeps: int = 1, anderson: int = 0,
                 dtype: torch.dtype = torch.float64) -> None:
        if not isinstance(law, (NeoHookean, Ogden, StrainEnergy)):
            raise ValueError(f"the law prior steps a NeoHookean, Ogden or learned law, not {law!r}")
        if int(iterations) < 1:
            raise ValueError(f"the law prior's Newton iterations a step: {iterations!r}, expected >= 1")
        newton_rtol = NEWTON_RTOL if newton_rtol is None else newton_rtol
        if not float(newton_rtol) > 0.0:
            raise ValueError(f"the law prior's Newton tolerance: {newton_rtol!r}, expected > 0")
        if max_iterations is not None and int(max_iterations) < int(iterations):
            raise ValueError(f"the law prior's most Newton iterations a step: {max_iterations!r}, expected >= "
                             f"its iterations ({iterations})")
        if not 0 <= int(step_cuts) <= MAX_STEP_CUTS or (int(step_cuts) > 0 and not (
                max_iterations is not None and int(max_iterations) > int(iterations))):
            raise ValueError(f"the law prior's step cuts: {step_cuts!r}, expected 0 to {MAX_STEP_CUTS}, and more "
                             f"than 0 only with max_iterations > iterations (a step it can tell has not converged)")
        if tangent not in TANGENTS or (tangent == "kept" and not (
                max_iterations is not None and int(max_iterations) > int(iterations))):
            raise ValueError(f"the law prior's tangent: {tangent!r}, expected one of {' | '.join(TANGENTS)}, and kept "
                             f"only with max_iterations > iterations (a tolerance ends each step)")
        if isinstance(anderson, bool) or not 0 <= int(anderson) <= MAX_ANDERSON or (int(anderson) > 0
                                                                                    and tangent != "kept"):
            raise ValueError(f"the law prior's Anderson mixing: {anderson!r}, expected 0 (none) to {MAX_ANDERSON} "
                             f"earlier chord updates, and more than 0 only with the tangent kept")
        if isinstance(substeps, bool) or int(substeps) not in SUBSTEPS:
            raise ValueError(f"the law prior's sub-steps: {substeps!r}, expected one of {list(SUBSTEPS)} (the data's "
                             f"scene.time.substeps)")
        if isinstance(line_search, bool) or not 0 <= int(line_search) <= MAX_HALVINGS:
            raise ValueError(f"the law prior's line search: {line_search!r}, expected 0 (none) to {MAX_HALVINGS} "
                             f"halvings of a Newton update")
        super().__init__(linear, n_nodes, dt, X, tets, lam, mu, sweeps=1, dtype=dtype, relax=bool(linear.prony))
        self.iterations = int(iterations)
        # a Newton update shortened by up to this many halvings where it does not lower the
        # residual norm (``searched_iterate``); 0: every update taken whole (``iterate``)
        self.line_search, self.line_search_decrease = int(line_search), LINE_SEARCH_DECREASE
        self.rest_start_ratio = REST_START_RATIO
        # past ``iterations``, more (up to this many) while the last update still moved the state
        # by more than ``newton_rtol`` of its largest displacement (``step``); equal: a fixed budget
        self.max_iterations = int(max_iterations) if max_iterations is not None else self.iterations
        self.newton_rtol, self.newton_atol = float(newton_rtol), NEWTON_ATOL
        self.ogden = isinstance(law, Ogden)
        # ``model.prior_material = learned``: the law is a fitted strain energy (its weights in the
        # state_dict); otherwise a placeholder of it that is never evaluated (TorchScript types both)
        self.learned = isinstance(law, StrainEnergy)
        self.learned_law = law if isinstance(law, StrainEnergy) else StrainEnergy((1, 1), placeholder=True)
        if isinstance(law, Ogden):
            self.ogden_mu, self.ogden_alpha, self.ogden_d = list(law.mu), list(law.alpha), list(law.d)
        else:
            # unused; non-empty so that TorchScript types them List[float]
            self.ogden_mu, self.ogden_alpha, self.ogden_d = [0.0], [1.0], [1.0]
            if isinstance(law, NeoHookean):
                self.c10, self.d1 = law.c10, law.d1
        # S_iso's weight in a relaxing step: g∞ + Σ ḡ_i w_i (1 elastic)
        self.iso_weight = 1.0 - self._shrink()
        # a step that has not converged after ``max_iterations`` is stepped again as two halves, each
        # cut again where it does not converge, down to Δt / 2^step_cuts (``step``), as the FE cuts
        # its steps (``thermognn.generate.solid``): per level k (a sub-step Δt / 2^k) the constants
        # that depend on Δt, which ``use_level`` puts in place (level 0: the step's own, to the bit)
        self.step_cuts = int(step_cuts)
        # ``substeps`` 2^L: every step taken as that many sub-steps of Δt / 2^L (level L), its loads
        # and remainders linear between the step's, as the data's FE took it (``scene.time.substeps``:
        # the FE's own rule, so the law follows data solved finer than their stored Δt); each cut
        # again down to level L + step_cuts where it does not converge (``cut_step``)
        self.substeps, self.sub_level = int(substeps), int(substeps).bit_length() - 1
        self.beta_k = float(linear.rayleigh[1])
        # the Newmark rule of the data (β = 1/4, γ = 1/2, the FE's) with HHT's numerical
        # dissipation ``hht`` (``set_hht``; 0: the data's rule, to the bit)
        self.hht, self.mass_scale = 0.0, 1.0
        # ``set_rule("energy")``: the trapezoid with its step potential's discrete gradient, and
        # the step start that needs (``rule_start``: u0 [B, n] m, the Prony history's stress of
        # the step [B, T, 3, 3] Pa (empty elastic), the step's internal force at u0 [B, n] N)
        self.energy_rule = False
        for name in ("rule_u0", "rule_extra", "rule_force0"):
            self.register_buffer(name, torch.zeros(0, dtype=dtype), persistent=False)
        self.newmark_beta, self.newmark_gamma = self.beta, self.gamma
        # per level [Δt s, c, c0, mass_factor, iso_weight]
        self.level_constants: List[List[float]] = [[self.dt, self.c, self.c0, self.mass_factor, self.iso_weight]]
        decay, increment = [self.prony_decay], [self.prony_increment]                      # [T_p] each
        for k in range(1, self.sub_level + self.step_cuts + 1):
            h = self.dt / 2 ** k
            terms = linear.relaxation(h) if self.n_terms else []          # [(ḡ_i, d_i, w_i)]
            self.level_constants.append([h, self.beta_k / h, 1.0 / (self.beta * h**2),
                                         1.0 + self.alpha_m * self.gamma * h,
                                         1.0 - sum(g * (1.0 - w) for g, _, w in terms)])
            decay.append(torch.tensor([d for _, d, _ in terms], dtype=torch.float64).to(dtype))
            increment.append(torch.tensor([w for _, _, w in terms], dtype=torch.float64).to(dtype))
        self.register_buffer("level_decay", torch.stack(decay), persistent=False)             # [levels, T_p]
        self.register_buffer("level_increment", torch.stack(increment), persistent=False)     # [levels, T_p]
        self.j_floor, self.max_halvings = J_FLOOR, MAX_HALVINGS
        # ``tangent = "kept"``: steps taken without a gradient (serve, evaluate, validation) iterate
        # with one tangent's factors kept between iterations and steps (``kept_iterations``): the
        # dense path's in kept_* (``factor``'s six), the eager CPU's sparse LUs in _kept_lus, for a
        # batch of kept_batch samples (0: none kept); training's steps form theirs as "fresh"
        self.kept_tangent = tangent == "kept"
        # ``anderson`` > 0: each chord update mixed with up to that many earlier ones of the step
        # (``anderson_update``), and a fresh tangent formed only where a mixed update leaves more
        # than ANDERSON_CONTRACTION of its start's residual norm
        self.anderson = int(anderson)
        self.kept_contraction = ANDERSON_CONTRACTION if self.anderson > 0 else KEPT_CONTRACTION
        self.kept_batch = 0
        self._kept_lus: list = []
        self._start_memo = None         # eager CPU: the last step start and its factors (``_eager_first_iteration``)
        # dense path without gradients (TorchScript, serve): the last step start, by value, and its
        # LU factors (``first_iteration``); empty until a step sets them. memo_law_*: the last F the
        # law met without a gradient and its (S_iso, S_vol) (``law``; eager too); memo_cells_*: the last
        # displacements ``cells`` met without a gradient (a copy) and their F
        for name in ("memo_key", "memo_predictor", "memo_S_iso0", "memo_extra", "memo_damping0", "memo_u1",
                     "memo_internal", "memo_lu", "memo_law_F", "memo_law_S_iso", "memo_law_S_vol",
                     "memo_cells_u", "memo_cells_F"):
            self.register_buffer(name, torch.zeros(0, dtype=dtype), persistent=False)
        self.register_buffer("memo_pivots", torch.zeros(0, dtype=torch.int32), persistent=False)
        # ... and the rest of ``factor``'s factors: the block-tridiagonal factor's X and lower blocks
        # (the dissection's W and couplings A_s), the dissection separator's Schur complement's LU
        self.register_buffer("memo_band_X", torch.zeros(0, dtype=dtype), persistent=False)
        self.register_buffer("memo_band_L", torch.zeros(0, dtype=dtype), persistent=False)
        self.register_buffer("memo_sep_lu", torch.zeros(0, dtype=dtype), persistent=False)
        self.register_buffer("memo_sep_pivots", torch.zeros(0, dtype=torch.int32), persistent=False)
        # ... and where its last step started (u0, v0, a0, h0 flat), ended (u1 [B, n] m), and its
        # chord's last contraction ρ [B] (0: none): a model step's second prior step starts there
        for name in ("kept_lu", "kept_band_X", "kept_band_L", "kept_sep_lu", "kept_from", "kept_end", "kept_rate"):
            self.register_buffer(name, torch.zeros(0, dtype=dtype), persistent=False)
        for name in ("kept_pivots", "kept_sep_pivots"):
            self.register_buffer(name, torch.zeros(0, dtype=torch.int32), persistent=False)
        self.set_band(BAND_MAX_SHARE, DISSECTION_MAX_SHARE)
        # how many updates ``admissible`` has shortened (samples x updates), since it was last zeroed:
        # where the budget does not hold a step (evaluate names such rollouts)
        self.register_buffer("shortened", torch.zeros((), dtype=torch.int64), persistent=False)
        # ... and how many the line search has (``line_search``)
        self.register_buffer("searched", torch.zeros((), dtype=torch.int64), persistent=False)
        # since they were last zeroed: the Newton iterations taken (a batch's step counts once, its
        # sub-steps' all), the steps taken, the steps that spent ``max_iterations`` > ``iterations``
        # and still moved (cut: at Δt / 2^step_cuts), and the steps cut into sub-steps: what the
        # most spent, and where it did not converge (evaluate reports them)
        self.register_buffer("newton_taken", torch.zeros(4, dtype=torch.int64), persistent=False)
        # since it was last zeroed: how many times a batch's tangent was formed (``tangent_pairs``):
        # once a Newton iteration with "fresh" tangents (a kept step start's once for both of a
        # model step's prior steps), only where it no longer contracts with "kept"
        self.register_buffer("tangents_formed", torch.zeros((), dtype=torch.int64), persistent=False)
        if hht:
            self.set_hht(hht)
        if rule != "newmark":
            self.set_rule(rule)

    @torch.jit.unused
    def set_rule(self, rule: str) -> None:
        """How a step is integrated in time: ``"newmark"`` (the data's average-acceleration rule,
        with ``set_hht``'s dissipation where set) or ``"energy"``: the same trapezoid,
        u1 − u0 = Δt (v0 + v1)/2, M (v1 − v0)/Δt = (f0 + f1)/2 − f̄_int, with the internal force's
        trapezoid (f_int(u0) + f_int(u1))/2 corrected by a discrete gradient (Gonzalez 1996) of the
        step's potential Π (the law's energy with the step's S_iso weight and its Prony history's
        stress, whose gradient is the step's f_int), so that within a step Π(u1) − Π(u0) is the
        work of the force that moves the body there (to Simpson's rule's fifth order in Δu:
        ``discrete_gradient``). Per sample, with Δu = u1 − u0 and the mass matrix as metric, the
        correction is

            e M Δu / (Δuᵀ M Δu),  e = Π(u1) − Π(u0) − (∇Π(u0) + ∇Π(u1))/2 · Δu,

        e the trapezoid's error on Π (zero for a quadratic energy, of third order in Δu
        otherwise). The average-acceleration rule conserves a linear body's energy, not a
        stiffening law's: the liver's learned law rang up after a release of the sim press (its
        energy 0.032 → 0.071 J in 35 unloaded steps), and does not with this rule (0.030 →
        0.026 J, as with Newmark sub-steps of Δt/4). It is not the data's rule: the liver's test
        split moves from whole v 0.563 % to 1.85 % (docs/accuracy.md, session 91). The carried
        acceleration is the end's own, M a1 = f1 − f_int(u1) (``end_rates``), so the next step's
        trapezoid starts from its start's forces as the data's does. Its tangent is the plain
        one (e's own derivative left out: about 15 % more Newton iterations on the liver, the
        converged step exact). Needs the data's β 1/4, γ 1/2, no Rayleigh damping and no HHT
        dissipation; steps without gradients only (rollouts, export, serve)."""
        if rule not in RULES:
            raise ValueError(f"the law prior's time rule: {rule!r}, expected one of {' | '.join(RULES)}")
        if rule == "energy" and (self.beta_k != 0.0 or self.alpha_m != 0.0 or self.hht != 0.0
                                 or self.newmark_beta != 0.25 or self.newmark_gamma != 0.5):
            raise ValueError(f"the law prior's energy rule needs the data's average-acceleration Newmark rule "
                             f"(β 1/4, γ 1/2, here {self.newmark_beta}, {self.newmark_gamma}) without Rayleigh "
                             f"damping (αM {self.alpha_m}, βK {self.beta_k}) or HHT dissipation ({self.hht})")
        self.energy_rule = rule == "energy"
        self.forget()

    def rule_start(self, u0: Tensor, F0: Tensor, extra: Optional[Tensor]) -> None:
        """Keep a step's start u0 [B, n] m (its cells' F0, the step's history stress ``extra``) for
        ``discrete_gradient``: u0 and the step's internal force there, ∇Π(u0) [B, n] N. Called by
        ``step_origin``, and again where a step's start is reused from a memo (a sub-step's may
        have been kept since)."""
        self.rule_u0 = u0
        self.rule_extra = extra if extra is not None else u0.new_zeros(0)
        self.rule_force0 = self.assemble(self.pk1(F0, self.iso_weight, 1.0, extra))

    def discrete_gradient(self, u1: Tensor, force1: Tensor) -> Tensor:
        """2 e M Δu / (Δuᵀ M Δu) [B, n] N of a step's end u1 [B, n] m (the step's
        internal force there ∇Π(u1) [B, n] N), from the start ``rule_start`` kept: what the energy
        rule adds to the trapezoid's residual (which is the trapezoid's equation times 2). e is
        the trapezoid's error on the step potential's change, Π(u1) − Π(u0) − (∇Π(u0) + ∇Π(u1))/2
        · Δu, with Π's change by Simpson's rule along Δu, (∇Π(u0) + 4 ∇Π(u_mid) + ∇Π(u1))/6 · Δu:
        e = 2/3 (∇Π(u_mid) − (∇Π(u0) + ∇Π(u1))/2) · Δu, exact for a cubic Π, of fifth order in Δu
        otherwise, and free of the round-off a difference of energies has (a body near rest: Π
        1e-13 J, its evaluations 1e-16 J apart). Zero where the step has not moved."""
        extra: Optional[Tensor] = None
        if self.n_terms > 0:
            extra = self.rule_extra
        du = u1 - self.rule_u0                                                            # [B, n] m
        middle = self.assemble(self.pk1(self.cells(self.rule_u0 + 0.5 * du), self.iso_weight, 1.0, extra))
        e = (2.0 / 3.0) * ((middle - 0.5 * (self.rule_force0 + force1)) * du).sum(1, keepdim=True)   # [B, 1] J
        Mdu = self.mass(du)
        norm = (du * Mdu).sum(1, keepdim=True)                                            # [B, 1] kg m²
        moved = norm > 1e-300
        return torch.where(moved, 2.0 * e / torch.where(moved, norm, torch.ones_like(norm)), torch.zeros_like(norm)) * Mdu

    @torch.jit.unused
    def set_hht(self, hht: float) -> None:
        """Step with HHT's numerical dissipation (Hilber, Hughes & Taylor 1977) of α = −``hht``
        (0 to ``MAX_HHT``; 0: the data's average-acceleration Newmark rule, to the bit): the
        equation of motion is met at t_{n+1+α}, between the step's start and end,

            M a1 + (1 − hht) [f_int(u1; h0) − G1] + hht [f_int(u0) − G0] = f1 + f_body,
            β = (1 + hht)² / 4,  γ = 1/2 + hht,

        which keeps second order, damps the modes Δt does not resolve (spectral radius
        (1 − hht)/(1 + hht) as ωΔt → ∞) and leaves the resolved ones almost alone. The loads are
        the step's end loads (or, with ``cut_loads_linear``'s start loads, weighted as f_int).
        Divided by 1 − hht the residual is the plain one with M a1 weighted by ``mass_scale`` =
        1/(1 − hht) and the start's hht/(1 − hht) [f_int(u0) − G0 − f0 − f_body] moved to the
        fixed side (``step_origin``, ``step``). The average-acceleration rule conserves a linear
        body's energy but not a stiffening law's: the liver law rang up after a release under the
        sim press (docs/accuracy.md, session 91), which sub-steps of Δt/4 do not. Stiffness-
        proportional Rayleigh damping (βK > 0) is not weighted so; refused."""
        hht = float(hht)
        if not 0.0 <= hht <= MAX_HHT:
            raise ValueError(f"the law prior's HHT dissipation: {hht!r}, expected 0 to {MAX_HHT:.4f}")
        if hht > 0.0 and (not hht_applies(self.newmark_beta, self.newmark_gamma, self.beta_k) or self.energy_rule):
            raise ValueError(f"the law prior's HHT dissipation {hht} needs the data's average-acceleration Newmark "
                             f"rule (β 1/4, γ 1/2, here {self.newmark_beta}, {self.newmark_gamma}) without "
                             f"stiffness-proportional damping (βK {self.beta_k}), and the Newmark rule "
                             f"(not the energy rule)")
        self.hht = hht
        if hht == 0.0:
            self.beta, self.gamma, self.mass_scale = self.newmark_beta, self.newmark_gamma, 1.0
        else:
            self.beta, self.gamma, self.mass_scale = (1.0 + hht) ** 2 / 4.0, 0.5 + hht, 1.0 / (1.0 - hht)
        self.c1 = 1.0 / (2.0 * self.beta) - 1.0
        for k, level in enumerate(self.level_constants):
            h = level[0]
            level[2] = 1.0 / (self.beta * h**2)
            level[3] = self.mass_scale + self.alpha_m * self.gamma * h
        self.use_level(0)
        self.forget()

    # --- the law per cell -----------------------------------------------------------------------
    def pk2(self, F: Tensor) -> Tuple[Tensor, Tensor]:
        """(S_iso, S_vol) [..., 3, 3] Pa of cells' deformation gradients F [..., 3, 3]."""
        if self.learned:
            return self.learned_law.pk2(F.transpose(-1, -2) @ F)
        if self.ogden:
            C = F.transpose(-1, -2) @ F
            return (ogden_isochoric_pk2(C, self.ogden_mu, self.ogden_alpha),
                    ogden_volumetric_pk2(F, C, self.ogden_d))
        return neo_hookean_pk2(F, self.c10, self.d1)

    def law(self, F: Tensor) -> Tuple[Tensor, Tensor]:
        """``pk2`` (S_iso, S_vol) [B, T, 3, 3] Pa of the cells' F [B, T, 3, 3], the last F's kept
        where it takes no gradient (serve, evaluate): a carried model step meets the law at its
        start three times (``unpack``'s stress and relaxation, ``step_start``) and at each prior
        step's end twice (``relax_from``, ``physical_state``). Kept by value, so a new F is never
        served an old S; ``forget`` drops it."""
        if F.requires_grad:
            return self.pk2(F)
        if self.memo_law_F.shape == F.shape and bool(torch.equal(self.memo_law_F, F)):
            return self.memo_law_S_iso, self.memo_law_S_vol
        s_iso, s_vol = self.pk2(F)
        self.memo_law_F, self.memo_law_S_iso, self.memo_law_S_vol = F, s_iso, s_vol
        return s_iso, s_vol

    def pk1(self, F: Tensor, w_iso: float, w_vol: float, extra: Optional[Tensor]) -> Tensor:
        """P = F (w_vol S_vol + w_iso S_iso + extra) [..., 3, 3] Pa (``extra`` [B, T, 3, 3] a stress
        constant in F: the Prony history's part of a step)."""
        s_iso, s_vol = self.law(F)
        S = w_vol * s_vol + w_iso * s_iso
        if extra is not None:
            S = S + extra
        return F @ S

    def cells(self, u: Tensor) -> Tensor:
        """The cells' deformation gradients F [B, T, 3, 3] at free-DOF displacements u [B, n] m, the
        last u's kept where it takes no gradient: a kept-tangent iteration meets each iterate three
        times (the line search's floor at its start, its trial, the residual at the trial). Kept
        by value (a copy of u), as ``law`` keeps its stresses; ``forget`` drops it."""
        if u.requires_grad:
            return self.deformation_gradients(self.positions(u))
        if self.memo_cells_u.shape == u.shape and bool(torch.equal(self.memo_cells_u, u)):
            return self.memo_cells_F
        F = self.deformation_gradients(self.positions(u))
        self.memo_cells_u, self.memo_cells_F = u.clone(), F
        return F

    def strain_energy_density(self, F: Tensor) -> Tuple[Tensor, Tensor]:
        """(Ψ_iso, Ψ_vol) [...] J/m³ of cells' deformation gradients F [..., 3, 3]: the law's strain
        energy, whose 2 ∂/∂C are ``pk2``'s (S_iso, S_vol) (for reports and the exported
        ``energy_entropy``; a step never needs it)."""
        C = F.transpose(-1, -2) @ F
        if self.learned:
            return self.learned_law.energy_parts(C)
        J = det3(F)
        if self.ogden:
            return (ogden_isochoric_energy(C, self.ogden_mu, self.ogden_alpha),
                    ogden_volumetric_energy(J, self.ogden_d))
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        return self.c10 * (J.pow(-2.0 / 3.0) * I1 - 3.0), (J - 1.0).pow(2) / self.d1

    def energy(self, u: Tensor, v: Tensor) -> Tuple[Tensor, Tensor]:
        """(kinetic ½ vᵀ M v, potential Σ_e V_e (Ψ_vol + g∞ Ψ_iso)(F_e) − f_body · u) [B] J at free-DOF
        displacements u [B, n] m and velocities v [B, n] m/s: the energy the body holds whatever its
        Prony history (g∞ = 1 − Σ ḡ_i, 1 for an elastic law). From rest, the work of the loads less
        this energy's change is what the body has dissipated or holds in its Prony terms, ≥ 0 for a
        passive body, and 0 for an elastic law up to the integrator's drift (``evaluate``)."""
        kinetic = self.kinetic_energy(v)                                               # [B]
        iso, vol = self.strain_energy_density(self.cells(u))                          # [B, T] each
        g_inf = 1.0 - self.prony_weight.sum()
        stored = ((vol + g_inf * iso) * self.cell_volume).sum(-1)                     # [B]
        return kinetic, stored - (u * self.body_force).sum(-1)

    def body_energy(self, u: Tensor, v: Tensor) -> Tensor:
        """``energy``'s kinetic + potential [B] J (the exported model's ``energy_entropy``)."""
        kinetic, potential = self.energy(u, v)
        return kinetic + potential

    def admissible(self, base: Tensor, du: Tensor) -> Tensor:
        """base − s du [B, n] m with, per sample, the largest s of 1, 1/2, 1/4, ... (``MAX_HALVINGS``)
        that leaves every cell's J = det F above min(``J_FLOOR``, half the smallest J at base),
        and s = 0 where none does: a Newton update (or the predictor's Δt v) that would crush or
        invert a cell is shortened, one that would not (every step of the data) is taken whole, to
        the bit. s carries no gradient."""
        with torch.no_grad():
            floor = torch.clamp(0.5 * det3(self.cells(base)).amin(1), max=self.j_floor)                # [B]
            s = torch.ones(base.shape[0], 1, dtype=base.dtype, device=base.device)
            for k in range(self.max_halvings + 1):
                J = det3(self.cells(base - s * du)).amin(1)                                       # [B]
                short = ~(J > floor)                                                                # NaN too
                if not bool(short.any()):
                    break
                if k == self.max_halvings:        # still crushing after every halving: no update at all
                    s = torch.where(short.unsqueeze(1), torch.zeros_like(s), s)
                else:
                    s = torch.where(short.unsqueeze(1), 0.5 * s, s)
            self.shortened.add_((s < 1.0).sum())
        return base - s * du

    def assemble(self, P: Tensor) -> Tensor:
        """Σ_e V_e P_e Grad φ_a over the free DOFs [B, n] N of the cells' P [B, T, 3, 3] Pa."""
        B, T = P.shape[0], P.shape[1]
        fe = torch.einsum("btij,taj->btai", P, self.shape_grad) * self.cell_volume.view(1, -1, 1, 1)   # [B, T, 4, 3]
        full = fe.new_zeros(B, 3 * self.n_nodes).index_add(1, self.cell_dofs, fe.reshape(B, 12 * T))
        return full.index_select(1, self.free_index)

    def tangent_pairs(self, F: Tensor, w_iso: float, w_vol: float, extra: Optional[Tensor]) -> Tensor:
        """The cells' tangent stiffness V_e Grad φ_a · ∂P/∂F · Grad φ_b on the pairs of free DOFs
        [B, k] N/m (``pair_keep``; as ``rotated_pairs``), detached: ∂P/∂F in closed form
        (:func:`neo_hookean_tangent`, :func:`ogden_tangent`)."""
        with torch.no_grad():
            self.tangents_formed.add_(1)
            B, T = F.shape[0], F.shape[1]
            if self.learned:
                A = learned_tangent(self.learned_law, F, w_iso, w_vol, extra)
            elif self.ogden:
                A = ogden_tangent(F, self.ogden_mu, self.ogden_alpha, self.ogden_d, w_iso, w_vol, extra)
            else:
                A = neo_hookean_tangent(F, self.c10, self.d1, w_iso, w_vol, extra)         # [B, T, i, j, k, l]
            Ke = torch.einsum("taj,btijkl,tcl->btaick", self.shape_grad, A, self.shape_grad)
            Ke = Ke * self.cell_volume.view(1, -1, 1, 1, 1, 1)                             # [B, T, 4, 3, 4, 3]
            return Ke.reshape(B, T * 144).index_select(1, self.pair_keep)

    @torch.jit.unused
    def set_band(self, max_share: float, dissection_share: float = 0.0) -> None:
        """Factor the dense path's step matrices (TorchScript, so serve; a GPU) block-tridiagonally
        where :func:`thermognn.train.prior.band_layout` finds it at most ``max_share`` of a dense
        LU's flops (the shell's 1032 DOFs: bandwidth 50 after reordering); else by one level of
        nested dissection where :func:`thermognn.train.prior.dissection_layout` finds that at most
        ``dissection_share`` of them (the liver's 1278: halves of 639 and 549 and a separator of
        90, 0.31 of the flops); densely elsewhere."""
        layout = band_layout(self.pattern, max_share)
        long = torch.long
        if layout is None:
            order, w, nb, slot, pad = np.zeros(0), 0, 0, np.zeros(0), np.zeros(0)
        else:
            order, w, nb, slot, pad = layout
        self.band_width, self.band_blocks = int(w), int(nb)                 # 0 blocks: not banded
        self.register_buffer("band_order", torch.as_tensor(order, dtype=long), persistent=False)   # [n]
        self.register_buffer("band_slot", torch.as_tensor(slot, dtype=long), persistent=False)     # [nnz]
        self.register_buffer("band_pad", torch.as_tensor(pad, dtype=long), persistent=False)       # [nb w − n]
        cut = dissection_layout(self.pattern, dissection_share) if layout is None else None
        if cut is None:
            gather, scatter, m, sep, slot, pad = np.zeros(0), np.zeros(0), 0, 0, np.zeros(0), np.zeros(0)
        else:
            gather, scatter, m, sep, slot, pad = cut
        self.dissection_half, self.dissection_separator = int(m), int(sep)    # 0: not dissected
        self.register_buffer("dissection_gather", torch.as_tensor(gather, dtype=long), persistent=False)  # [2m + s]
        self.register_buffer("dissection_scatter", torch.as_tensor(scatter, dtype=long), persistent=False)  # [n]
        self.register_buffer("dissection_slot", torch.as_tensor(slot, dtype=long), persistent=False)      # [nnz]
        self.register_buffer("dissection_pad", torch.as_tensor(pad, dtype=long), persistent=False)

    def band_system(self, pairs: Tensor) -> Tensor:
        """The step matrix c0 m_f M + K_T of K_T's pairs [B, k] N/m in ``set_band``'s blocks
        [B, 3, nb, w, w] (diagonal, lower, upper), the padding's diagonal 1."""
        B, nb, w = pairs.shape[0], self.band_blocks, self.band_width
        flat = self.placed_values(pairs, 3 * nb * w * w, self.band_slot)
        return flat.index_fill_(1, self.band_pad, 1.0).reshape(B, 3, nb, w, w)

    def dissection_system(self, pairs: Tensor) -> Tensor:
        """The step matrix c0 m_f M + K_T of K_T's pairs [B, k] N/m in ``set_band``'s dissection,
        flat [B, 2m² + 4ms + s²] (``thermognn.train.prior.dissection_layout``), the padding's diagonal 1."""
        m, sep = self.dissection_half, self.dissection_separator
        flat = self.placed_values(pairs, 2 * m * m + 4 * m * sep + sep * sep, self.dissection_slot)
        return flat.index_fill_(1, self.dissection_pad, 1.0)

    def dissection_rhs(self, b: Tensor) -> Tensor:
        """Free-DOF vectors b [B, n] in the dissection's places [B, 2m + s] (halves zero padded)."""
        return torch.cat([b, b.new_zeros(b.shape[0], 1)], 1).index_select(1, self.dissection_gather)

    def dissection_result(self, x: Tensor) -> Tensor:
        """``dissection_rhs`` undone: [B, 2m + s] -> [B, n] free DOFs."""
        return x.index_select(1, self.dissection_scatter)

    def band_rhs(self, b: Tensor) -> Tensor:
        """Free-DOF vectors b [B, n] in ``set_band``'s order and blocks [B, nb, w] (zero padded)."""
        B, nb, w = b.shape[0], self.band_blocks, self.band_width
        ordered = b.index_select(1, self.band_order)
        return torch.cat([ordered, ordered.new_zeros(B, nb * w - self.n_free)], 1).reshape(B, nb, w)

    def band_result(self, x: Tensor) -> Tensor:
        """``band_rhs`` undone: [B, nb, w] in blocks -> [B, n] free DOFs."""
        B = x.shape[0]
        return x.new_zeros(B, self.n_free).index_copy(1, self.band_order, x.reshape(B, -1)[:, :self.n_free])

    @torch.jit.unused
    def law_solve(self, pairs: Tensor, b: Tensor) -> Tensor:
        """u [B, n] solving (c0 m_f M + K_T) u = b [B, n] N, K_T's pairs [B, k] N/m, by sparse LU."""
        return SparseSolve.apply(self.sparse_values(pairs), b, self.pattern)

    def solve(self, pairs: Tensor, b: Tensor) -> Tensor:
        """``law_solve``, dense (batched on a GPU; in TorchScript) off the CPU path."""
        if not torch.jit.is_scripting() and self.sparse_cpu and b.device.type == "cpu":
            return self.law_solve(pairs, b)
        lu, pivots, blocks, coupling, lu_s, pivots_s = self.factor(pairs)
        return self.back_substitute(lu, pivots, blocks, coupling, lu_s, pivots_s, b)

    def factor(self, pairs: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The dense path's factors of the step matrix c0 m_f M + K_T of K_T's pairs [B, k] N/m,
        as ``set_band`` chose: (LU, pivots, then the band's X and L or the dissection's W and A_sk,
        then the dissection separator's LU and pivots; empty where unused) for ``back_substitute``."""
        empty = pairs.new_zeros(0)
        no_pivots = torch.zeros(0, dtype=torch.int32, device=pairs.device)
        if self.band_blocks > 0:
            lu, pivots, X, L = band_factor(self.band_system(pairs))
            return lu, pivots, X, L, empty, no_pivots
        if self.dissection_half > 0:
            return dissection_factor(self.dissection_system(pairs), self.dissection_half, self.dissection_separator)
        lu, pivots = lu_factor_each(self.dense_system(pairs))                                 # [B, n, n] N/m
        return lu, pivots, empty, empty, empty, no_pivots

    def back_substitute(self, lu: Tensor, pivots: Tensor, blocks: Tensor, coupling: Tensor, lu_s: Tensor,
                        pivots_s: Tensor, b: Tensor) -> Tensor:
        """u [B, n] solving the step's system for b [B, n] N with ``factor``'s factors."""
        if self.band_blocks > 0:
            return self.band_result(band_solve(lu, pivots, blocks, coupling, self.band_rhs(b)))
        if self.dissection_half > 0:
            return self.dissection_result(dissection_solve(lu, pivots, blocks, coupling, lu_s, pivots_s,
                                                           self.dissection_rhs(b)))
        return torch.linalg.lu_solve(lu, pivots, b.unsqueeze(-1)).squeeze(-1)

    def require_finite(self, residual: Tensor) -> None:
        """Raise where a residual [B, n] N is not finite (a cell inverted, or the remainders blew
        up): the message training and validation catch (``prior.DIVERGED``); a sub-step's
        constants are put back first (``use_level``)."""
        if not bool(torch.isfinite(residual).all()):
            self.use_level(0)
            raise RuntimeError("law prior: a non-finite state (a cell inverted, or the remainders diverged)")

    # --- the step -------------------------------------------------------------------------------
    def elastic_force(self, u: Tensor) -> Tensor:
        """f_el = Σ_e V_e F (S_iso + S_vol) Grad φ [B, n] N at free-DOF displacements u [B, n]."""
        return self.assemble(self.pk1(self.cells(u), 1.0, 1.0, None))

    def history_stress(self, S_iso0: Tensor, h0: Tensor) -> Optional[Tensor]:
        """Σ ḡ_i (d_i h_i − w_i S_iso,0) [B, T, 3, 3] Pa: the part of a step's relaxed stress fixed
        at its start (None elastic); S_iso0 [B, T, 3, 3], h0 [B, T_prony, 6 T]."""
        if self.n_terms == 0:
            return None
        B = h0.shape[0]
        h = _matrix(h0.reshape(B, self.n_terms, self.n_cells, 6))                           # [B, T_p, T, 3, 3]
        w = self.prony_weight.view(1, -1, 1, 1, 1)
        return (w * (self.prony_decay.view(1, -1, 1, 1, 1) * h
                     - self.prony_increment.view(1, -1, 1, 1, 1) * S_iso0.unsqueeze(1))).sum(1)

    def step_origin(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor
                    ) -> Tuple[Tensor, Tensor, Optional[Tensor], Tensor, Tensor]:
        """Where a step's iterations start, from the step's start (u0, v0, a0 [B, n], h0) alone:
        (predictor [B, n], S_iso,0 [B, T, 3, 3] Pa, the history's stress ``extra`` [B, T, 3, 3] Pa
        (None elastic), c f_el(u0) [B, n] N, the FE's predictor u0 + Δt v0 [B, n] m, shortened by
        ``admissible`` where it would crush a cell)."""
        predictor = self.newmark_predictor(u0, v0, a0)                                    # a1 = c0 u1 − predictor
        F0 = self.cells(u0)
        S_iso0, S_vol0 = self.law(F0)
        extra = self.history_stress(S_iso0, h0)
        u1 = self.admissible(u0, -self.dt * v0)                 # the FE's predictor u0 + Δt v0 (shortened if it crushes)
        damping0 = self.c * self.assemble(F0 @ (S_iso0 + S_vol0))                        # c f_el(u0): [B, n] N
        if self.hht > 0.0:                  # HHT: − hht/(1 − hht) (f_int(u0) + αM M v0) (``set_hht``)
            S0 = S_iso0 + S_vol0
            if self.n_terms > 0:
                S0 = S0 + self._relaxed_from(S_iso0, h0)
            damping0 = damping0 - (self.mass_scale - 1.0) * (self.assemble(F0 @ S0) + self.alpha_m * self.mass(v0))
        if self.energy_rule:                # the start ``discrete_gradient`` needs (``set_rule``)
            self.rule_start(u0, F0, extra)
        return predictor, S_iso0, extra, damping0, u1

    def end_rates(self, u1: Tensor, v0: Tensor, a0: Tensor, predictor: Tensor) -> Tuple[Tensor, Tensor]:
        """(a1 [m/s²], v1 [m/s]) [B, n] of a step (or sub-step) ending at u1 [B, n] m: Newmark's
        (``newmark_rates``); with the energy rule the acceleration carried on is the end's own,
        M a1 = f1 − f_int(u1), not the trapezoid's 2 ā − a0, which differs from it by M⁻¹ of
        ``discrete_gradient``'s correction: the next step's trapezoid starts from its start's
        forces (``set_rule``). v1 = 2 Δu / Δt − v0 either way."""
        a1, v1 = self.newmark_rates(u1, v0, a0, predictor)
        if self.energy_rule:
            F = self.cells(u1)
            extra: Optional[Tensor] = None
            if self.n_terms > 0:
                extra = self.rule_extra
            internal = self.assemble(self.pk1(F, self.iso_weight, 1.0, extra))
            a1 = a1 + self.mass_solve(self.discrete_gradient(u1, internal))
        return a1, v1

    def step_residual(self, u1: Tensor, v0: Tensor, a0: Tensor, predictor: Tensor, extra: Optional[Tensor],
                      fixed: Tensor) -> Tuple[Tensor, Tensor]:
        """(R(u1) [B, n] N, the cells' F [B, T, 3, 3] there) of a step's end u1 [B, n] m from v0, a0
        with ``step_origin``'s predictor and history stress ``extra``, ``fixed`` = its loads +
        c f_el(u0) [B, n] N: M (a1 + αM v1) + f_int(u1; h0) + c f_el(u1) − fixed, f_int and c f_el
        in one law evaluation, P = F ((1 + c) S_vol + (w_iso + c) S_iso + extra)."""
        a1, v1 = self.newmark_rates(u1, v0, a0, predictor)
        F = self.cells(u1)
        internal = self.assemble(self.pk1(F, self.iso_weight + self.c, 1.0 + self.c, extra))          # [B, n] N
        residual = self.mass(self.mass_scale * a1 + self.alpha_m * v1) + internal - fixed
        if self.energy_rule:
            residual = residual + self.discrete_gradient(u1, internal)
        return residual, F

    def step_start(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor
                   ) -> Tuple[Tensor, Tensor, Optional[Tensor], Tensor, Tensor, Tensor, Tensor]:
        """What a step's first Newton iteration takes from the step's start (u0, v0, a0 [B, n],
        h0) alone, not from its loads or remainders: ``step_origin``'s (predictor, S_iso,0, extra,
        c f_el(u0), the predictor u0 + Δt v0), the residual there without the loads and
        remainders [B, n] N, M (a + αM v) + f_int + c f_el − c f_el(u0), and the tangent's pairs
        there [B, k] N/m. A model step with the network's remainders steps the prior twice from
        the same start (``LinearPriorModel.advance``): with one Newton iteration all of it is
        shared but one back-substitution (``first_iteration`` keeps it with the tangent's factors)."""
        predictor, S_iso0, extra, damping0, u1 = self.step_origin(u0, v0, a0, h0)
        internal, F = self.step_residual(u1, v0, a0, predictor, extra, damping0)
        pairs = self.tangent_pairs(F.detach(), self.iso_weight + self.c, 1.0 + self.c,
                                   None if extra is None else extra.detach())
        return predictor, S_iso0, extra, damping0, u1, internal, pairs

    @torch.jit.unused
    def _eager_first_iteration(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor, loads: Tensor
                               ) -> Tuple[Tensor, Tensor, Tensor, Optional[Tensor], Tensor]:
        """``first_iteration`` on the CPU, eager: ``step_start`` and its tangent's sparse LU kept
        for the next step from the same start tensors (the same objects, unmodified, with the same
        grad mode), so that a model step's second prior step costs one back-substitution more."""
        key = (u0, v0, a0, h0)
        stamp = tuple(t._version for t in key) + (torch.is_grad_enabled(),)
        memo = self._start_memo
        kept = memo is not None and all(a is b for a, b in zip(memo[0], key)) and memo[1] == stamp
        start = memo[2] if kept else self.step_start(u0, v0, a0, h0)
        predictor, S_iso0, extra, damping0, u1, internal, pairs = start
        residual = internal - loads
        self.require_finite(residual)
        if kept:
            lus = memo[3]
            if self.energy_rule:
                self.rule_start(u0, self.cells(u0), start[2])
        else:
            lus = sparse_factors(self.sparse_values(pairs), self.pattern)
            self._start_memo = (key, stamp, start, lus)
        return self.admissible(u1, FactoredSolve.apply(residual, lus)), predictor, S_iso0, extra, damping0

    @torch.jit.unused
    def _forget_eager(self) -> None:
        self._start_memo = None

    @torch.jit.export
    def forget(self) -> None:
        """Drop the step start the first Newton iteration keeps (``first_iteration``), the law's
        kept stresses and a kept tangent (``keep_tangent``), e.g. before a model is saved or a
        rollout starts: they hold the last step's tensors and factors."""
        if not torch.jit.is_scripting():
            self._forget_eager()
        empty = self.memo_key.new_zeros(0)
        self.memo_key, self.memo_predictor, self.memo_S_iso0, self.memo_extra = empty, empty, empty, empty
        self.memo_damping0, self.memo_u1, self.memo_internal, self.memo_lu = empty, empty, empty, empty
        self.memo_pivots = self.memo_pivots.new_zeros(0)
        self.memo_band_X, self.memo_band_L, self.memo_sep_lu = empty, empty, empty
        self.memo_sep_pivots = self.memo_sep_pivots.new_zeros(0)
        self.memo_law_F, self.memo_law_S_iso, self.memo_law_S_vol = empty, empty, empty
        self.memo_cells_u, self.memo_cells_F = empty, empty
        self.drop_kept()

    def fresh_first_iteration(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor, loads: Tensor
                              ) -> Tuple[Tensor, Tensor, Tensor, Optional[Tensor], Tensor]:
        """``first_iteration`` from scratch, nothing kept: ``step_start`` and one solve with its
        tangent (training's differentiable path; a cut step's sub-steps, at their own Δt)."""
        predictor, S_iso0, extra, damping0, u1, internal, pairs = self.step_start(u0, v0, a0, h0)
        residual = internal - loads
        self.require_finite(residual)
        return self.admissible(u1, self.solve(pairs, residual)), predictor, S_iso0, extra, damping0

    def first_iteration(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor, loads: Tensor
                        ) -> Tuple[Tensor, Tensor, Tensor, Optional[Tensor], Tensor]:
        """(u1 after the first Newton iteration [B, n] m, predictor, S_iso,0, extra, c f_el(u0))
        of a step from (u0, v0, a0, h0) under ``loads`` = f1 + f_body + (1 + c) G1 − c G0 [B, n] N
        (``step_start``'s names). A second step from the same start (a model step's, with the
        network's remainders) reuses the first one's start and factors: on the CPU's sparse path
        kept by tensor identity (``_eager_first_iteration``, gradients included), on the dense
        path (TorchScript, GPU) by value where no gradient is taken (serve)."""
        if not torch.jit.is_scripting() and self.sparse_cpu and u0.device.type == "cpu":
            return self._eager_first_iteration(u0, v0, a0, h0, loads)
        if u0.requires_grad or v0.requires_grad or a0.requires_grad or h0.requires_grad or loads.requires_grad:
            return self.fresh_first_iteration(u0, v0, a0, h0, loads)      # training: one solve, differentiable
        key = torch.cat([u0.reshape(-1), v0.reshape(-1), a0.reshape(-1), h0.reshape(-1)])
        if not (self.memo_key.shape == key.shape and bool(torch.equal(self.memo_key, key))):
            predictor, S_iso0, extra, damping0, u1, internal, pairs = self.step_start(u0, v0, a0, h0)
            self.require_finite(internal)
            (self.memo_lu, self.memo_pivots, self.memo_band_X, self.memo_band_L, self.memo_sep_lu,
             self.memo_sep_pivots) = self.factor(pairs)
            self.memo_key, self.memo_predictor, self.memo_S_iso0 = key, predictor, S_iso0
            self.memo_extra = extra if extra is not None else key.new_zeros(0)
            self.memo_damping0, self.memo_u1, self.memo_internal = damping0, u1, internal
        elif self.energy_rule:
            self.rule_start(u0, self.cells(u0), self.memo_extra if self.n_terms > 0 else None)
        residual = self.memo_internal - loads
        self.require_finite(residual)
        du = self.back_substitute(self.memo_lu, self.memo_pivots, self.memo_band_X, self.memo_band_L,
                                  self.memo_sep_lu, self.memo_sep_pivots, residual)
        extra_kept: Optional[Tensor] = None
        if self.n_terms > 0:
            extra_kept = self.memo_extra
        return self.admissible(self.memo_u1, du), self.memo_predictor, self.memo_S_iso0, extra_kept, self.memo_damping0

    def use_level(self, level: int) -> None:
        """Put in place the constants of a sub-step Δt / 2^level (``level_constants``; 0: the step's
        own): Δt, c = βK / Δt, c0, the mass factor, S_iso's weight and the Prony decays and weights."""
        k = self.level_constants[level]
        self.dt, self.c, self.c0, self.mass_factor, self.iso_weight = k[0], k[1], k[2], k[3], k[4]
        self.prony_decay, self.prony_increment = self.level_decay[level], self.level_increment[level]

    def iterate(self, u1: Tensor, u0: Tensor, v0: Tensor, a0: Tensor, predictor: Tensor, extra: Optional[Tensor],
                fixed: Tensor) -> Tuple[Tensor, int, Tensor]:
        """(u1 [B, n] m, the Newton iterations taken in all, which samples had not converged [B]
        bool) after a step's first iteration u1 from (u0, v0, a0 [B, n]) with ``step_start``'s
        predictor and history stress ``extra``, ``fixed`` = its loads + c f_el(u0) [B, n] N:
        ``iterations`` in all, then up to ``max_iterations`` while the last update moved some DOF
        of the batch by more than ``newton_rtol`` of its sample's largest displacement. A fixed
        budget always counts as converged. With ``line_search`` > 0, ``searched_iterate``'s."""
        if self.line_search > 0:
            return self.searched_iterate(u1, u0, v0, a0, predictor, extra, fixed)
        w_iso, w_vol = self.iso_weight + self.c, 1.0 + self.c
        taken = 1
        last = u0.detach() + self.dt * v0.detach()          # where the last update started: the predictor
        move = u1.detach() - last                            # the last update, whole (see below)
        for it in range(1, self.max_iterations):
            if it >= self.iterations and not self.moves(move, u1.detach()):
                break
            residual, F = self.step_residual(u1, v0, a0, predictor, extra, fixed)            # [B, n] N
            self.require_finite(residual)
            last = u1.detach()
            du = self.solve(self.tangent_pairs(F.detach(), w_iso, w_vol, None if extra is None else extra.detach()),
                            residual)
            u1 = self.admissible(u1, du)
            move = self.whole_move(last, du, u1.detach())
            taken += 1
        if self.max_iterations > self.iterations and taken == self.max_iterations:
            return u1, taken, self.moving(move, u1.detach())
        return u1, taken, torch.zeros(u1.shape[0], dtype=torch.bool, device=u1.device)

    def whole_move(self, base: Tensor, du: Tensor, taken: Tensor) -> Tensor:
        """The update [B, n] m a step's convergence is judged by, of a Newton update du [B, n]
        from base that ``admissible`` took as ``taken``: taken − base where it was taken whole
        (to the bit what it moved), the whole update du where it was shortened. An update
        shortened to nothing, where any part of it would crush a cell, is not convergence: the
        step stands where its residual is not small (the liver law under the sim's press, session
        90, 'converged' so with 4.6e3 N left and ran away)."""
        with torch.no_grad():
            whole = (taken == base - du.detach()).all(1)                                     # [B]
            return torch.where(whole.unsqueeze(1), taken - base, du.detach())

    def searched_iterate(self, u1: Tensor, u0: Tensor, v0: Tensor, a0: Tensor, predictor: Tensor,
                         extra: Optional[Tensor], fixed: Tensor) -> Tuple[Tensor, int, Tensor]:
        """``iterate`` with a back-tracking line search on the residual norm (``line_search`` > 0;
        arguments and result as ``iterate``'s): each Newton update u − du, the first one's from
        the predictor u0 + Δt v0 included, is taken as u − s du with the largest s of 1, 1/2, ...,
        1/2^line_search that lowers ‖R‖ by at least ``LINE_SEARCH_DECREASE`` s of its value at u
        (per sample; the smallest s where none does), as an undamped update can wander off where
        the step's solution lies beyond a region the tangent does not describe (the bunny's
        traj_14 ran away so at the cut floor, and stays finite searched; docs/accuracy.md session
        88). A kept tangent's chord updates (``kept_iterations``) are not searched: a step they do
        not converge is taken again with fresh tangents, searched. An update within the step's
        tolerance (``tolerance``: converged, its residual round-off) is never shortened, and one
        taken whole is the plain update, to the bit; whether a step has converged is judged on the
        whole update du, not a shortened one (the search's or ``admissible``'s, as plain ``iterate``
        does since session 90: ``whole_move``). s carries no gradient. Where the residual at the
        step's start u0 is below ``REST_START_RATIO`` of the predictor's, the first update is taken
        from u0 instead (a node ringing after a sudden release whose Δt v0 crushes a cell: the
        predictor's residual 870 N, u0's 0.8 N, and the step converges in 5 iterations where from
        the predictor it was cut twice; session 90)."""
        w_iso, w_vol = self.iso_weight + self.c, 1.0 + self.c
        taken = 1
        # where the first update started: the FE's predictor u0 + Δt v0, shortened by ``admissible``
        # where it crushes a cell (as ``step_origin`` shortened it; whole, it is u0 + Δt v0 to the
        # bit). Searched from the whole predictor instead, an update from a crushing one ran back
        # through inverted cells, which ``admissible`` lets pass from an inverted base: the liver's
        # law under 17 s of the sim press inverted 519 cells in one step (docs/accuracy.md, session 95)
        base = self.admissible(u0, -self.dt * v0)
        r_base, _ = self.step_residual(base, v0, a0, predictor, extra, fixed)
        # where the predictor is far worse than the step's start (a node whose Δt v0 crushes a cell,
        # its residual 1e2-1e3 N where the start's is the inertia's 0.1 N), the first update is
        # taken from the start instead
        r_rest, F_rest = self.step_residual(u0, v0, a0, predictor, extra, fixed)
        with torch.no_grad():
            rest = (torch.linalg.vector_norm(r_rest.detach(), dim=1)
                    < self.rest_start_ratio * torch.linalg.vector_norm(r_base.detach(), dim=1))      # [B]
        if bool(rest.any()):
            u1_rest = self.admissible(u0, self.solve(self.tangent_pairs(F_rest.detach(), w_iso, w_vol,
                                                                        None if extra is None else extra.detach()),
                                                     r_rest))
            at = rest.unsqueeze(1)
            base, r_base, u1 = torch.where(at, u0, base), torch.where(at, r_rest, r_base), torch.where(at, u1_rest, u1)
        u1, residual, F, move = self.back_track(base, base - u1, r_base, u1, v0, a0, predictor, extra, fixed)
        for it in range(1, self.max_iterations):
            if it >= self.iterations and not bool(self.moving(move, u1.detach()).any()):
                break
            self.require_finite(residual)
            du = self.solve(self.tangent_pairs(F.detach(), w_iso, w_vol, None if extra is None else extra.detach()),
                            residual)
            u1, residual, F, move = self.back_track(u1, du, residual, self.admissible(u1, du), v0, a0, predictor,
                                                    extra, fixed)
            taken += 1
        if self.max_iterations > self.iterations and taken == self.max_iterations:
            return u1, taken, self.moving(move, u1.detach())
        return u1, taken, torch.zeros(u1.shape[0], dtype=u1.dtype, device=u1.device) != 0

    def back_track(self, base: Tensor, du: Tensor, r_base: Tensor, trial: Tensor, v0: Tensor, a0: Tensor,
                   predictor: Tensor, extra: Optional[Tensor], fixed: Tensor
                   ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(u [B, n] m, R(u) [B, n] N, the cells' F there, the update to judge convergence by
        [B, n] m) of a Newton update du [B, n] from base (residual r_base) whose whole step
        (``admissible``'s) is ``trial``: ``searched_iterate``'s line search."""
        residual, F = self.step_residual(trial, v0, a0, predictor, extra, fixed)
        with torch.no_grad():
            before = torch.linalg.vector_norm(r_base.detach(), dim=1)                            # [B] N
            # a base whose residual is not finite (a predictor that crushes a cell, which
            # ``admissible`` shortened before the first update): any finite residual lowers it
            before = torch.where(torch.isfinite(before), before, torch.full_like(before, float("inf")))
            s = torch.ones(base.shape[0], 1, dtype=base.dtype, device=base.device)
            move = trial.detach() - base.detach()
            # an update within the step's tolerance is converged: its residual is round-off, which
            # need not decrease
            settled = du.detach().abs().amax(1) <= self.tolerance(base.detach())                 # [B]
        for k in range(self.line_search):
            after = torch.linalg.vector_norm(residual.detach(), dim=1)
            worse = ~(after <= (1.0 - self.line_search_decrease * s.squeeze(1)) * before) & ~settled   # NaN too
            if not bool(worse.any()):
                break
            s = torch.where(worse.unsqueeze(1), 0.5 * s, s)
            trial = self.admissible(base, s * du)
            residual, F = self.step_residual(trial, v0, a0, predictor, extra, fixed)
        with torch.no_grad():
            # the whole update where it was shortened (by the search, or by ``admissible``): a short
            # step taken is not a converged one
            whole = (s.squeeze(1) == 1.0) & (trial.detach() == (base - du).detach()).all(1)           # [B]
            move = torch.where(whole.unsqueeze(1), move, du.detach())
            self.searched.add_((s < 1.0).sum())
        return trial, residual, F, move

    def fresh_iterations(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor, loads: Tensor
                         ) -> Tuple[Tensor, Tensor, Tensor, int, Tensor]:
        """A step's iterations with a tangent formed at each (``first_iteration``, ``iterate``), as
        ``kept_iterations`` returns them: (u1, predictor, S_iso,0, Newton iterations taken, which
        samples had not converged [B] bool) of the step from (u0, v0, a0, h0) under ``loads``."""
        u1, predictor, S_iso0, extra, damping0 = self.first_iteration(u0, v0, a0, h0, loads)
        u1, taken, still = self.iterate(u1, u0, v0, a0, predictor, extra, loads + damping0)
        return u1, predictor, S_iso0, taken, still

    # --- a kept tangent (``tangent = "kept"``): chord iterations between fresh tangents -----------
    def keep_tangent(self, F: Tensor, extra: Optional[Tensor]) -> None:
        """Form the tangent at the cells' F [B, T, 3, 3] (with the history stress ``extra``) and keep
        its step matrix's factors for ``kept_solve``: sparse LUs on the eager CPU path, else
        ``factor``'s (dense, block-tridiagonal or dissected)."""
        pairs = self.tangent_pairs(F, self.iso_weight + self.c, 1.0 + self.c, extra)
        if not torch.jit.is_scripting() and self.sparse_cpu and F.device.type == "cpu":
            self._keep_sparse(pairs)
        else:
            (self.kept_lu, self.kept_pivots, self.kept_band_X, self.kept_band_L, self.kept_sep_lu,
             self.kept_sep_pivots) = self.factor(pairs)
        self.kept_batch = int(F.shape[0])

    def drop_kept(self) -> None:
        """Drop the kept tangent and where its last step started and ended (``kept_iterations``)."""
        empty = self.kept_rate.new_zeros(0)
        self.kept_lu, self.kept_band_X, self.kept_band_L, self.kept_sep_lu = empty, empty, empty, empty
        self.kept_pivots, self.kept_sep_pivots = self.memo_pivots.new_zeros(0), self.memo_pivots.new_zeros(0)
        self.kept_from, self.kept_end, self.kept_rate = empty, empty, empty
        self.kept_batch = 0
        if not torch.jit.is_scripting():
            self._drop_kept_sparse()

    @torch.jit.unused
    def _drop_kept_sparse(self) -> None:
        self._kept_lus = []

    @torch.jit.unused
    def _keep_sparse(self, pairs: Tensor) -> None:
        self._kept_lus = sparse_factors(self.sparse_values(pairs), self.pattern)

    def kept_solve(self, b: Tensor) -> Tensor:
        """u [B, n] solving the kept tangent's step matrix for b [B, n] N (``keep_tangent``)."""
        if not torch.jit.is_scripting() and self.sparse_cpu and b.device.type == "cpu":
            return self._kept_sparse_solve(b)
        return self.back_substitute(self.kept_lu, self.kept_pivots, self.kept_band_X, self.kept_band_L,
                                    self.kept_sep_lu, self.kept_sep_pivots, b)

    @torch.jit.unused
    def _kept_sparse_solve(self, b: Tensor) -> Tensor:
        return lu_solves(self._kept_lus, b)

    def kept_iterations(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor, loads: Tensor
                        ) -> Tuple[Tensor, Tensor, Tensor, int, Tensor, bool]:
        """A step's iterations with a kept tangent, without gradients: (u1 [B, n] m, predictor,
        S_iso,0, Newton updates taken, which samples had not converged [B] bool, whether the step
        was abandoned) of the step from (u0, v0, a0 [B, n], h0) under ``loads`` (``step``'s).

        Each update solves with the factors of a tangent formed at an earlier iterate, of this
        step or an earlier one (chord iterations: one law evaluation and one back-substitution
        each). Where an update leaves a residual norm above ``kept_contraction`` of the one it
        started from (in any sample), the tangent is formed afresh where that update started and
        the update redone with it, a Newton update. Where that Newton update does not contract
        either, the chords have led the step where Newton's method does not converge (the liver's
        Ogden law at 5 times the data's loads, where a smaller residual is no nearer the
        solution): the step is abandoned, and ``step`` drops the tangent and takes the step again
        as fresh tangents do, from the predictor. A step takes at least ``iterations`` updates
        and at most ``max_iterations``, and has converged where its last update's remaining error
        is below ``newton_rtol`` of the largest displacement (and NEWTON_ATOL): for a Newton update
        its own size, as for fresh tangents; for a chord update the size times ρ/(1 − ρ), ρ its
        ratio to the update before (the chord's contraction; a small update of a slowly
        contracting chord is not yet converged).

        With ``anderson`` = m > 0 each update past the first two with a tangent is Anderson's
        mixing of the chord's update with up to m earlier ones made with the same tangent
        (``anderson_update``): the iterates of a slowly contracting chord then converge faster, and
        a tangent is formed afresh only where a mixed update leaves more than ANDERSON_CONTRACTION
        of its start's residual norm. The first two stay plain, and their ratio (the chord's
        contraction ρ, as carried) judges a mixed update: converged where the chord's own update
        from its iterate (the one the mixing starts from) times ρ/(1 − ρ) is below the tolerance.
        The mixed iterates' own ratios rise and fall: judged by them, the shell's served rollout
        stopped short of the root (7x further from the converged law), and judged by a mixed
        update's size alone, as Newton's are, the liver's took most of the updates mixing saves. A
        Newton update, with a tangent formed where it starts, is never mixed.

        A model step steps the prior twice from the same start, the second time under loads that
        differ by its network's remainders (``LinearPriorModel.advance``): the second one starts
        from where the first ended (``kept_end``), not from the predictor, and its first update
        takes the first one's last ρ (``kept_rate``), so that it stops after one update where the
        remainders moved the step by less than the tolerance."""
        predictor, S_iso0, extra, damping0, u1 = self.step_origin(u0, v0, a0, h0)
        fixed = loads + damping0
        key = self.start_key(u0, v0, a0, h0)
        B = u1.shape[0]
        carried = torch.zeros(B, dtype=u1.dtype, device=u1.device)      # ρ known before this step's updates
        if (self.kept_from.shape == key.shape and bool(torch.equal(self.kept_from, key))
                and self.kept_end.shape == u1.shape):
            u1, carried = self.kept_end, self.kept_rate
        residual, F = self.step_residual(u1, v0, a0, predictor, extra, fixed)             # [B, n] N
        self.require_finite(residual)
        fresh = self.kept_batch != B
        if fresh:
            self.keep_tangent(F, extra)
        last = torch.zeros(B, dtype=u1.dtype, device=u1.device)        # the last update's size [B] m (0: none)
        done = torch.zeros(B, dtype=torch.bool, device=u1.device)
        abandoned = False
        taken = 0
        # ``anderson``: the differences of the iterates and of their chord updates since the kept
        # tangent was formed (or this step began), the latest last: [B, n, j] m, j <= anderson
        iterates = u1.new_zeros(B, u1.shape[1], 0)
        updates = u1.new_zeros(B, u1.shape[1], 0)
        last_u, last_du = u1, u1              # the latest iterate and its chord update (set by the first)
        plain = 0                                            # updates taken unmixed with this tangent
        while taken < self.max_iterations:
            du = self.kept_solve(residual)
            size = du.abs().amax(1)                                                        # [B] m
            move = du
            mixed = False
            if self.anderson > 0:
                if taken > 0:
                    iterates = torch.cat([iterates, (u1 - last_u).unsqueeze(2)], 2)[:, :, -self.anderson:]
                    updates = torch.cat([updates, (du - last_du).unsqueeze(2)], 2)[:, :, -self.anderson:]
                    if plain >= 2:                           # the chord's own ratio measured first
                        move = self.anderson_update(du, iterates, updates)
                        mixed = True
                last_u, last_du = u1, du
            trial = self.admissible(u1, move)
            r_trial, F_trial = self.step_residual(trial, v0, a0, predictor, extra, fixed)
            contracts = self.contracts(r_trial, residual)
            # a converged sample's residual, or one an update below NEWTON_ATOL leaves (a body at
            # rest), is round-off: it need not contract
            settled = done | (size <= self.newton_atol)
            if not fresh and not bool((contracts | settled).all()):
                self.keep_tangent(F, extra)                  # no longer contracting: a fresh tangent at u1
                fresh = True
                last, carried = torch.zeros_like(last), torch.zeros_like(carried)
                du = self.kept_solve(residual)
                iterates, updates = iterates[:, :, :0], updates[:, :, :0]   # mixed only with this tangent's
                last_u, last_du, mixed, plain = u1, du, False, 0
                size = du.abs().amax(1)
                trial = self.admissible(u1, du)
                r_trial, F_trial = self.step_residual(trial, v0, a0, predictor, extra, fixed)
                newton = self.contracts(r_trial, residual)
                if not bool((newton | (size <= self.tolerance(trial)) | done).all()) \
                        or not bool(torch.isfinite(r_trial).all()):
                    abandoned = True         # Newton's update from a chord's iterate does not contract either
                    break
            self.require_finite(r_trial)
            taken += 1
            scale = self.tolerance(trial)
            if fresh:                                        # Newton's update: its own size
                done = size <= scale
            else:                                            # a chord's: its size times ρ / (1 − ρ)
                measured = last > 0
                rate = torch.where(measured, size / torch.where(measured, last, torch.ones_like(last)), carried)
                if mixed:       # a mixed one's: the chord's own ρ (the mixed iterates' ratios rise and fall)
                    rate = carried
                else:
                    carried = torch.where(measured, rate, carried)
                done = (size <= self.newton_atol) | ((rate > 0) & (rate < 1.0) & (size * rate <= scale * (1.0 - rate)))
            if not mixed:
                plain += 1
            u1, residual, F, last, fresh = trial, r_trial, F_trial, size, False
            if taken >= self.iterations and bool(done.all()):
                break
        if abandoned:
            return u1, predictor, S_iso0, taken, torch.ones_like(done), True
        self.kept_from, self.kept_end, self.kept_rate = key, u1, carried
        return u1, predictor, S_iso0, taken, ~done, False

    def anderson_update(self, du: Tensor, iterates: Tensor, updates: Tensor) -> Tensor:
        """Anderson's mixing (Walker & Ni 2011, "type II") of the chord update du [B, n] m, which
        ``kept_iterations`` subtracts from the iterate, with the earlier iterates' differences
        ``iterates`` [B, n, j] m and their chord updates' differences ``updates`` [B, n, j] m:
        du + (iterates − updates) γ, γ [B, j] fitting du by ``updates`` in least squares (per
        sample; the normal equations, j <= MAX_ANDERSON, regularised by 1e-12 of their trace).
        With j = 1 the new iterate mixes the two iterates' chord images u − du with the weights
        whose updates mix to the least norm."""
        normal = updates.transpose(1, 2) @ updates                                          # [B, j, j] m²
        right = updates.transpose(1, 2) @ du.unsqueeze(2)                                   # [B, j, 1] m²
        j = normal.shape[1]
        # [B] m²: the regularisation, and at least about the smallest normal number (a sample at
        # rest, whose updates do not change, mixes nothing: γ = 0)
        floor = 1e-300 if du.dtype == torch.float64 else 1e-36
        ridge = 1e-12 * normal.diagonal(dim1=1, dim2=2).sum(1) + floor
        eye = torch.eye(j, dtype=du.dtype, device=du.device).unsqueeze(0)                 # [1, j, j]
        gamma = torch.linalg.solve(normal + ridge.view(-1, 1, 1) * eye, right)              # [B, j, 1]
        return du + ((iterates - updates) @ gamma).squeeze(2)

    def contracts(self, r_new: Tensor, r_old: Tensor) -> Tensor:
        """Per sample [B] bool, whether an update left a residual norm of at most ``kept_contraction``
        of the one it started from (residuals [B, n] N)."""
        return (torch.linalg.vector_norm(r_new, dim=1)
                <= self.kept_contraction * torch.linalg.vector_norm(r_old, dim=1))

    def start_key(self, u0: Tensor, v0: Tensor, a0: Tensor, h0: Tensor) -> Tensor:
        """A step's start (u0, v0, a0 [B, n], h0) flat, by which ``kept_iterations`` knows a
        second step from it."""
        return torch.cat([u0.reshape(-1), v0.reshape(-1), a0.reshape(-1), h0.reshape(-1)])

    def step(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor,
             G1: Tensor, h0: Tensor, f0: Optional[Tensor] = None) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(u1, v1, a1, h1) as :meth:`NewmarkPrior.step`: ``iterations`` Newton iterations on
        R(u1) = 0 (module docstring) from the predictor u0 + Δt v0 (the first one
        ``first_iteration``'s), then, up to ``max_iterations`` in all, more while the last update
        moved some DOF of the batch by more than ``newton_rtol`` of its largest displacement (and
        NEWTON_ATOL): a step the budget does not converge (the shell's snap-through) takes the
        iterations it needs, the others cost nothing more than the check.

        With a kept tangent (``tangent = "kept"``, no gradient) the iterations are
        ``kept_iterations``'; a step they abandon or do not converge is taken again as with fresh
        tangents, so that whether a step has converged, and where it is cut, is decided as fresh
        tangents decide it (the shell's snap-through takes another branch where a step is cut
        that the FE did not cut). With ``step_cuts`` > 0 the samples whose step still has not
        converged are stepped again from their start as the FE steps it (``cut_step``, with
        fresh tangents); the others keep their whole step. A cut step's sub-steps hold its end
        loads f1, or with the step's start loads f0 [B, n] N given, the loads linearly between
        them at each sub-step's end (``cut_step``). With ``substeps`` > 1 every step is taken so, as
        that many sub-steps (``cut_step`` from level ``sub_level``, fresh tangents), as the data's
        FE took it; give the start loads f0 then (the loads of a ramp are linear between the
        step's)."""
        if len(self.level_constants) > 1:   # (a cut an error left mid-way does not leave its constants)
            self.use_level(0)
        if self.sub_level > 0:              # the data's sub-steps: every step as they were taken
            u, v, a, h, t, unconverged = self.cut_step(u0, v0, a0, f1, G0, G1, h0, f0, self.sub_level, self.substeps)
            self.count_step(t, unconverged, 0)
            return u, v, a, h
        # what R takes from outside the step's start: loads and remainders
        loads = f1 + self.body_force + (1.0 + self.c) * G1 - self.c * G0                  # [B, n] N
        if self.hht > 0.0:                  # HHT: + hht/(1 − hht) (f0 + f_body + G0) (``set_hht``)
            loads = loads + (self.mass_scale - 1.0) * ((f1 if f0 is None else f0) + self.body_force + G0)
        if self.kept_tangent and not (u0.requires_grad or v0.requires_grad or a0.requires_grad
                                      or h0.requires_grad or loads.requires_grad):
            u1, predictor, S_iso0, taken, still, abandoned = self.kept_iterations(u0, v0, a0, h0, loads)
            if abandoned or bool(still.any()):   # the step as fresh tangents take it, from its predictor
                self.drop_kept()
                u1, predictor, S_iso0, retaken, still = self.fresh_iterations(u0, v0, a0, h0, loads)
                taken += retaken             # (a second step from this start starts where it ended)
                self.kept_from, self.kept_end = self.start_key(u0, v0, a0, h0), u1
                self.kept_rate = torch.zeros(u1.shape[0], dtype=u1.dtype, device=u1.device)
        else:
            u1, predictor, S_iso0, taken, still = self.fresh_iterations(u0, v0, a0, h0, loads)
        a1, v1 = self.end_rates(u1, v0, a0, predictor)
        h1 = self.relax_from(S_iso0, u1, h0)
        unconverged = bool(still.any())
        if self.step_cuts == 0 or not unconverged:
            self.count_step(taken, int(unconverged), 0)
            return u1, v1, a1, h1
        cut = still.nonzero().squeeze(1)                                                   # [b] samples
        B = u0.shape[0]
        u, v, a, h, t, unconverged = self.cut_step(
            self.rows(u0, B, cut), self.rows(v0, B, cut), self.rows(a0, B, cut), self.rows(f1, B, cut),
            self.rows(G0, B, cut), self.rows(G1, B, cut), self.rows(h0, B, cut),
            None if f0 is None else self.rows(f0, B, cut), 1, 2)
        self.count_step(taken + t, unconverged, 1)
        return u1.index_copy(0, cut, u), v1.index_copy(0, cut, v), a1.index_copy(0, cut, a), h1.index_copy(0, cut, h)

    @staticmethod
    def rows(x: Tensor, batch: int, rows: Tensor) -> Tensor:
        """The samples ``rows`` [b] of x [B or 1, ...] (one sample stands for all B)."""
        return x.expand([batch] + list(x.shape[1:])).index_select(0, rows)

    def cut_step(self, u0: Tensor, v0: Tensor, a0: Tensor, f1: Tensor, G0: Tensor, G1: Tensor,
                 h0: Tensor, f0: Optional[Tensor] = None, start: int = 1, parts: int = 2
                 ) -> Tuple[Tensor, Tensor, Tensor, Tensor, int, int]:
        """``step`` from (u0, v0, a0, h0) under f1, G0, G1 [b, ...] as the FE steps it where a
        whole step fails (``thermognn.generate.solid``'s ``step``): as two halves, each cut again
        where it does not converge, down to Δt / 2^step_cuts, whose last try is kept. A sub-step
        holds the step's end loads f1, or with the step's start loads f0 given the loads linearly
        from f0 to f1 at its own end (the FE's loads are those at the sub-step's end: within a
        load ramp holding f1 loads a cut step early, and the bunny's traj_14, cut from its 4th step
        within its 10-step ramp, then leaves the data; docs/accuracy.md session 88), and its
        remainders go linearly from G0 to G1. Returns (u1, v1, a1, h1, the Newton iterations
        taken, whether a sub-step at the floor had not converged). ``start``, ``parts``: the first
        sub-steps' level and how many (2^start): two halves where a whole step failed, the data's
        sub-steps (``substeps``) where every step is taken so; the floor is level ``sub_level`` +
        ``step_cuts``."""
        u, v, a, h = u0, v0, a0, h0
        pending: List[int] = []              # the sub-steps still to take, in order, by level
        for _ in range(parts):
            pending.append(start)
        done = 0.0                           # how much of Δt they have taken
        taken, unconverged = 0, 0
        while len(pending) > 0:
            level = pending[0]
            part = 0.5 ** level
            self.use_level(level)
            Gs, Ge = G0 + done * (G1 - G0), G0 + (done + part) * (G1 - G0)                 # [b, n] N
            fe = f1 if f0 is None else f0 + (done + part) * (f1 - f0)                      # [b, n] N
            sub_loads = fe + self.body_force + (1.0 + self.c) * Ge - self.c * Gs
            if self.hht > 0.0:
                fs = f1 if f0 is None else f0 + done * (f1 - f0)                          # [b, n] N
                sub_loads = sub_loads + (self.mass_scale - 1.0) * (fs + self.body_force + Gs)
            u1, predictor, S_iso0, extra, damping0 = self.fresh_first_iteration(u, v, a, h, sub_loads)
            u1, t, still = self.iterate(u1, u, v, a, predictor, extra, sub_loads + damping0)
            taken += t
            converged = not bool(still.any())
            if converged or level == self.sub_level + self.step_cuts:   # taken: the next starts here
                a1, v = self.end_rates(u1, v, a, predictor)
                h = self.relax_from(S_iso0, u1, h)
                u, a = u1, a1
                done += part
                unconverged = max(unconverged, int(not converged))
                pending.pop(0)
            else:                                            # cut: two halves in its place
                pending[0] = level + 1
                pending.insert(0, level + 1)
        self.use_level(0)
        return u, v, a, h, taken, unconverged

    def count_step(self, taken: int, unconverged: int, cut: int) -> None:
        """Add a step to ``newton_taken``: its Newton iterations, whether it did not converge,
        whether it was cut."""
        self.newton_taken.add_(torch.tensor([taken, 1, unconverged, cut], dtype=torch.int64,
                                            device=self.newton_taken.device))

    def moving(self, update: Tensor, u: Tensor) -> Tensor:
        """Per sample [B] bool, whether a Newton update [B, n] m still moved some DOF by more than
        ``newton_rtol`` of the sample's largest displacement u [B, n] m (and more than NEWTON_ATOL)."""
        return update.abs().amax(1) > self.tolerance(u)

    def tolerance(self, u: Tensor) -> Tensor:
        """The largest Newton update [B] m of a converged step at displacements u [B, n] m:
        ``newton_rtol`` of the sample's largest displacement, and NEWTON_ATOL."""
        return self.newton_rtol * u.abs().amax(1) + self.newton_atol

    def moves(self, update: Tensor, u: Tensor) -> bool:
        """Whether a Newton update [B, n] m still moved some DOF of some sample (``moving``)."""
        return bool(self.moving(update, u).any())

    @torch.jit.unused
    def budget_loads(self, u: Tensor, v: Tensor, f: Tensor, rtol: float = BUDGET_RTOL,
                     max_corrections: int = BUDGET_CORRECTIONS) -> Tuple[Tensor, float]:
        """What the Newton budget misses along one FE trajectory, as loads: e [S - 1, n] N such
        that the budgeted step (``iterations`` Newton iterations, no remainders) from the data's
        state s (u[s], v[s] [S, n], its Newmark acceleration and Prony history) under the load
        f[s + 1] + e[s] lands on the data's u[s + 1]; and the largest miss left, relative to the
        largest displacement (round-off where the corrections converged).

        The end of a budgeted step moves with its load as the inverse step matrix
        A = c0 m_f M + K_T of its last iteration's start (each iteration solves with the exact
        tangent; to first order in that start's residual), so e is corrected by
        e ← e + A (u[s + 1] − u1(e)), Newton's method for e: with one iteration a step the step is
        affine in its load and one correction is exact; with k, A is taken where k − 1 iterations
        under the current e end (``max_corrections`` at most, until the miss is below ``rtol``, or
        ``BUDGET_STALLED`` corrections in a row have not lowered it)."""
        with torch.no_grad():
            shortened, taken = self.shortened.clone(), self.newton_taken.clone()
            iterations, most = self.iterations, self.max_iterations
            a = self.accelerations(u, v, f)
            h = self.internal_history(u)
            u0, v0, a0, h0, f1, target = u[:-1], v[:-1], a[:-1], h[:-1], f[1:], u[1:]
            zero = torch.zeros_like(u0)
            _, _, extra, _, _, _, start_pairs = self.step_start(u0, v0, a0, h0)
            e = torch.zeros_like(u0)
            scale = float(target.abs().max().clamp(min=1e-300))
            miss, best, stalled = math.inf, math.inf, 0
            self.forget()
            try:
                self.max_iterations = iterations        # what a fixed budget of ``iterations`` leaves
                for _ in range(max_corrections):
                    gap = target - self.step(u0, v0, a0, f1 + e, zero, zero, h0)[0]       # [S - 1, n] m
                    miss = float(gap.abs().max()) / scale
                    stalled = stalled + 1 if miss >= best else 0
                    best = min(best, miss)
                    if miss <= rtol or stalled >= BUDGET_STALLED:     # reached, or no load reaches it
                        break
                    pairs = start_pairs
                    if iterations > 1:                  # the last iteration's start: k − 1 iterations' end
                        self.iterations = self.max_iterations = iterations - 1
                        last = self.step(u0, v0, a0, f1 + e, zero, zero, h0)[0]
                        self.iterations = self.max_iterations = iterations
                        pairs = self.tangent_pairs(self.cells(last), self.iso_weight + self.c, 1.0 + self.c, extra)
                    values, gap_np = self.sparse_values(pairs).cpu().numpy(), gap.cpu().numpy()   # [S - 1, nnz]
                    e = e + torch.as_tensor(np.stack([self.pattern.matrix(values[i]) @ gap_np[i]
                                                      for i in range(values.shape[0])]), dtype=e.dtype)
            finally:
                self.iterations, self.max_iterations = iterations, most
                self.forget()
                self.shortened.copy_(shortened)
                self.newton_taken.copy_(taken)
        return e, miss

    # --- the Prony history per cell (the FE's h_i) ----------------------------------------------
    def internal_variables(self, u: Tensor) -> Tensor:
        """h [B, T_prony, 6 T] at displacements u [B, n] applied at once: h_i = S_iso(F)."""
        if self.n_terms == 0:
            return u.new_zeros(u.shape[0], 0, 0)
        s = _voigt(self.law(self.cells(u))[0]).reshape(u.shape[0], 1, -1)
        return s.expand(-1, self.n_terms, -1).contiguous()

    def relax(self, u0: Tensor, u1: Tensor, h0: Tensor) -> Tensor:
        """h1 after a step from u0 to u1 [B, n]: h_i ← d_i h_i + w_i (S_iso(u1) − S_iso(u0))."""
        if self.n_terms == 0:
            return h0
        return self.relax_from(self.law(self.cells(u0))[0], u1, h0)

    def relax_from(self, S_iso0: Tensor, u1: Tensor, h0: Tensor) -> Tensor:
        """``relax`` with the step start's S_iso,0 [B, T, 3, 3] Pa already evaluated."""
        if self.n_terms == 0:
            return h0
        B = u1.shape[0]
        step = _voigt(self.law(self.cells(u1))[0] - S_iso0).reshape(B, 1, -1)
        return self.prony_decay.view(1, -1, 1) * h0 + self.prony_increment.view(1, -1, 1) * step

    def _law_relaxed(self, F: Tensor, h: Tensor) -> Tensor:
        """Σ ḡ_i (h_i − S_iso(F)) [B, T, 3, 3] Pa: what relaxation takes off the unrelaxed S."""
        return self._relaxed_from(self.law(F)[0], h)

    def _relaxed_from(self, S_iso: Tensor, h: Tensor) -> Tensor:
        """``_law_relaxed`` with the cells' S_iso [B, T, 3, 3] Pa already evaluated."""
        s = _matrix(h.reshape(h.shape[0], self.n_terms, self.n_cells, 6))                  # [B, T_p, T, 3, 3]
        return (self.prony_weight.view(1, -1, 1, 1, 1) * (s - S_iso.unsqueeze(1))).sum(1)

    def relaxation_force(self, u: Tensor, h: Tensor) -> Tensor:
        """Σ_e V_e F Σ ḡ_i (h_i − S_iso) Grad φ [B, n] N at displacements u [B, n] with the internal
        variables h of a step's end (f_int = f_el + this)."""
        F = self.cells(u)
        return self.assemble(F @ self._law_relaxed(F, h))

    def stress_relaxation(self, u: Tensor, h: Tensor) -> Tensor:
        """J⁻¹ F Σ ḡ_i (h_i − S_iso) Fᵀ [B, N, 6] Pa, volume-averaged at the nodes."""
        B = u.shape[0]
        if self.n_terms == 0:
            return u.new_zeros(B, self.n_nodes, 6)
        F = self.cells(u)
        J = torch.linalg.det(F)[..., None, None]
        return self.nodal(F @ self._law_relaxed(F, h) @ F.transpose(-1, -2) / J)

    def physical_state(self, X: Tensor, u: Tensor, v: Tensor, H: Optional[Tensor], h: Tensor) -> Tensor:
        """:meth:`NewmarkPrior.physical_state` [B, N, 12] (q m, v m/s, σ Pa) with the law evaluated
        once: σ = J⁻¹ F (S_iso + S_vol + Σ ḡ_i (h_i − S_iso)) Fᵀ + H, volume-averaged at the nodes
        (``stress`` and ``stress_relaxation`` together, which each evaluate it)."""
        U = self.scatter(u)                                                                 # [B, N, 3] m
        F = self.deformation_gradients(self.reference.unsqueeze(0) + U)                    # [B, T, 3, 3]
        s_iso, s_vol = self.law(F)
        S = s_iso + s_vol
        if self.n_terms > 0:
            S = S + self._relaxed_from(s_iso, h)
        sigma = self.nodal(F @ S @ F.transpose(-1, -2) / torch.linalg.det(F)[..., None, None])
        if H is not None:
            sigma = sigma + H
        return torch.cat([X.unsqueeze(0) + U, self.scatter(v), sigma], -1)

    def stress(self, u: Tensor, H: Optional[Tensor] = None) -> Tensor:
        """Nodal Cauchy stress σ = J⁻¹ F (S_iso + S_vol) Fᵀ + H [B, N, 6] Pa of the nodal
        displacements u [B, N, 3] m (unrelaxed; ``stress_relaxation`` adds the history's part),
        volume-averaged at the nodes as the dataset's."""
        F = self.deformation_gradients(self.reference.unsqueeze(0) + u)
        s_iso, s_vol = self.law(F)
        J = torch.linalg.det(F)[..., None, None]
        cell = self.nodal(F @ (s_iso + s_vol) @ F.transpose(-1, -2) / J)
        return cell if H is None else cell + H


__all__ = ["HyperelasticNewmarkPrior", "cofactor", "learned_tangent", "neo_hookean_pk2", "neo_hookean_tangent",
           "ogden_isochoric", "pk1_tangent",
           "ogden_isochoric_pk2", "ogden_tangent", "ogden_volumetric_pk2"]
