"""A learned hyperelastic law (``model.prior_material=learned``): the strain energy a law prior
steps, fitted to the training trajectories instead of read from the scene's material.

The law prior (:mod:`thermognn.train.law_prior`) steps the FE's own discretisation (P1 cells, the
stored mass, Rayleigh damping, Newmark rule) with a hyperelastic law and, for a viscous scene, its
Prony terms. With ``model.prior_material=data`` that law is the scene's (neo-Hookean or Ogden); with
``learned`` it is :class:`StrainEnergy`, an isotropic energy per unit reference volume

    Ψ(C) = Ψ_iso(Ī1, Ī2) + U(J)                                                        [J/m³]
    Ψ_iso = μ_s (c · x + Σ_k a_k (softplus(w_k · x + b_k) − softplus(b_k))),
    x     = ((Ī1 − 3)/s1, (Ī2 − 3)/s2)
    U     = κ_s (½ k0 y² + Σ_m e_m (softplus(v_m y + d_m) − softplus(d_m) − σ(d_m) v_m y)),  y = (J − 1)/s3

with Ī1 = J^(-2/3) tr C, Ī2 = J^(-4/3) ½((tr C)² − tr C²), J = √det C: one hidden softplus layer
in the two isochoric invariants, one in J. Any isotropic isochoric energy is a function of
(Ī1, Ī2); the family holds the neo-Hookean (Ψ_iso = C10 (Ī1 − 3)) and Mooney–Rivlin laws exactly
and approximates Ogden's. The isochoric stress vanishes at C = I for any weights (the invariants'
derivatives do), and U'(1) = 0 by construction, so the body is stress-free at rest (and Ψ(I) = 0). μ_s, κ_s
(the moduli at rest of ``/linear``) and s1..s3 (the training states' largest invariants) only
scale the network; its weights start from a zero linear part (``c = k0 = 0``) and small random
hidden ones, and are fitted to the data alone (:func:`fit_strain_energy`).

As the scene's laws (:func:`thermognn.train.law_prior.neo_hookean_pk2`), the stress
S = 2 ∂Ψ/∂C is in closed form (``pk2``): with ψ1, ψ2 = ∂Ψ_iso/∂Ī1, ∂Ψ_iso/∂Ī2,

    ∂Ī1/∂C = J^(-2/3) I − Ī1/3 C⁻¹,   ∂Ī2/∂C = J^(-4/3) (tr C I − C) − 2 Ī2/3 C⁻¹,
    S_iso = 2 (ψ1 ∂Ī1/∂C + ψ2 ∂Ī2/∂C),   S_vol = U'(J) J C⁻¹,

and so are S's derivatives along C's six symmetric directions (``pk2_differentials``), which the
law prior turns into the Newton tangent ∂P/∂F as it does Ogden's. The weights are buffers, not parameters: they are
fitted before the graph network trains and then held (a rollout's gradients pass them by), and
they travel in the model's state_dict, so a checkpoint or an exported file carries its law.

The fit (:func:`fit_strain_energy`) is equation error, not rollouts: along each training
trajectory the law prior's exact remainders (``NewmarkPrior.remainders``: what the data's own
balance M a + f_int(u) − f leaves per free DOF, and σ_data − σ_law per node) vanish for the data's
law, so the fit minimises their mean squares, each relative to the loads' and the stresses' RMS,
by L-BFGS over all of the weights at once. A viscous scene's Prony terms (as many as it declares)
are fitted with them (``model.prior_material_prony=learned``, :class:`PronySeries`): the
relaxation's weights and times enter the same remainders through the internal variables' history.
"""

from __future__ import annotations

import math
import time
from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from .data import spread
from .mat3 import det_inverse3

#: default hidden units (isochoric, volumetric): ``model.prior_material_hidden``
HIDDEN = (16, 8)
#: the fit's L-BFGS iterations (``train.law_fit_iterations``)
FIT_ITERATIONS = 150
#: ... on at most this many training trajectories (``train.law_fit_trajectories``)
FIT_TRAJECTORIES = 8
#: the fit reports its loss at most this often [s]
PROGRESS_SECONDS = 60.0
#: a training trajectory whose remainders under the fitted law exceed this many times the median
#: trajectory's (relative to its loads) is left out of the fit and fitted again without it: where
#: the FE cut its steps the data's step is not one Newmark step of Δt (the law prior's own rule)
OUTLIER_FACTOR = 20.0
#: StrainEnergy's fitted tensors, in order
WEIGHT_NAMES = ("iso_linear", "iso_weight", "iso_bias", "iso_out", "vol_quadratic", "vol_weight", "vol_bias", "vol_out")
#: the convex family (``model.prior_material_convex``): these weights non-negative (squares). Ψ_iso's Hessian in x
#: is μ_s Σ_k a_k σ_k (1 − σ_k) w_k w_kᵀ and U'' = κ_s (k0 + Σ_m e_m v_m² σ_m (1 − σ_m)) / s3², so
#: with a, k0, e >= 0 the energy is convex in x and in y whatever the other weights
CONVEX = ("iso_out", "vol_quadratic", "vol_out")
#: ... each starting from its random value's magnitude, at least this (relative to μ_s, κ_s)
CONVEX_START = 1e-3
#: the guard beyond the fitted states (``StrainEnergy.settle_guard``): it starts at this many times
#: the training states' largest invariants (within them the law is its fit's, mildly extrapolated:
#: a test case's rollout may pass the training split's largest, and a small dataset's test split
#: does), its stiffness sampled at this many points a side of the fitted box, and never softer than
#: this (relative to μ_s, κ_s per scaled invariant²)
GUARD_MARGIN = 2.0
GUARD_SAMPLES = 33
GUARD_FLOOR = 1e-6


