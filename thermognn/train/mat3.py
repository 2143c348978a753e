"""Determinants and inverses of stacks of 3×3 matrices (the cells' F and C) in closed form.

A law step meets every cell's F [B, T, 3, 3] (T = 1493 on the liver) several times a Newton
iteration: det F for the line search's admissibility, det C and C⁻¹ for the learned law. LAPACK's
batched LU (``torch.linalg.det``, ``torch.linalg.inv``) factors each 3×3 matrix in its own call;
on the liver's cells (TorchScript, 1 thread, this 2-core VM) a determinant took 82–84 µs that way
and 39–40 µs here, a determinant with the inverse 235–238 µs and 123–124 µs here. The formulas:

    det A = a00 (a11 a22 − a12 a21) − a01 (a10 a22 − a12 a20) + a02 (a10 a21 − a11 a20),
    A⁻¹  = adj A / det A,   adj A = (cof A)ᵀ,

equal LAPACK's to round-off (tests/test_law_prior.py). Unlike ``torch.linalg.inv`` a singular A
raises nothing: its inverse is inf or NaN, which the law prior's finiteness checks catch as they
catch any non-finite state (``prior.DIVERGED``). Autograd passes through both. (An inverse by
Cayley–Hamilton, A² − I1 A + I2 I over det A, was no faster than LAPACK's: 227–252 µs.)
The price: a scripted law step built of these takes the graph executor longer to optimise, once
(docs/accuracy.md, session 101). ``serve`` steps with it off. The law prior's once-a-step stress
outputs keep LAPACK's determinant, which saves nothing there.
"""

from __future__ import annotations

from typing import Tuple

from torch import Tensor
import torch


def det3(A: Tensor) -> Tensor:
    """det A [...] of matrices A [..., 3, 3] (cofactor expansion along the first row)."""
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a10, a11, a12 = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    a20, a21, a22 = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    return a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)


def det_inverse3(A: Tensor) -> Tuple[Tensor, Tensor]:
    """(det A [...], A⁻¹ = adj A / det A [..., 3, 3]) of matrices A [..., 3, 3]: the adjugate's nine
    cofactors, the first column's three giving the determinant as in :func:`det3`."""
    a00, a01, a02 = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    a10, a11, a12 = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    a20, a21, a22 = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    c00, c01, c02 = a11 * a22 - a12 * a21, a12 * a20 - a10 * a22, a10 * a21 - a11 * a20   # cofactors, row 0
    det = a00 * c00 + a01 * c01 + a02 * c02
    adj = torch.stack([c00, a02 * a21 - a01 * a22, a01 * a12 - a02 * a11,
                       c01, a00 * a22 - a02 * a20, a02 * a10 - a00 * a12,
                       c02, a01 * a20 - a00 * a21, a00 * a11 - a01 * a10], -1)          # [..., 9] row-major
    return det, adj.reshape(A.shape) / det[..., None, None]


def inverse3(A: Tensor) -> Tensor:
    """A⁻¹ [..., 3, 3] of matrices A [..., 3, 3] (:func:`det_inverse3`)."""
    return det_inverse3(A)[1]
