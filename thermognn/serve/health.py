"""The served body's health: are its cells still cells, and still within the states its law knows?

A served rollout can stay finite long after the body it carries is gone. The shipped liver law,
pressed by the sim device for 30 s at the data's 20 ms (docs/accuracy.md, session 94), rang up in
its smallest cells: from the sixth press they left the states its law was fitted on, from the
seventh the tool felt 6 N instead of 2.4 N, from the ninth cells were inverted and the body
428 mm out of shape, every number still finite. Finiteness says nothing a user can feel; the
cells do. For a body that carries its mesh (a law prior: its cells' nodes ``cell_nodes`` [C, 4])
:class:`BodyHealth` reads, from the carried positions q [N, 3] m alone:

- each cell's volume ratio J = det F (F = ∂q/∂X, constant over a linear tetrahedron): J ≤ 0 is an
  inverted cell, J ≤ ``CRUSHED`` (1 %) a crushed one, which no solid's law holds either; a body
  with either is destroyed (the liver's law's cells went 0.47 → 0.019 → 8e-5 in eight steps
  before one inverted, session 95);
- for a learned law (its ``scales`` s [3], the largest |Ī1 − 3|, |Ī2 − 3|, |J − 1| of its
  training states), each cell's scaled invariants x = ((Ī1 − 3)/s1, (Ī2 − 3)/s2, (J − 1)/s3) with
  Ī1 = J^(−2/3) I1, Ī2 = J^(−4/3) I2 of C = FᵀF and J = √det C, as the law reads them: the largest
  |x| over the cells is 1 at the edge of the law's training states, and beyond it the law
  extrapolates (its guard starts at twice it);
- the largest displacement |q − X| [m].

``serve``'s physics process checks every step (``thermognn.serve.physics.run_physics``); the
sim press (``thermognn.serve.lockstep.press_rollout``) records the figures step by step. Numpy
only: no torch, no training code.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from thermognn.core.kinematics import deformation_gradients, shape_gradients

#: the learned law's guard starts at this multiple of its training states' box (``GUARD_MARGIN``
#: of ``thermognn.train.learned_law``, read from the exported module where it has it)
GUARD_MARGIN = 2.0

#: a cell whose volume ratio J = det F is at most this is crushed (the body destroyed); the data's
#: cells keep J within 0.66–1.34 (the liver's law's box), a foam's within a few tens of per cent
CRUSHED = 0.01


@dataclass(frozen=True)
class Health:
    """One carried state's health (module docstring)."""

    inverted_cells: int             # cells with J = det F <= 0
    crushed_cells: int              # cells with J <= CRUSHED (the inverted ones too)
    smallest_volume_ratio: float    # the smallest J over the cells (1 at rest)
    largest_invariant: float        # the largest |scaled invariant| of any cell (1: the edge of the
                                    # law's training states); nan without a learned law's scales
    cells_beyond_states: int        # cells with some |scaled invariant| > 1 (0 without scales)
    largest_displacement_m: float   # the largest |q − X| over the nodes [m]

    @property
    def destroyed(self) -> bool:
        """True where a cell is crushed or inverted (or a figure is not finite): no law steps back from it."""
        return self.crushed_cells > 0 or not np.isfinite(self.smallest_volume_ratio)


