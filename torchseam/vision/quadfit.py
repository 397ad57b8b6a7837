"""The closed-form quadratic fit TIPM's corner search and the anchored tracker share.

Pure Python on floats, so numba compiles the very same function for TIPM's kernels
(:mod:`torchseam.vision._kernels`) and the tracker calls it from Python; apart from
:mod:`torchseam.vision.tipm`, which loads those kernels (no import cycle).
"""

from __future__ import annotations

import numpy as np

__all__ = ["power_sums", "quad_normal_adjugate"]


def power_sums(x: np.ndarray) -> tuple[float, float, float, float, float]:
    """(n, sum x, sum x^2, sum x^3, sum x^4) of ``x`` (N,): what a quadratic fit's 3x3 normal
    matrix is made of.

    Example:
        >>> power_sums(np.array([1.0, 2.0]))
        (2.0, 3.0, 5.0, 9.0, 17.0)
    """
    x2 = x * x
    return float(len(x)), float(x.sum()), float(x2.sum()), float(x2 @ x), float(x2 @ x2)


def quad_normal_adjugate(sums: tuple[float, ...], w: tuple[float, float] = (0.0, 0.0)
                         ) -> tuple[tuple[float, ...], float]:
    """Adjugate (A00, A01, A02, A11, A12, A22) and determinant of the normal matrix
    ``A = [[n, s1, s2], [s1, s2 + w_b, s3], [s2, s3, s4 + w_c]]`` of a quadratic fit with power
    sums ``sums`` (:func:`power_sums`) and ridge weights ``w`` on slope and curvature.

    In closed form: on a 3x3, ``np.linalg.solve``'s per-call overhead is far more than the
    handful of float operations this takes. ``A^-1 = adj / det``. TIPM's corner search runs
    this very function compiled (:mod:`torchseam.vision._kernels`); the fix covariance of the
    anchored tracker calls it from Python.

    Example:
        >>> adj, det = quad_normal_adjugate(power_sums(np.arange(3.0)))  # x = 0, 1, 2
        >>> det
        4.0
    """
    a, b, c, f, g = sums
    d, g = c + w[0], g + w[1]
    A00, A01, A02 = d * g - f * f, c * f - b * g, b * f - c * d
    A11, A12, A22 = a * g - c * c, b * c - a * f, a * d - b * b
    return (A00, A01, A02, A11, A12, A22), a * A00 + b * A01 + c * A02
