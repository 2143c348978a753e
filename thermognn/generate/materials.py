"""Hyperelastic and viscoelastic material laws as UFL expressions (total Lagrangian, SI units).

Every law splits its strain energy density Ψ(C) [J/m^3 = Pa] into an isochoric part Ψ_iso(C̄),
C̄ = J^(-2/3) C, and a volumetric part U(J), so the viscous (Prony) relaxation can act on the
isochoric stress only (the bulk response stays elastic, as in Abaqus' default for shear
relaxation)::

    neo-Hookean  Ψ = C10 (Ī1 − 3) + (1/D1) (J − 1)^2
    Ogden        Ψ = Σ_i 2 μi/αi² (λ̄1^αi + λ̄2^αi + λ̄3^αi − 3) + Σ_i (1/Di) (J − 1)^(2i)

Second Piola–Kirchhoff stress S = 2 ∂Ψ/∂C, first P = F S, Cauchy σ = J⁻¹ F S Fᵀ.

Ogden needs the principal stretches λ̄a = sqrt(eig(C̄)). UFL has no eigendecomposition, and the
closed-form (Cardano / trigonometric) eigenvalues have infinite derivatives where eigenvalues
coincide (F = I: all three; uniaxial stretch: two). :func:`regularised_eigenvalues` keeps the
trigonometric formula but replaces the deviatoric norm p by p_ε = sqrt(p² + ε²). The result is
exactly the eigenvalues of a matrix with the same first and third deviatoric invariants and the
second raised by 6ε², so Ψ is smooth everywhere and its error is O(ε²) (ε = 1e-6: ~1e-12 relative).
The uniaxial test in tests/test_fe_materials.py checks the stress to 1e-6 against the closed form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import ufl

from thermognn.core.errors import ConfigError

#: regularisation of the deviatoric norm in the eigenvalue formula (C̄ is dimensionless, ~1)
EIGEN_EPS = 1.0e-6


@dataclass(frozen=True)
class PronyTerm:
    """One Prony term of g_R(t) = 1 − Σ ḡi (1 − exp(−t/τi)): ḡ (dimensionless), τ [s]."""

    g: float
    tau: float


@dataclass(frozen=True)
class Material:
    """A hyperelastic law with optional Prony viscoelasticity.

    law: 'neo_hookean' (params C10 [Pa], D1 [1/Pa]) or 'ogden' (mu [Pa], alpha [-], D [1/Pa],
    lists of equal length or D shorter). density [kg/m^3].
    """

    law: str
    params: dict
    density: float = 1000.0
    prony: tuple[PronyTerm, ...] = field(default_factory=tuple)

    @property
    def shear_modulus(self) -> float:
        """Initial shear modulus μ0 [Pa]."""
        if self.law == "neo_hookean":
            return 2.0 * self.params["C10"]
        return sum(m for m in self.params["mu"])  # Ogden: μ0 = Σ μi (with the 2μi/αi² scaling)

    @property
    def bulk_modulus(self) -> float:
        """Initial bulk modulus K0 [Pa]."""
        if self.law == "neo_hookean":
            return 2.0 / self.params["D1"]
        return 2.0 / self.params["D"][0]


def material_from_config(mat, where: str = "scene.material") -> Material:
    """Build a :class:`Material` from the scene's ``material`` config node; ConfigError if bad."""
    law = str(mat.get("law", ""))
    density = float(mat.get("density", 1000.0))
    prony = tuple(PronyTerm(float(t["g"]), float(t["tau"])) for t in (mat.get("prony", None) or []))
    if sum(t.g for t in prony) >= 1.0 or any(t.g < 0 or t.tau <= 0 for t in prony):
        raise ConfigError(f"{where}.prony = {[(t.g, t.tau) for t in prony]}: expected g >= 0, sum g < 1, tau > 0")
    if density <= 0:
        raise ConfigError(f"{where}.density = {density}: expected > 0 [kg/m^3]")
    if law == "neo_hookean":
        params = {}
        for key in ("C10", "D1"):
            if mat.get(key, None) is None or float(mat[key]) <= 0:
                raise ConfigError(f"{where}.{key} = {mat.get(key, None)!r}: expected a positive number")
            params[key] = float(mat[key])
    elif law == "ogden":
        try:
            mu = [float(x) for x in mat["mu"]]
            alpha = [float(x) for x in mat["alpha"]]
            D = [float(x) for x in mat["D"]]
        except Exception:
            raise ConfigError(f"{where}: ogden needs lists 'mu' [Pa], 'alpha' [-], 'D' [1/Pa]") from None
        if not mu or len(mu) != len(alpha) or not D or any(a == 0 for a in alpha) or any(d <= 0 for d in D):
            raise ConfigError(f"{where}: ogden mu={mu}, alpha={alpha}, D={D}: expected equal-length mu/alpha, "
                              "alpha != 0, D > 0")
        params = {"mu": mu, "alpha": alpha, "D": D}
    else:
        raise ConfigError(f"{where}.law = {law!r}: expected 'neo_hookean' or 'ogden'")
    return Material(law, params, density, prony)