class StrainEnergy(nn.Module):
    """The learned isotropic strain energy Ψ(C) (module docstring), hidden units ``hidden`` =
    (isochoric, volumetric), scaled by the moduli at rest mu, kappa [Pa] and the invariants'
    scales (s1, s2, s3). ``placeholder`` makes one the law prior holds but never evaluates (the
    scene's law steps), its buffers left out of the state_dict."""

    def __init__(self, hidden: Sequence[int] = HIDDEN, mu: float = 1.0, kappa: float = 1.0,
                 scales: Sequence[float] = (1.0, 1.0, 1.0), seed: int = 0, placeholder: bool = False,
                 dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        k, m = (int(h) for h in hidden)
        if k < 1 or m < 1:
            raise ValueError(f"the learned law's hidden units: {tuple(hidden)!r}, expected two integers >= 1")
        self.hidden = [k, m]
        self.mu_scale, self.kappa_scale = float(mu), float(kappa)
        self.placeholder = bool(placeholder)
        self.guard_margin = GUARD_MARGIN
        g = torch.Generator().manual_seed(int(seed))
        keep = not placeholder

        def buffer(name: str, value: Tensor) -> None:
            self.register_buffer(name, value.to(dtype), persistent=keep)

        buffer("scales", torch.tensor([float(s) for s in scales], dtype=torch.float64))   # [3] s1, s2, s3
        buffer("iso_linear", torch.zeros(2, dtype=torch.float64))                           # [2] c
        buffer("iso_weight", torch.randn(k, 2, generator=g, dtype=torch.float64))           # [k, 2] w
        buffer("iso_bias", torch.randn(k, generator=g, dtype=torch.float64))                # [k] b
        buffer("iso_out", 0.01 * torch.randn(k, generator=g, dtype=torch.float64))          # [k] a
        buffer("vol_quadratic", torch.zeros(1, dtype=torch.float64))                         # [1] k0
        buffer("vol_weight", torch.randn(m, generator=g, dtype=torch.float64))              # [m] v
        buffer("vol_bias", torch.randn(m, generator=g, dtype=torch.float64))                # [m] d
        buffer("vol_out", 0.01 * torch.randn(m, generator=g, dtype=torch.float64))          # [m] e
        # the guard's stiffness (g1, g2, g3) beyond twice the fitted box |x_i|, |y| <= 1 (``settle_guard``):
        # derived from the weights, so never stored; zero until they are settled
        self.register_buffer("guard", torch.zeros(3, dtype=dtype), persistent=False)     # [3]

    @torch.jit.unused
    def settle_guard(self) -> None:
        """Set the guard from the weights as they stand. The scales are the training states'
        largest |Ī1 − 3|, |Ī2 − 3|, |J − 1|, so the data lie within the box |x1|, |x2|, |y| <= 1
        (Ī >= 3: x >= 0); beyond it the family is only extrapolated, and a free fit may soften
        there (its softplus units grow linearly, with weights of either sign: the shipped liver
        law's energy falls as Ī2 grows, and under the sim's press a cell collapsed onto a state
        beyond its box, a converged step of the law; docs/accuracy.md, session 90). The guard adds

            Ψ_guard = μ_s ½ (g1 e1² + g2 e2²) + κ_s ½ g3 e3²,   e = the excess of x1, x2, y beyond ±m,

        m = ``GUARD_MARGIN`` (2): nothing within twice the box (the fit, every state of the data and
        a rollout passing its largest states mildly are unchanged: at m = 1 the tiny block's test
        split, beyond its small training split's states, was stepped 4× further from its data),
        and beyond it stiffens the law at least as fast as the law curves within the box, and at
        an excess of the box's own width adds at least the largest stress the law has within it
        (the liver's law falls beyond about 3 s1): g_i is the larger
        of the largest ∂²(Ψ/μ_s)/∂x_i² and |∂(Ψ/μ_s)/∂x_i| (∂²(U/κ_s)/∂y², |∂(U/κ_s)/∂y|) over the
        box, sampled at ``GUARD_SAMPLES`` points a side, at least ``GUARD_FLOOR``. The energy is
        then bounded below (the family grows at most linearly) and C¹: the stress continuous, its
        tangent jumping by μ_s g_i / s_i² where the guard starts."""
        with torch.no_grad():
            t = torch.linspace(0.0, 1.0, GUARD_SAMPLES, dtype=self.iso_weight.dtype)
            x = torch.stack(torch.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)           # [P, 2] x >= 0
            sig = torch.sigmoid(self.iso_preactivation(x))                                   # [P, k]
            slope = self.iso_linear + (sig * self.iso_out) @ self.iso_weight                  # [P, 2] ∂(Ψ/μ_s)/∂x
            curvature = (sig * (1.0 - sig) * self.iso_out) @ self.iso_weight.pow(2)          # [P, 2] ∂²/∂x_i²
            y = torch.linspace(-1.0, 1.0, 2 * GUARD_SAMPLES - 1, dtype=self.vol_weight.dtype).unsqueeze(-1)
            sv = torch.sigmoid(y * self.vol_weight + self.vol_bias)                          # [P, m]
            dU = self.vol_quadratic * y + (self.vol_out * self.vol_weight * (sv - torch.sigmoid(self.vol_bias))
                                           ).sum(-1, True)                                     # [P, 1] ∂(U/κ_s)/∂y
            ddU = self.vol_quadratic + (self.vol_out * self.vol_weight.pow(2) * sv * (1.0 - sv)).sum(-1, True)
            most = torch.cat([torch.maximum(curvature.amax(0), slope.abs().amax(0)),
                              torch.maximum(ddU.amax(0), dU.abs().amax(0))])                 # [3]
            self.guard.copy_(most.clamp(min=GUARD_FLOOR).to(self.guard.dtype))

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        super()._load_from_state_dict(*args, **kwargs)
        if not self.placeholder:               # weights loaded: their guard
            self.settle_guard()

    def excess(self, x: Tensor) -> Tensor:
        """How far scaled invariants x [...] lie beyond the guard's start, ``GUARD_MARGIN`` times the
        fitted box, signed: x − m above it, x + m below it, 0 within."""
        return x - x.clamp(min=-self.guard_margin, max=self.guard_margin)

    @torch.jit.unused
    def weights(self) -> List[Tensor]:
        """The fitted tensors (all but the scales), in the order of ``WEIGHT_NAMES``."""
        return [getattr(self, name) for name in WEIGHT_NAMES]

    def invariants(self, C: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(Ī1, Ī2, J, C⁻¹) of right Cauchy–Green tensors C [..., 3, 3]: [...] each, C⁻¹ [..., 3, 3]."""
        det, Ci = det_inverse3(C)                                                         # closed form (mat3)
        J = torch.sqrt(det)
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        I2 = 0.5 * (I1 * I1 - (C * C).sum((-2, -1)))
        a = J.pow(-2.0 / 3.0)
        return a * I1, a * a * I2, J, Ci

    def iso_preactivation(self, x: Tensor) -> Tensor:
        """w_k · x + b_k [..., k] of scaled invariants x [..., 2]: one addmm over the rows (``x @ wᵀ``
        on a stack [B, T, 2] took 6× as long on the liver's cells, a batched product against a
        transposed weight)."""
        k = self.iso_weight.shape[0]
        rows = torch.addmm(self.iso_bias, x.reshape(-1, 2), self.iso_weight.t())              # [R, k]
        return rows.reshape(list(x.shape[:-1]) + [k])

    def iso_contract(self, h: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        """bias + h @ weight [..., j] of hidden values h [..., k] and weight [k, j] (one addmm over the
        rows, as ``iso_preactivation``)."""
        k, j = weight.shape[0], weight.shape[1]
        return torch.addmm(bias, h.reshape(-1, k), weight).reshape(list(h.shape[:-1]) + [j])

    def energy_derivatives(self, I1b: Tensor, I2b: Tensor, J: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """(ψ1 = ∂Ψ_iso/∂Ī1, ψ2 = ∂Ψ_iso/∂Ī2, U'(J)) [...] Pa at the invariants [...]."""
        s = self.scales
        x = torch.stack([(I1b - 3.0) / s[0], (I2b - 3.0) / s[1]], -1)                    # [..., 2]
        sig = torch.sigmoid(self.iso_preactivation(x))                                     # [..., k]
        dx = self.iso_contract(sig, self.iso_out.unsqueeze(-1) * self.iso_weight, self.iso_linear) \
            + self.guard[0:2] * self.excess(x)                                             # [..., 2] ∂Ψ/∂x / μ_s
        y = ((J - 1.0) / s[2]).unsqueeze(-1)                                               # [..., 1]
        sv = torch.sigmoid(y * self.vol_weight + self.vol_bias)                            # [..., m]
        dU = ((self.vol_quadratic * y) + self.guard[2] * self.excess(y)).squeeze(-1) + (
            self.vol_out * self.vol_weight * (sv - torch.sigmoid(self.vol_bias))).sum(-1)   # [...] U'/κ_s·s3
        return (self.mu_scale * dx[..., 0] / s[0], self.mu_scale * dx[..., 1] / s[1],
                self.kappa_scale * dU / s[2])

    def energy(self, C: Tensor) -> Tensor:
        """Ψ(C) [...] J/m³ (not needed by a step; for tests and reports)."""
        iso, vol = self.energy_parts(C)
        return iso + vol

    def energy_parts(self, C: Tensor) -> Tuple[Tensor, Tensor]:
        """(Ψ_iso, U) [...] J/m³ of C [..., 3, 3]: the isochoric and volumetric parts of ``energy``
        (their 2 ∂/∂C are ``pk2``'s S_iso and S_vol)."""
        I1b, I2b, J, _ = self.invariants(C)
        s = self.scales
        x = torch.stack([(I1b - 3.0) / s[0], (I2b - 3.0) / s[1]], -1)
        sp = torch.nn.functional.softplus(self.iso_preactivation(x))
        rest = torch.nn.functional.softplus(self.iso_bias)
        iso = (x * self.iso_linear).sum(-1) + ((sp - rest) * self.iso_out).sum(-1) \
            + 0.5 * (self.guard[0:2] * self.excess(x).pow(2)).sum(-1)
        y = ((J - 1.0) / s[2]).unsqueeze(-1)
        z = y * self.vol_weight + self.vol_bias
        vol = 0.5 * (self.vol_quadratic * y * y + self.guard[2] * self.excess(y).pow(2)).squeeze(-1) + (self.vol_out * (
            torch.nn.functional.softplus(z) - torch.nn.functional.softplus(self.vol_bias)
            - torch.sigmoid(self.vol_bias) * self.vol_weight * y)).sum(-1)
        return self.mu_scale * iso, self.kappa_scale * vol

    def geometry(self, C: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """What the stress takes from C [..., 3, 3] alone, whatever the weights: (Ī1, Ī2, J [...],
        J C⁻¹, ∂Ī1/∂C, ∂Ī2/∂C [..., 3, 3])."""
        I1b, I2b, J, Ci = self.invariants(C)
        eye = torch.eye(3, dtype=C.dtype, device=C.device)
        a = J.pow(-2.0 / 3.0)[..., None, None]
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]
        dI1 = a * eye - (I1b / 3.0)[..., None, None] * Ci
        dI2 = a * a * (I1 * eye - C) - (2.0 * I2b / 3.0)[..., None, None] * Ci
        return I1b, I2b, J, J[..., None, None] * Ci, dI1, dI2

    def stress(self, I1b: Tensor, I2b: Tensor, J: Tensor, JCi: Tensor, dI1: Tensor, dI2: Tensor
               ) -> Tuple[Tensor, Tensor]:
        """(S_iso, S_vol) [..., 3, 3] Pa of ``geometry``'s tensors: 2 (ψ1 ∂Ī1/∂C + ψ2 ∂Ī2/∂C), U' J C⁻¹."""
        psi1, psi2, dU = self.energy_derivatives(I1b, I2b, J)
        S_iso = 2.0 * (psi1[..., None, None] * dI1 + psi2[..., None, None] * dI2)
        return S_iso, dU[..., None, None] * JCi

    @torch.jit.export
    def pk2(self, C: Tensor) -> Tuple[Tensor, Tensor]:
        """(S_iso, S_vol) [..., 3, 3] Pa, S = 2 ∂Ψ/∂C at C [..., 3, 3] (module docstring), as ``stress``
        of ``geometry`` gives them (to round-off) with the invariants' derivatives gathered per cell
        first (fewer operations on the cells' 3×3 stacks; a law step evaluates it every iteration):

            S_iso = α I + β C + γ C⁻¹,   α = 2 a (ψ1 + a I1 ψ2),  β = −2 a² ψ2,  γ = −⅔ (ψ1 Ī1 + 2 ψ2 Ī2),
            S_vol = U'(J) J C⁻¹,        a = J^(-2/3)."""
        I1b, I2b, J, Ci = self.invariants(C)
        psi1, psi2, dU = self.energy_derivatives(I1b, I2b, J)                            # [...] Pa each
        a = J.pow(-2.0 / 3.0)
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        alpha = 2.0 * a * (psi1 + a * I1 * psi2)                                           # [...]
        beta = -2.0 * a * a * psi2
        gamma = -(2.0 / 3.0) * (psi1 * I1b + 2.0 * psi2 * I2b)
        eye = torch.eye(3, dtype=C.dtype, device=C.device)
        S_iso = alpha[..., None, None] * eye + beta[..., None, None] * C + gamma[..., None, None] * Ci
        return S_iso, (dU * J)[..., None, None] * Ci

    def energy_second_derivatives(self, I1b: Tensor, I2b: Tensor, J: Tensor
                                  ) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(ψ11, ψ12, ψ22, U''(J)) [...] Pa: the energy's second derivatives in Ī1, Ī2 and J."""
        s = self.scales
        x = torch.stack([(I1b - 3.0) / s[0], (I2b - 3.0) / s[1]], -1)                    # [..., 2]
        sig = torch.sigmoid(self.iso_preactivation(x))                                     # [..., k]
        w1, w2 = self.iso_weight[:, 0], self.iso_weight[:, 1]
        pairs = self.iso_out.unsqueeze(-1) * torch.stack([w1 * w1, w1 * w2, w2 * w2], -1)  # [k, 3] a_k w_ki w_kj
        second = self.iso_contract(sig * (1.0 - sig), pairs, self.iso_linear.new_zeros(3))  # [..., 3] (11, 12, 22)
        mu = self.mu_scale
        y = ((J - 1.0) / s[2]).unsqueeze(-1)
        sv = torch.sigmoid(y * self.vol_weight + self.vol_bias)                            # [..., m]
        ddU = self.vol_quadratic + (self.vol_out * self.vol_weight * self.vol_weight * sv * (1.0 - sv)).sum(-1, True) \
            + self.guard[2] * (self.excess(y) != 0).to(y.dtype)                            # [..., 1]
        beyond = (self.excess(x) != 0).to(x.dtype) * self.guard[0:2]                       # [..., 2] the guard's
        return (mu * (second[..., 0] + beyond[..., 0]) / (s[0] * s[0]),
                mu * second[..., 1] / (s[0] * s[1]),
                mu * (second[..., 2] + beyond[..., 1]) / (s[1] * s[1]),
                self.kappa_scale * ddU.squeeze(-1) / (s[2] * s[2]))

    @torch.jit.export
    def pk2_differentials(self, C: Tensor, E: Tensor) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """(S_iso, S_vol) [..., 3, 3] Pa as ``pk2`` gives them, and (dS_iso, dS_vol) [6, ..., 3, 3]
        Pa along C's directions E [6, 1.., 3, 3] (one evaluation of the invariants and the energy's
        derivatives for both), in closed form: with e = C⁻¹ : E, t = tr E, a = J^(-2/3), dJ = J e / 2, dC⁻¹ = −C⁻¹ E C⁻¹,

            dĪ1 = a t − Ī1 e / 3,   dĪ2 = a² (I1 t − C : E) − 2 Ī2 e / 3,
            d∂Ī1/∂C = −a e / 3 I − dĪ1 / 3 C⁻¹ − Ī1 / 3 dC⁻¹,
            d∂Ī2/∂C = −2 a² e / 3 (I1 I − C) + a² (t I − E) − 2 dĪ2 / 3 C⁻¹ − 2 Ī2 / 3 dC⁻¹,
            dS_iso = 2 (dψ1 ∂Ī1/∂C + ψ1 d∂Ī1/∂C + dψ2 ∂Ī2/∂C + ψ2 d∂Ī2/∂C),  dψ_k = Σ_l ψ_kl dĪ_l,
            dS_vol = (U'' J + U') dJ C⁻¹ + U' J dC⁻¹."""
        I1b, I2b, J, JCi, dI1, dI2 = self.geometry(C)
        psi1, psi2, dU = self.energy_derivatives(I1b, I2b, J)
        p11, p12, p22, ddU = self.energy_second_derivatives(I1b, I2b, J)
        Ci = JCi / J[..., None, None]
        eye = torch.eye(3, dtype=C.dtype, device=C.device)
        a = J.pow(-2.0 / 3.0)
        I1 = C.diagonal(dim1=-2, dim2=-1).sum(-1)
        e = (Ci * E).sum((-2, -1))                                                         # [6, ...]
        t = E.diagonal(dim1=-2, dim2=-1).sum(-1)                                           # [6, 1..]
        CE = (C * E).sum((-2, -1))
        dCi = -(Ci @ E @ Ci)                                                               # [6, ..., 3, 3]
        dJ = 0.5 * J * e
        dI1b = a * t - I1b * e / 3.0
        dI2b = a * a * (I1 * t - CE) - 2.0 * I2b * e / 3.0
        m = [6] + [1] * (C.dim() - 2)
        ddI1 = (-(a * e / 3.0))[..., None, None] * eye - (dI1b / 3.0)[..., None, None] * Ci \
            - (I1b / 3.0)[..., None, None] * dCi
        ddI2 = (-(2.0 * a * a * e / 3.0))[..., None, None] * (I1[..., None, None] * eye - C) \
            + (a * a)[..., None, None] * (t.reshape(m)[..., None, None] * eye - E) \
            - (2.0 * dI2b / 3.0)[..., None, None] * Ci - (2.0 * I2b / 3.0)[..., None, None] * dCi
        dpsi1 = p11 * dI1b + p12 * dI2b
        dpsi2 = p12 * dI1b + p22 * dI2b
        dS_iso = 2.0 * (dpsi1[..., None, None] * dI1 + psi1[..., None, None] * ddI1
                        + dpsi2[..., None, None] * dI2 + psi2[..., None, None] * ddI2)
        dS_vol = ((ddU * J + dU) * dJ)[..., None, None] * Ci + (dU * J)[..., None, None] * dCi
        S_iso = 2.0 * (psi1[..., None, None] * dI1 + psi2[..., None, None] * dI2)
        return S_iso, dU[..., None, None] * JCi, dS_iso, dS_vol


class EquationError:
    """The law prior's exact remainders along one trajectory (``NewmarkPrior.remainders``: G [S, n]
    N, H [S, N, 6] Pa) as functions of a learned law's weights and Prony constants, for the fit:
    what does not depend on them (the cells' F and ``StrainEnergy.geometry`` at the data's
    states, the inertia M (a + αM v) − f − f_body) formed once, the rest vectorised over the steps.
    ``prior`` the law prior, z [S, N, 12], f [S, N, 3] the trajectory, X [N, 3] m, a [S, n] its
    Newmark accelerations (tests/test_law_prior.py: equal to ``remainders`` to round-off)."""

    def __init__(self, prior, z: Tensor, f: Tensor, X: Tensor, a: Tensor) -> None:
        self.prior = prior
        with torch.no_grad():
            u, v = prior.gather(z[..., 0:3] - X), prior.gather(z[..., 3:6])
            self.F = prior.cells(u)                                                       # [S, T, 3, 3]
            self.Ft = self.F.transpose(-1, -2)
            self.geometry = prior.learned_law.geometry(self.Ft @ self.F)
            self.inertia = prior.mass(a[1:] + prior.alpha_m * v[1:]) - prior.gather(f[1:]) - prior.body_force
            self.sigma = z[..., 6:12]

    def __call__(self, g: Optional[Tensor] = None, d: Optional[Tensor] = None,
                 w: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
        """(G [S, n] N, H [S, N, 6] Pa) under the law's weights as they stand and the Prony
        constants g, d, w [T_p] (``PronySeries.terms``; None: the prior's own)."""
        p = self.prior
        S_iso, S_vol = p.learned_law.stress(*self.geometry)                               # [S, T, 3, 3] each
        S = S_iso + S_vol
        elastic = p.assemble(self.F @ S)                                                  # [S, n] f_el
        f_int = elastic[1:]
        if p.n_terms > 0:
            g = p.prony_weight if g is None else g
            d = p.prony_decay if d is None else d
            w = p.prony_increment if w is None else w
            h = S_iso[0].unsqueeze(0).expand(p.n_terms, -1, -1, -1)                      # [T_p, T, 3, 3]
            relaxed = [(g.view(-1, 1, 1, 1) * (h - S_iso[0])).sum(0)]
            for k in range(1, S_iso.shape[0]):
                h = d.view(-1, 1, 1, 1) * h + w.view(-1, 1, 1, 1) * (S_iso[k] - S_iso[k - 1])
                relaxed.append((g.view(-1, 1, 1, 1) * (h - S_iso[k])).sum(0))
            relaxed = torch.stack(relaxed)                                                # [S, T, 3, 3]
            f_int = f_int + p.assemble(self.F[1:] @ relaxed[1:])
            S = S + relaxed
        lumped = self.inertia + p.c * (elastic[1:] - elastic[:-1]) + f_int
        J = self.geometry[2][..., None, None]
        return p.carried_remainders(lumped), self.sigma - p.nodal(self.F @ S @ self.Ft / J)


def invariant_scales(C: Tensor) -> Tuple[float, float, float]:
    """(s1, s2, s3): the largest |Ī1 − 3|, |Ī2 − 3|, |J − 1| over cells' C [..., 3, 3] (at least 1e-6)."""
    law = StrainEnergy(placeholder=True)
    I1b, I2b, J, _ = law.invariants(C)
    return tuple(max(float(v.abs().max()), 1e-6) for v in (I1b - 3.0, I2b - 3.0, J - 1.0))


#: the ellipticity check (``ellipticity``): deformations sampled within the box, direction pairs
#: each, the floor the fit's penalty keeps the acoustic values above (relative to μ_s; the liver's
#: own Ogden law, α = 16.19, comes down to 0.01 μ at twice its data's box)
ELLIPTIC_SAMPLES = 1024
ELLIPTIC_DIRECTIONS = 12
ELLIPTIC_FLOOR = 1e-3


def principal_deformations(scales: Sequence[float], bound: float, count: int = ELLIPTIC_SAMPLES,
                           seed: int = 0) -> Tensor:
    """``count`` diagonal deformation gradients F [count, 3, 3] (principal stretches; an isotropic
    law needs no other) whose scaled invariants |Ī1 − 3|/s1, |Ī2 − 3|/s2, |J − 1|/s3 are within
    ``bound`` (J at least 0.05): J uniform over its range, the isochoric stretches
    exp(a), exp(b), exp(−a−b) with a, b uniform over ±√(bound·max(s1, s2)), drawn until enough fall in."""
    s1, s2, s3 = (float(v) for v in scales)
    g = torch.Generator().manual_seed(int(seed))
    spread = math.sqrt(bound * max(s1, s2))
    kept: List[Tensor] = []
    have = 0
    for _ in range(200):
        J = (1.0 - bound * s3) + 2.0 * bound * s3 * torch.rand(4 * count, generator=g, dtype=torch.float64)
        J = J.clamp(min=0.05)
        ab = spread * (2.0 * torch.rand(4 * count, 2, generator=g, dtype=torch.float64) - 1.0)
        iso = torch.exp(torch.stack([ab[:, 0], ab[:, 1], -ab[:, 0] - ab[:, 1]], -1))      # [4 count, 3] λ̄
        I1b = iso.pow(2).sum(-1)
        I2b = iso.pow(-2).sum(-1)                                                          # λ̄1 λ̄2 λ̄3 = 1
        inside = ((I1b - 3.0).abs() <= bound * s1) & ((I2b - 3.0).abs() <= bound * s2)
        lam = iso[inside] * J[inside].pow(1.0 / 3.0).unsqueeze(-1)                          # [n, 3] λ
        kept.append(lam)
        have += lam.shape[0]
        if have >= count:
            break
    lam = torch.cat(kept)[:count]
    return torch.diag_embed(lam)                                                           # [count, 3, 3]


def direction_pairs(count: int, per: int = ELLIPTIC_DIRECTIONS, seed: int = 0) -> Tuple[Tensor, Tensor]:
    """Unit vectors (m, n) [count, per, 3] each: the nine pairs of principal axes, then random pairs."""
    g = torch.Generator().manual_seed(int(seed) + 1)
    eye = torch.eye(3, dtype=torch.float64)
    axes_m = eye.repeat_interleave(3, 0)                                                   # [9, 3]
    axes_n = eye.repeat(3, 1)                                                              # [9, 3]
    m = torch.nn.functional.normalize(torch.randn(count, per, 3, generator=g, dtype=torch.float64), dim=-1)
    n = torch.nn.functional.normalize(torch.randn(count, per, 3, generator=g, dtype=torch.float64), dim=-1)
    k = min(per, 9)
    m[:, :k], n[:, :k] = axes_m[:k], axes_n[:k]
    return m, n


def acoustic_values(law: StrainEnergy, F: Tensor, m: Tensor, n: Tensor, create_graph: bool = False) -> Tensor:
    """(m ⊗ n) : A : (m ⊗ n) [P, K] Pa, A = ∂P/∂F the law's first elasticity tensor (P = F S the first
    Piola–Kirchhoff stress) at F [P, 3, 3], for the unit direction pairs m, n [P, K, 3]. The law is
    strongly elliptic at F (its waves travel, its strain cannot localise) where every value is
    positive; ``create_graph`` keeps them differentiable in the law's weights (the fit's penalty)."""
    P_, K = m.shape[0], m.shape[1]
    D = m.unsqueeze(-1) * n.unsqueeze(-2)                                                  # [P, K, 3, 3] m ⊗ n
    Fk = F.unsqueeze(1).expand(P_, K, 3, 3).reshape(-1, 3, 3).detach().requires_grad_(True)  # [P K, 3, 3]
    S_iso, S_vol = law.pk2(Fk.transpose(-1, -2) @ Fk)
    first = Fk @ (S_iso + S_vol)                                                           # [P K, 3, 3] P
    D = D.reshape(-1, 3, 3)
    (AD,) = torch.autograd.grad((first * D).sum(), Fk, create_graph=True)                  # [P K, 3, 3] A : D
    q = (AD * D).sum((-2, -1)).reshape(P_, K)
    return q if create_graph else q.detach()


def ellipticity_penalty(law: StrainEnergy, F: Tensor, m: Tensor, n: Tensor) -> Tensor:
    """The mean square of the acoustic values (``acoustic_values`` at F [P, 3, 3], directions m, n
    [P, K, 3]) below ``ELLIPTIC_FLOOR`` μ_s, each relative to μ_s: zero where the law is strongly
    elliptic by that margin, differentiable in its weights (the fit's ``elliptic`` term)."""
    q = acoustic_values(law, F, m, n, create_graph=True) / law.mu_scale                   # [P, K]
    return torch.relu(ELLIPTIC_FLOOR - q).pow(2).mean()


def ellipticity(law: StrainEnergy, bound: float = 1.0, count: int = ELLIPTIC_SAMPLES, seed: int = 0) -> dict:
    """How far the law is from losing strong ellipticity over deformations within ``bound`` times its
    fitted box (``principal_deformations``): {"min": the smallest acoustic value over them relative to
    μ_s (1 for a neo-Hookean law at rest, negative: not elliptic there), "fraction": the share of
    deformations with a non-positive value, "where": (λ1, λ2, λ3) of the worst}. A law fitted to
    data can lose it between the states it saw, where its own data's law keeps it (the liver's
    free fit, shipped in session 86: docs/accuracy.md, session 94)."""
    F = principal_deformations(law.scales.tolist(), bound, count, seed)
    m, n = direction_pairs(F.shape[0], seed=seed)
    with torch.enable_grad():
        q = acoustic_values(law, F, m, n).amin(-1) / law.mu_scale                          # [P]
    worst = int(torch.argmin(q))
    return {"min": float(q[worst]), "fraction": float((q <= 0).to(q.dtype).mean()),
            "where": [float(v) for v in F[worst].diagonal()]}


class PronySeries(nn.Module):
    """Learned Prony terms (ḡ_i, τ_i) of a viscous law, as many as the scene declares: the weights
    (g∞, ḡ_1, ..) = softmax(logits), so each is positive and g∞ = 1 − Σ ḡ_i > 0, and τ_i = exp(log τ_i)
    [s], started equal (ḡ_i = 1/(T+1)) at τ log-spaced from half the trajectories' duration to
    five times it (``duration`` [s])."""

    def __init__(self, n_terms: int, duration: float) -> None:
        super().__init__()
        self.logits = nn.Parameter(torch.zeros(int(n_terms) + 1, dtype=torch.float64))
        spread = torch.linspace(math.log(5.0 * duration), math.log(0.5 * duration), int(n_terms), dtype=torch.float64)
        if n_terms == 1:
            spread = torch.full((1,), math.log(duration), dtype=torch.float64)
        self.log_tau = nn.Parameter(spread)

    def terms(self, dt: float) -> Tuple[Tensor, Tensor, Tensor]:
        """(ḡ_i, d_i = exp(−Δt/τ_i), w_i = τ_i/Δt (1 − d_i)) [T] over a step Δt [s]: the law prior's
        ``prony_weight``, ``prony_decay``, ``prony_increment`` (``LinearSolid.relaxation``)."""
        g = torch.softmax(self.logits, 0)[1:]
        x = dt / torch.exp(self.log_tau)
        return g, torch.exp(-x), -torch.expm1(-x) / x

    def values(self) -> List[Tuple[float, float]]:
        """[(ḡ_i, τ_i [s])] as plain floats (a checkpoint's ``law_prony``)."""
        g = torch.softmax(self.logits.detach(), 0)[1:]
        return [(float(a), float(b)) for a, b in zip(g, torch.exp(self.log_tau.detach()))]


def convex_roots(law: "StrainEnergy", names: Sequence[str] = CONVEX) -> dict:
    """The convex family's start (``model.prior_material_convex``): each of ``names`` (of ``CONVEX``)
    its random value's magnitude, at least ``CONVEX_START``; returned as {name: its square root}, the
    tensors a fit adjusts (the law's weight is then the root squared, never negative)."""
    with torch.no_grad():
        return {name: getattr(law, name).abs().clamp(min=CONVEX_START).sqrt() for name in names}


def widest_first(trajs: list, extents: Tensor, k: int) -> list:
    """At most k of ``trajs`` for the learned law's fit (``train.law_fit_pick=widest``): first the
    ones reaching the training states' largest |Ī1 − 3|, |Ī2 − 3| and |J − 1| (``extents`` [n, 3],
    each trajectory's largest, ``invariant_scales``), then the rest evenly through the others
    (``spread``), in the list's order. A law fitted by equation error is only known on the states
    its trajectories pass through; beyond them a free family may soften, so the fit sees the
    widest the training split reaches."""
    if k >= len(trajs):
        return list(trajs)
    widest = []
    for column in extents.T:                    # [n] one invariant's largest per trajectory
        i = int(torch.argmax(column))
        if i not in widest:
            widest.append(i)
    widest = widest[:k]
    others = [i for i in range(len(trajs)) if i not in widest]
    chosen = set(widest) | set(spread(others, k - len(widest)))
    return [t for i, t in enumerate(trajs) if i in chosen]


def fit_strain_energy(prior, trajs, X: Tensor, iterations: int = FIT_ITERATIONS,
                      max_trajectories: int = FIT_TRAJECTORIES, log=print, prony: bool = False,
                      convex: bool = False, extents: Optional[Tensor] = None, elliptic: float = 0.0) -> dict:
    """Fit the law prior's learned law ``prior.learned_law`` (a :class:`StrainEnergy`) to the
    training trajectories ``trajs`` (``z`` [S, N, 12], ``force`` [S, N, 3], ``name``) by
    equation error (module docstring), X [N, 3] m the reference positions: at most
    ``max_trajectories`` of them, evenly through the list (a law has some hundred weights; each of
    its trajectories gives thousands of cell states), or with ``extents`` [len(trajs), 3] (each
    trajectory's largest |Ī1 − 3|, |Ī2 − 3|, |J − 1|) the widest ones first (``widest_first``). Where one
    trajectory's remainders stay above ``OUTLIER_FACTOR`` times the median's it is left out and the
    fit goes on without it. With ``prony`` (a viscous prior) its Prony terms are fitted too
    (:class:`PronySeries`, as many as it has) and left in its ``prony_*`` buffers. With ``convex``
    the fit keeps the energy convex in x and in y (``CONVEX``: the hidden units' output weights and
    k0 fitted by their square roots, so never negative), so it cannot soften beyond the states it saw.
    With ``elliptic`` > 0 the loss adds that weight times the mean square of the acoustic values
    below ``ELLIPTIC_FLOOR`` μ_s (each relative to μ_s) over ``ELLIPTIC_SAMPLES`` deformations within the
    guard's start (``GUARD_MARGIN`` times the box) and ``ELLIPTIC_DIRECTIONS`` direction pairs each
    (``ellipticity``): the fitted law stays strongly elliptic where the data's does (a free fit of the
    liver's Ogden data lost it over a fifth of its own box; docs/accuracy.md, session 94). Returns a report
    {"seconds", "iterations", "force", "stress" (the final RMS remainders relative to the loads'
    and the stresses' RMS), "left_out" [(name, ratio)], "prony" [(ḡ_i, τ_i)] (None: not fitted),
    "ellipticity" (``ellipticity`` over the box and over twice it)}."""
    law = prior.learned_law
    free = prior.free_nodes()
    trajs = spread(trajs, max_trajectories) if extents is None else widest_first(trajs, extents, max_trajectories)
    data = [(t.z.double(), t.force.double(), t.name) for t in trajs]
    with torch.no_grad():                      # the data's Newmark accelerations: the law's at rest only (S(I) = 0)
        accelerations = [prior.accelerations(prior.gather(z[..., 0:3] - X), prior.gather(z[..., 3:6]),
                                             prior.gather(f)) for z, f, _ in data]
    errors = [EquationError(prior, z, f, X, a) for (z, f, _), a in zip(data, accelerations)]
    load_rms = torch.cat([f[:, free] for _, f, _ in data]).pow(2).mean().sqrt().clamp(min=1e-300)
    stress_rms = torch.cat([z[..., 6:12].reshape(-1, 6) for z, _, _ in data]).pow(2).mean().sqrt()
    stress_rms = stress_rms.clamp(min=1e-300)
    positive = convex_roots(law) if convex else {}   # the convex family's non-negative weights, by their square roots
    weights = [w for w, name in zip(law.weights(), WEIGHT_NAMES) if name not in positive]
    roots = list(positive.values())
    for w in weights + roots:
        w.requires_grad_(True)

    def positive_weights() -> None:            # the law's buffers from their square roots (in the graph)
        for name, root in positive.items():
            setattr(law, name, root * root)
    series = None
    if prony and prior.n_terms > 0:
        duration = float(trajs[0].z.shape[0] - 1) * float(prior.dt)
        series = PronySeries(prior.n_terms, duration)
    t0, calls = time.perf_counter(), [0]
    shown = [t0]
    if elliptic < 0.0 or not math.isfinite(elliptic):
        raise ValueError(f"the learned law's ellipticity weight: {elliptic!r}, expected a number >= 0")
    if elliptic > 0.0:                         # the penalty's deformations and directions, fixed (L-BFGS)
        sampled = principal_deformations(law.scales.tolist(), GUARD_MARGIN, ELLIPTIC_SAMPLES)   # [P, 3, 3]
        pairs = direction_pairs(sampled.shape[0])                                          # [P, K, 3] each

    def softening() -> Tensor:                 # the ellipticity penalty (0 without one)
        if elliptic <= 0.0:
            return torch.zeros((), dtype=torch.float64)
        return elliptic * ellipticity_penalty(law, sampled, *pairs)

    def residuals(chosen):
        terms = (None, None, None) if series is None else series.terms(float(prior.dt))
        positive_weights()
        out = []
        for _, _, _, error in chosen:
            G, H = error(*terms)
            out.append((G.pow(2).mean() / load_rms**2, H.pow(2).mean() / stress_rms**2))
        return out

    def run(chosen, n):
        fitted = weights + roots + ([] if series is None else list(series.parameters()))
        opt = torch.optim.LBFGS(fitted, lr=1.0, max_iter=n, history_size=50, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-14, tolerance_change=1e-16)

        def closure():
            opt.zero_grad()
            parts = residuals(chosen)
            loss = sum(g + h for g, h in parts) / len(parts) + softening()
            loss.backward()
            calls[0] += 1
            if time.perf_counter() - shown[0] > PROGRESS_SECONDS:   # a fit of some minutes says where it is
                shown[0] = time.perf_counter()
                log(f"train: fitting the learned law: evaluation {calls[0]}, loss {float(loss.detach()):.3e} "
                    f"({shown[0] - t0:.0f} s)")
            return loss

        opt.step(closure)

    data = [(z, f, name, error) for (z, f, name), error in zip(data, errors)]
    left_out: List[Tuple[str, float]] = []
    try:
        run(data, iterations)
        with torch.no_grad():
            ratios = [float(g.sqrt()) for g, _ in residuals(data)]
        median = sorted(ratios)[len(ratios) // 2]
        keep = [d for d, r in zip(data, ratios) if r <= OUTLIER_FACTOR * max(median, 1e-12)]
        left_out = [(d[2], r) for d, r in zip(data, ratios) if r > OUTLIER_FACTOR * max(median, 1e-12)]
        if left_out and keep:
            run(keep, iterations)
        else:
            keep = data
        with torch.no_grad():
            parts = residuals(keep)
    finally:
        for w in weights + roots:
            w.requires_grad_(False)
        with torch.no_grad():
            positive_weights()
        law.settle_guard()                         # the fitted law's guard beyond its states
        if series is not None:
            with torch.no_grad():
                prior.prony_weight, prior.prony_decay, prior.prony_increment = series.terms(float(prior.dt))
    force = math.sqrt(sum(float(g) for g, _ in parts) / len(parts))
    stress = math.sqrt(sum(float(h) for _, h in parts) / len(parts))
    if not (math.isfinite(force) and math.isfinite(stress)):
        raise RuntimeError("prior: a non-finite state while fitting the learned law")
    report = {"seconds": time.perf_counter() - t0, "iterations": calls[0], "force": force, "stress": stress,
              "left_out": left_out, "trajectories": len(keep),
              "prony": None if series is None else series.values(),
              "ellipticity": {"box": ellipticity(law, 1.0), "guard": ellipticity(law, GUARD_MARGIN)}}
    log(f"train: the learned law{' (convex)' if convex else ''} fitted to {len(keep)} training trajectories in {report['seconds']:.0f} s "
        f"({calls[0]} evaluations): RMS force remainder {force:.3e} of the loads, stress {stress:.3e} of σ"
        + ("; Prony terms (g, tau [s]) " + ", ".join(f"({g:.4g}, {t:.4g})" for g, t in report["prony"])
           if report["prony"] else "")
        + (f"; {len(left_out)} left out (the FE cut its steps there?): " + ", ".join(n for n, _ in left_out)
           if left_out else ""))
    box, guard = report["ellipticity"]["box"], report["ellipticity"]["guard"]
    verdict = "strongly elliptic" if guard["min"] > 0 else (
        f"not elliptic on {guard['fraction']:.1%} of the deformations sampled"
        + ("" if elliptic > 0 else "; train.law_fit_elliptic keeps it elliptic"))
    log(f"train: the learned law's smallest acoustic value {box['min']:.3g} μ_s over its training states' box, "
        f"{guard['min']:.3g} over twice it ({verdict})")
    return report


__all__ = ["CONVEX", "HIDDEN", "EquationError", "PronySeries", "StrainEnergy", "acoustic_values", "convex_roots",
           "direction_pairs", "ellipticity", "ellipticity_penalty", "fit_strain_energy", "invariant_scales", "principal_deformations",
           "widest_first"]
