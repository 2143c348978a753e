"""Which state variables z a scene carries, derived from its declared effects.

A scene declares effects, a subset of::

    elastic   hyperelastic strain energy (always present for a solid)
    viscous   Prony-series viscoelasticity (internal variables per term)
    inertia   dynamics: mass matrix, velocity is a state variable
    gravity   body force rho*g

The per-node state z (the paper's z = (q, v, sigma)) follows from them:

    q      (3)  current position x = X + u              [m]
    v      (3)  velocity, only with ``inertia``          [m/s]
    sigma  (6)  Cauchy stress, Voigt order s11 s22 s33 s12 s13 s23 [Pa]
    xi_k   (6)  viscous internal stress of Prony term k, only with ``viscous`` and
                ``store_internal``                      [Pa]

Pure Python: used by generate (no torch), train and serve (no dolfinx).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from .errors import ConfigError

EFFECTS = ("elastic", "viscous", "inertia", "gravity")
VOIGT = ("11", "22", "33", "12", "13", "23")


@dataclass(frozen=True)
class StateLayout:
    """Ordered variable groups of the per-node state vector z, e.g. (("q",3),("v",3),("sigma",6))."""

    groups: tuple[tuple[str, int], ...]

    @property
    def dim(self) -> int:
        return sum(d for _, d in self.groups)

    def slice(self, name: str) -> slice:
        start = 0
        for g, d in self.groups:
            if g == name:
                return slice(start, start + d)
            start += d
        raise KeyError(f"state variable '{name}' not in layout {self.names}")

    @property
    def names(self) -> list[str]:
        return [g for g, _ in self.groups]

    def to_json(self) -> str:
        return json.dumps([list(g) for g in self.groups])

    @classmethod
    def from_json(cls, text: str) -> "StateLayout":
        return cls(tuple((str(n), int(d)) for n, d in json.loads(text)))


def check_effects(effects) -> tuple[str, ...]:
    effects = tuple(str(e) for e in effects)
    for e in effects:
        if e not in EFFECTS:
            raise ConfigError(f"scene.effects: unknown effect '{e}', expected some of {list(EFFECTS)}")
    if "elastic" not in effects:
        raise ConfigError("scene.effects: a solid needs 'elastic'")
    return effects


def state_layout(effects, n_prony: int = 0, store_internal: bool = False) -> StateLayout:
    """The state layout a scene's effects call for (see module docstring)."""
    effects = check_effects(effects)
    groups: list[tuple[str, int]] = [("q", 3)]
    if "inertia" in effects:
        groups.append(("v", 3))
    groups.append(("sigma", 6))
    if "viscous" in effects and store_internal:
        groups += [(f"xi{k + 1}", 6) for k in range(n_prony)]
    return StateLayout(tuple(groups))


def is_reversible(effects) -> bool:
    """Reversible (Hamiltonian) scenes have no dissipation: no viscous term."""
    return "viscous" not in tuple(effects)


def time_error_parts(record: dict) -> str:
    """"u 1.1 %, v 7.9 %, σ 1.6 %": the groups of a time-convergence record (``generate``'s check,
    an exported file's ``data_time_error``) that it has."""
    return ", ".join(f"{'σ' if g == 'sigma' else g} {100 * float(record[g]):.2g} %" for g in ("u", "v", "sigma")
                     if record.get(g) is not None)


def describe_time_error(record) -> str:
    """An exported file's ``data_time_error`` in words ("" where absent): how far the data behind
    the body are from the FE at twice their sub-steps, what its force is worth in time."""
    if not record:
        return ""
    k = int(record.get("substeps", 1))
    return (f"{time_error_parts(record)} (the data, {k} FE step{'s' if k > 1 else ''} a stored step, against the FE at "
            f"{int(record.get('fine_substeps', 2 * k))}; generate's check)")


def law_iterates(step) -> bool:
    """Whether a law prior's step settings (a checkpoint's ``prior`` or an exported file's ``step``
    metadata: "law" Newton iterations at least, "law_max" at most) iterate each step to a tolerance
    rather than take a fixed budget; False for any other model."""
    return bool(step) and bool(step.get("law")) and int(step.get("law_max") or step["law"]) > int(step["law"])


def describe_step(step) -> str:
    """How a model steps, in one phrase used by evaluate, export's metadata readers, serve and the
    benchmarks, from its step settings ({"integrator", "implicit_iterations", "kinematics"}, the
    exported file's ``step`` metadata), e.g. "euler, learned kinematics" or "midpoint (3 sweeps),
    exact kinematics"."""
    if not isinstance(step, dict):
        return "not recorded in the model file"
    if step.get("prior") == "linear":
        calls = int(step.get("sweeps", 1))
        second = int(step.get("order", 1)) == 2
        solid = (f"corotated solid ({int(step['corotated'])} rotation sweeps)" if step.get("corotated")
                 else "linearised solid") + (", its stress the material's law" if step.get("stress") == "material" else "")
        if step.get("law"):
            iterations = int(step["law"])
            most = int(step.get("law_max", iterations))
            law = "a strain energy learned from the data" if step.get("law_material") == "learned" else "the data's own law"
            sub = int(step.get("law_substeps", 1))
            solid = (f"solid of {law} ("
                     + (f"{sub} sub-steps a step, each with " if sub > 1 else "")
                     + f"{iterations} Newton iteration{'s' if iterations > 1 else ''}"
                     + (f", up to {most} until converged to {float(step['law_rtol']):g}" if most > iterations
                        else "")
                     + (f", halved down to Δt/{2 ** int(step['law_cuts']) * sub} where not" if step.get("law_cuts") else "")
                     + (", its sub-steps loaded linearly between the step's loads"
                        if step.get("law_cut_loads") == "linear" else "")
                     + (", its tangent kept while it contracts" if step.get("law_tangent") == "kept" else "")
                     + (f", its chord updates Anderson-mixed with up to {int(step['law_anderson'])} earlier ones"
                        if step.get("law_anderson") else "")
                     + (f", its updates line-searched (up to {int(step['law_search'])} halvings)"
                        if step.get("law_search") else "")
                     + ")")
        rule = ("the data's Newmark step corrected to conserve the step's energy" if step.get("law_rule") == "energy"
                else f"HHT's step (α = -{float(step['law_hht']):g}, damping what Δt does not resolve)"
                if step.get("law_hht") else "the data's Newmark step")
        if step.get("remainders") == "zero":
            return f"{rule} of the {solid} alone (its remainders zero, no network call)"
        return (f"{rule} of the {solid} with learned remainders"
                + (" of second order" if second else "")
                + f" ({calls} network call{'s' if calls > 1 else ''} a step"
                + (", each on the state and its half-way state" if second else "") + ")")
    integrator = str(step.get("integrator", "?"))
    if integrator == "midpoint":
        integrator += f" ({step.get('implicit_iterations', '?')} sweeps)"
    return f"{integrator}, {step.get('kinematics', '?')} kinematics"