class BodyHealth:
    """Health of a meshed body's carried states (module docstring): ``reference_positions`` X
    [N, 3] m, its linear tetrahedra ``cell_nodes`` [C, 4] (indices into X), a learned law's
    invariant ``scales`` [3] (None: no law box to check), where its guard starts
    (``guard_margin`` times the box) and the HHT dissipation its law is stepped with (``hht``,
    α = −hht; 0: the data's undamped rule), which the warnings' advice follows."""

    def __init__(self, reference_positions: np.ndarray, cell_nodes: np.ndarray,
                 scales: np.ndarray | None = None, guard_margin: float = GUARD_MARGIN, hht: float = 0.0) -> None:
        X = np.asarray(reference_positions, dtype=float)
        cells = np.asarray(cell_nodes, dtype=np.int64)
        if X.ndim != 2 or X.shape[1] != 3:
            raise ValueError(f"BodyHealth: reference_positions has shape {X.shape}, expected [N, 3]")
        if cells.ndim != 2 or cells.shape[1] != 4 or (cells.size and (cells.min() < 0 or cells.max() >= len(X))):
            raise ValueError(f"BodyHealth: cell_nodes has shape {cells.shape} (or indices outside the {len(X)} "
                             f"nodes), expected [C, 4] tetrahedra")
        self.X, self.cells = X, cells
        self.grad = shape_gradients(X, cells)[0]                            # [C, 4, 3] 1/m: Grad φ_a
        self.scales = None if scales is None else np.asarray(scales, dtype=float).reshape(3)
        self.guard_margin = float(guard_margin)
        self.hht = float(hht)                       # the law's HHT dissipation (α = −hht; 0: undamped)

    @classmethod
    def of_module(cls, module, reference_positions: np.ndarray) -> "BodyHealth | None":
        """The health check of an exported model ``module`` (TorchScript) that carries its mesh (a
        law prior's ``core.prior.cell_nodes``; a learned law (``learned``) adds its ``scales``); None for a model
        without cells (a graph network alone)."""
        prior = getattr(getattr(module, "core", None), "prior", None)
        cells = getattr(prior, "cell_nodes", None)
        if cells is None:
            return None
        law = getattr(prior, "learned_law", None) if bool(getattr(prior, "learned", False)) else None
        scales = getattr(law, "scales", None)                               # the scene's own law: no box
        margin = getattr(law, "guard_margin", GUARD_MARGIN)
        return cls(reference_positions, cells.detach().cpu().numpy(),
                   None if scales is None else scales.detach().cpu().numpy(), float(margin),
                   float(getattr(prior, "hht", 0.0)))

    def deformation_gradients(self, q: np.ndarray) -> np.ndarray:
        """F [..., C, 3, 3] of carried positions q [..., N, 3] m (one per linear tetrahedron)."""
        return deformation_gradients(q, self.cells, self.grad)

    def scaled_invariants(self, F: np.ndarray) -> np.ndarray:
        """x [..., C, 3] of deformation gradients F [..., C, 3, 3] (module docstring); needs ``scales``."""
        C = np.swapaxes(F, -1, -2) @ F
        J = np.sqrt(np.abs(np.linalg.det(C)))
        I1 = np.trace(C, axis1=-2, axis2=-1)
        I2 = 0.5 * (I1 * I1 - np.sum(C * C, axis=(-2, -1)))
        with np.errstate(divide="ignore", invalid="ignore"):
            a = J ** (-2.0 / 3.0)
            return np.stack([(a * I1 - 3.0) / self.scales[0], (a * a * I2 - 3.0) / self.scales[1],
                             (J - 1.0) / self.scales[2]], axis=-1)

    def __call__(self, q: np.ndarray) -> Health:
        """The health of carried positions q [N, 3] m."""
        q = np.asarray(q, dtype=float)
        F = self.deformation_gradients(q)                                   # [C, 3, 3]
        J = np.linalg.det(F)                                                # [C]
        largest, beyond = float("nan"), 0
        if self.scales is not None:
            x = np.abs(self.scaled_invariants(F)).max(axis=-1)              # [C]
            largest = float(x.max()) if np.isfinite(x).all() else float("inf")
            beyond = int(np.count_nonzero(~(x <= 1.0)))
        return Health(int(np.count_nonzero(~(J > 0.0))), int(np.count_nonzero(~(J > CRUSHED))), float(J.min()),
                      largest, beyond,
                      float(np.linalg.norm(q - self.X, axis=1).max()))


def beyond_states_warning(health: Health, step: int, margin: float, hht: float = 0.0) -> str:
    """One line for the first step where cells leave the law's training states; its advice follows
    the law's time rule (``hht``: its HHT dissipation, 0 for the data's undamped Newmark rule)."""
    advice = (f"this file already damps with HHT's α = -{hht:g}; a larger rollout.prior_hht at export damps more "
              f"(0.05 held the liver 30 s at 2.18 % from its data)" if hht
              else "for long sessions export with HHT's dissipation (rollout.prior_hht, or a scene's "
                   "scene.time.served_hht, which export applies: the liver's)")
    return (f"at model step {step} {health.cells_beyond_states} cell(s) of the body left the states its "
            f"law was fitted on (largest scaled invariant {health.largest_invariant:.2f}, 1 at their edge; "
            f"the law's guard starts at {margin:g}): its force there is extrapolated, and a body ringing "
            f"up this way collapsed within a few presses (docs/accuracy.md, session 94); {advice}")


def destroyed_warning(health: Health, step: int, reset: bool) -> str:
    """One line for a step that left crushed or inverted cells."""
    then = ("the body was reset to rest (serve.body_reset)" if reset
            else "it is served as it is (serve.body_reset=false): its force is not a body's")
    return (f"at model step {step} {health.crushed_cells} cell(s) of the body are crushed or inverted ("
            f"{health.inverted_cells} inverted; smallest volume ratio {health.smallest_volume_ratio:.3g}, largest displacement "
            f"{health.largest_displacement_m * 1e3:.1f} mm): {then}")


__all__ = ["BodyHealth", "CRUSHED", "GUARD_MARGIN", "Health", "beyond_states_warning", "destroyed_warning"]
