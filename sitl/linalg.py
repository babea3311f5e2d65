"""Small dense linear algebra in Python floats: the same bits on every machine.

numpy's ``linalg`` calls LAPACK, whose kernels (chosen per CPU) round
differently: a pseudo-inverse computed once at start-up then differs in its
last bits from one machine to another, and a flight that saturates (a law that
switches on a sign) amplifies that into a different flight. What the simulation
computes from a vehicle's geometry is computed here instead, in a fixed order.
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["Matrix", "inverse", "pseudo_inverse"]

Matrix = tuple[tuple[float, ...], ...]


def inverse(a: Sequence[Sequence[float]]) -> Matrix:
    """The inverse of a square matrix (Gauss-Jordan, partial pivoting).

    Raises
    ------
    ValueError
        If the matrix is not square or is singular to working precision.
    """
    n = len(a)
    if any(len(r) != n for r in a):
        raise ValueError(f"expected a square matrix, got {[len(r) for r in a]} columns")
    scale = max((abs(float(v)) for r in a for v in r), default=0.0)
    eye = [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]
    m = [[float(v) for v in r] + eye[i] for i, r in enumerate(a)]
    for c in range(n):
        p = max(range(c, n), key=lambda i: abs(m[i][c]))
        if not abs(m[p][c]) > 1e-12 * scale:
            raise ValueError("the matrix is singular")
        m[c], m[p] = m[p], m[c]
        piv = m[c][c]
        m[c] = [v / piv for v in m[c]]
        for i in range(n):
            if i != c and m[i][c] != 0.0:
                f = m[i][c]
                m[i] = [vi - f * vc for vi, vc in zip(m[i], m[c], strict=True)]
    return tuple(tuple(r[n:]) for r in m)


def pseudo_inverse(a: Sequence[Sequence[float]]) -> Matrix:
    """The Moore-Penrose pseudo-inverse (columns x rows) of a matrix whose non-zero
    rows are linearly independent: ``B^T (B B^T)^-1`` over those rows, and zero
    columns for the rows that are all zero.

    Raises
    ------
    ValueError
        If the non-zero rows are dependent.
    """
    rows = [tuple(float(v) for v in r) for r in a]
    n_cols = len(rows[0]) if rows else 0
    keep = [i for i, r in enumerate(rows) if any(v != 0.0 for v in r)]
    b = [rows[i] for i in keep]
    gram = [[sum(x * y for x, y in zip(ri, rj, strict=True)) for rj in b] for ri in b]
    g_inv = inverse(gram)
    k = len(b)
    out = [[0.0] * len(rows) for _ in range(n_cols)]
    for c in range(n_cols):
        for j in range(k):
            out[c][keep[j]] = sum(b[i][c] * g_inv[i][j] for i in range(k))
    return tuple(tuple(r) for r in out)
