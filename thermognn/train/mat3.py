"""Determinants and inverses of stacks of 3×3 matrices (the cells' F and C) in closed form.

A law step meets every cell's F [B, T, 3, 3] (T = 1493 on the liver) several times a Newton
iteration: det F for the line search's admissibility, det C and C⁻¹ for the learned law. LAPACK's
batched LU (``torch.linalg.det``, ``torch.linalg.inv``) factors each 3×3 matrix in its own call;
on the liver's cells that took 106–119 µs for a determinant and 175 µs for an inverse on this
2-core VM, against about 40 µs and 130 µs here (TorchScript, 1 thread). The formulas:

    det A = a00 (a11 a22 − a12 a21) − a01 (a10 a22 − a12 a20) + a02 (a10 a21 − a11 a20),
    det A A⁻¹ = A² − I1 A + I2 I,   I1 = tr A,  I2 = ½ (I1² − tr A²)   (Cayley–Hamilton),

equal LAPACK's to round-off on the cells' F (tests/test_law_prior.py). Unlike ``torch.linalg.inv``
a singular A raises nothing: its inverse is inf or NaN, which the law prior's finiteness checks
catch as they catch any non-finite state (``prior.DIVERGED``). Autograd passes through both.
The price: a scripted law step built of these takes the graph executor longer to optimise, once
(the liver's learned law with its optimisation on: about 15 + 35 s for its first two steps against
11 + 23 s with LAPACK's; docs/accuracy.md, session 101). ``serve`` steps with it off. The law
prior's once-a-step stress outputs keep LAPACK's determinant, which saves nothing there.
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
    """(det A [...], A⁻¹ [..., 3, 3]) of matrices A [..., 3, 3], by Cayley–Hamilton:
    det A A⁻¹ = A² − I1 A + I2 I, I1 = tr A, I2 = ½ (I1² − tr A²)."""
    det = det3(A)
    A2 = A @ A
    I1 = A.diagonal(dim1=-2, dim2=-1).sum(-1)
    I2 = 0.5 * (I1 * I1 - A2.diagonal(dim1=-2, dim2=-1).sum(-1))
    eye = torch.eye(3, dtype=A.dtype, device=A.device)
    return det, (A2 - I1[..., None, None] * A + I2[..., None, None] * eye) / det[..., None, None]


def inverse3(A: Tensor) -> Tensor:
    """A⁻¹ [..., 3, 3] of matrices A [..., 3, 3] (:func:`det_inverse3`)."""
    return det_inverse3(A)[1]
