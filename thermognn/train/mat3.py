"""Determinants and inverses of stacks of 3×3 matrices (the cells' F and C) in closed form.

A law step meets every cell's F [B, T, 3, 3] (T = 1493 on the liver) several times a Newton
iteration: C = FᵀF, det F for the line search's admissibility, det C and C⁻¹ for the law. LAPACK's
batched LU (``torch.linalg.det``, ``torch.linalg.inv``) factors each 3×3 matrix in its own call;
on the liver's cells that took 106–119 µs for a determinant and 175 µs for an inverse on this
2-core VM, against 42 µs and about 130 µs (with the determinant) by cofactors. The formulas:

    det A = a00 (a11 a22 − a12 a21) − a01 (a10 a22 − a12 a20) + a02 (a10 a21 − a11 a20),
    A⁻¹  = adj A / det A,   adj A = (cof A)ᵀ,

equal LAPACK's to round-off (relative 1e-15 on the cells' F). Unlike ``torch.linalg.inv`` a
singular A raises nothing: its inverse is inf or NaN, which the law prior's finiteness checks
catch as they catch any non-finite state (``prior.DIVERGED``). Autograd passes through both.
"""

from __future__ import annotations

from typing import Tuple

from torch import Tensor
import torch


def det3(A: Tensor) -> Tensor:
    """det A [...] of matrices A [..., 3, 3] (cofactor expansion along the first row)."""
    c = A.reshape(list(A.shape[:-2]) + [9]).unbind(-1)                                # a00 .. a22, row-major
    return c[0] * (c[4] * c[8] - c[5] * c[7]) - c[1] * (c[3] * c[8] - c[5] * c[6]) \
        + c[2] * (c[3] * c[7] - c[4] * c[6])


def det_inverse3(A: Tensor) -> Tuple[Tensor, Tensor]:
    """(det A [...], A⁻¹ [..., 3, 3]) of matrices A [..., 3, 3], by the adjugate."""
    c = A.reshape(list(A.shape[:-2]) + [9]).unbind(-1)
    adj = [c[4] * c[8] - c[5] * c[7], c[2] * c[7] - c[1] * c[8], c[1] * c[5] - c[2] * c[4],
           c[5] * c[6] - c[3] * c[8], c[0] * c[8] - c[2] * c[6], c[2] * c[3] - c[0] * c[5],
           c[3] * c[7] - c[4] * c[6], c[1] * c[6] - c[0] * c[7], c[0] * c[4] - c[1] * c[3]]
    det = c[0] * adj[0] + c[1] * adj[3] + c[2] * adj[6]
    return det, torch.stack(adj, -1).reshape(A.shape) / det[..., None, None]


def inverse3(A: Tensor) -> Tensor:
    """A⁻¹ [..., 3, 3] of matrices A [..., 3, 3] (:func:`det_inverse3`)."""
    return det_inverse3(A)[1]
