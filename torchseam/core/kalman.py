"""A small linear Kalman filter, filterpy's names: ``x``, ``P``, ``F``, ``Q``, ``H``, ``R``;
:func:`predict` and :func:`update` apart, the innovation ``y`` and its covariance ``S`` kept for
inspection (gating, consistency checks).

The functions take numpy arrays or torch tensors alike (``@``, ``+``, ``-`` and a transpose of
the last two axes), so the same lines run on the live loop (numpy, one stream) and under
autograd when a filter's values are fitted (torch). The live tracker's fusion filter
(:mod:`torchseam.track.anchored`) is built on them; EAKF (:mod:`torchseam.track.eakf`) keeps its
own delayed-measurement equations for coloured noise (METHOD.md section 3).

Example:
    >>> import numpy as np
    >>> x, P = np.zeros(2), np.eye(2)
    >>> x, P = predict(x, P, np.eye(2), 0.5 * np.eye(2))
    >>> inn = innovation(x, P, np.array([1.0, 0.0]), np.eye(2), 0.5 * np.eye(2))
    >>> x, P = update(x, P, inn, np.eye(2), 0.5 * np.eye(2))
    >>> x.round(3).tolist(), round(float(inn.d2), 3)
    ([0.75, 0.0], 0.5)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["Innovation", "innovation", "predict", "update"]


def _t(a: Any) -> Any:
    """``a`` with its last two axes swapped (numpy or torch)."""
    return np.swapaxes(a, -1, -2) if isinstance(a, np.ndarray) else a.transpose(-1, -2)


def _inv(a: Any) -> Any:
    """Inverse of a square matrix (numpy or torch); a (2, 2) one in closed form."""
    if a.shape[-1] == 2 and a.ndim == 2:
        det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
        if isinstance(a, np.ndarray):
            return np.array([[a[1, 1], -a[0, 1]], [-a[1, 0], a[0, 0]]]) / det
        import torch

        return torch.stack([torch.stack([a[1, 1], -a[0, 1]]),
                            torch.stack([-a[1, 0], a[0, 0]])]) / det
    if isinstance(a, np.ndarray):
        return np.linalg.inv(a)
    import torch

    return torch.linalg.inv(a)


def _eye_like(a: Any) -> Any:
    n = a.shape[-1]
    if isinstance(a, np.ndarray):
        return np.eye(n)
    import torch

    return torch.eye(n, dtype=a.dtype, device=a.device)


@dataclass
class Innovation:
    """A measurement's innovation: ``y = z - H x`` (n,), its covariance ``S = H P H^T + R``
    (n, n), ``S^-1`` and the squared Mahalanobis distance ``d2 = y^T S^-1 y``."""

    y: Any
    S: Any
    S_inv: Any
    d2: Any


def predict(x: Any, P: Any, F: Any, Q: Any) -> tuple[Any, Any]:
    """``x <- F x``, ``P <- F P F^T + Q``."""
    return F @ x, F @ P @ _t(F) + Q


def innovation(x: Any, P: Any, z: Any, H: Any, R: Any) -> Innovation:
    """The innovation of measurement ``z`` (covariance ``R``) against the prediction."""
    y = z - H @ x
    S = H @ P @ _t(H) + R
    S_inv = _inv(S)
    return Innovation(y, S, S_inv, y @ S_inv @ y)


def update(x: Any, P: Any, inn: Innovation, H: Any, R: Any, w: Any = 1.0
           ) -> tuple[Any, Any]:
    """Kalman update with gain ``K = P H^T S^-1`` scaled by ``w`` (1: the usual update; a
    gate's weight otherwise, 0 leaves the state as it is), the covariance in Joseph form so it
    stays symmetric and positive: ``x <- x + w K y``,
    ``P <- (I - w K H) P (I - w K H)^T + w^2 K R K^T``."""
    K = w * (P @ _t(H) @ inn.S_inv)
    I_KH = _eye_like(P) - K @ H
    return x + K @ inn.y, I_KH @ P @ _t(I_KH) + K @ R @ _t(K)