# ---------------------------------------------------------------------------------------------
# kinematics


def kinematics(u):
    """F = I + Grad u, C = Fᵀ F, J = det F (UFL, reference configuration)."""
    d = len(u)
    F = ufl.variable(ufl.Identity(d) + ufl.grad(u))
    return F, F.T * F, ufl.det(F)


def regularised_eigenvalues(A, eps: float = EIGEN_EPS):
    """Eigenvalues (λ1 ≥ λ2 ≥ λ3) of a symmetric 3x3 UFL tensor, smooth where they coincide.

    Trigonometric formula with p → sqrt(p² + ε²) (see module docstring).
    """
    m = ufl.tr(A) / 3.0
    B = A - m * ufl.Identity(3)
    p = ufl.sqrt(ufl.inner(B, B) / 6.0 + eps**2)
    r = ufl.det(B) / (2.0 * p**3)
    r = ufl.max_value(ufl.min_value(r, 1.0), -1.0)  # |r| < 1 analytically; guard round-off
    phi = ufl.acos(r) / 3.0
    return tuple(m + 2.0 * p * ufl.cos(phi + 2.0 * math.pi * k / 3.0) for k in range(3))


def isochoric_energy(mat: Material, C, J):
    """Ψ_iso(C̄) [Pa] with C̄ = J^(-2/3) C."""
    Cbar = J ** (-2.0 / 3.0) * C
    if mat.law == "neo_hookean":
        return mat.params["C10"] * (ufl.tr(Cbar) - 3.0)
    lam2 = regularised_eigenvalues(Cbar)  # squared isochoric principal stretches λ̄a²
    psi = 0
    for mu, alpha in zip(mat.params["mu"], mat.params["alpha"]):
        psi += 2.0 * mu / alpha**2 * (sum(l2 ** (alpha / 2.0) for l2 in lam2) - 3.0)
    return psi


def volumetric_energy(mat: Material, J):
    """U(J) [Pa]."""
    if mat.law == "neo_hookean":
        return (J - 1.0) ** 2 / mat.params["D1"]
    return sum((J - 1.0) ** (2 * (i + 1)) / Di for i, Di in enumerate(mat.params["D"]))


def strain_energy(mat: Material, u):
    """Ψ(F) [Pa] (elastic, long-term + instantaneous parts together)."""
    F, C, J = kinematics(u)
    return isochoric_energy(mat, C, J) + volumetric_energy(mat, J)


def pk2_split(mat: Material, u):
    """(F, S_iso, S_vol): the isochoric and volumetric 2nd Piola–Kirchhoff stresses [Pa]."""
    F = ufl.Identity(3) + ufl.grad(u)
    C = ufl.variable(F.T * F)
    J = ufl.sqrt(ufl.det(C))
    S_iso = 2.0 * ufl.diff(isochoric_energy(mat, C, J), C)
    S_vol = 2.0 * ufl.diff(volumetric_energy(mat, J), C)
    return F, S_iso, S_vol


def cauchy_from_pk2(F, S):
    """σ = J⁻¹ F S Fᵀ [Pa]."""
    return F * S * F.T / ufl.det(F)


def voigt(T):
    """Symmetric 3x3 UFL tensor -> Voigt vector (11 22 33 12 13 23)."""
    return ufl.as_vector([T[0, 0], T[1, 1], T[2, 2], T[0, 1], T[0, 2], T[1, 2]])


# closed forms (numpy) used by the tests --------------------------------------------------------


def principal_cauchy_closed_form(mat: Material, stretches: Sequence[float]):
    """Principal Cauchy stresses [Pa] for F = diag(λ1, λ2, λ3), from the energies written in
    principal stretches (independent of the UFL code): σa = J⁻¹ λa ∂Ψ/∂λa."""
    import numpy as np

    lam = np.asarray(stretches, dtype=float)
    J = float(np.prod(lam))
    lb = lam * J ** (-1.0 / 3.0)
    if mat.law == "neo_hookean":
        I1b = float(np.sum(lb**2))
        dev = 2.0 * mat.params["C10"] / J * (lb**2 - I1b / 3.0)
        p = 2.0 * (J - 1.0) / mat.params["D1"]
    else:
        dev = np.zeros(3)
        for mu, a in zip(mat.params["mu"], mat.params["alpha"]):
            dev += 2.0 * mu / a / J * (lb**a - np.sum(lb**a) / 3.0)
        p = sum(2.0 * (i + 1) * (J - 1.0) ** (2 * i + 1) / Di for i, Di in enumerate(mat.params["D"]))
    return dev + p
