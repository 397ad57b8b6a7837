"""Boundary checks shared by the tracker modules (private)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchseam.core.errors import TorchseamError


class TrackInputError(TorchseamError, ValueError):
    """A tracker input has the wrong type, shape, size or value."""


def check_tensor(x: object, name: str, dims: Sequence[str | int]) -> Tensor:
    """Check that ``x`` is a tensor of shape ``dims`` (names are free sizes, ints are fixed).

    Returns ``x``. Raises :class:`TrackInputError` naming ``name`` and the expected shape.
    """
    want = "(" + ", ".join(str(d) for d in dims) + ")"
    if not isinstance(x, Tensor):
        raise TrackInputError(f"{name}: expected a torch.Tensor of shape {want}, "
                              f"got {type(x).__name__}")
    if x.ndim != len(dims) or any(
            isinstance(d, int) and s != d for s, d in zip(x.shape, dims, strict=True)):
        raise TrackInputError(f"{name}: expected shape {want}, got {tuple(x.shape)}")
    return x


def check_batch(x: Tensor, name: str, batch: int) -> None:
    """Check that the leading dimension of ``x`` is ``batch``."""
    if x.shape[0] != batch:
        raise TrackInputError(f"{name}: expected batch size {batch} (the tracker's B), "
                              f"got {x.shape[0]}")


def as_float(x: Tensor, like: Tensor) -> Tensor:
    """``x`` on ``like``'s dtype (a floating type); ints and uint8 frames are converted."""
    return x if x.dtype == like.dtype else x.to(like.dtype)


def check_size(size: Sequence[int], name: str) -> tuple[int, int]:
    """A (H, W) window size of two positive ints."""
    try:
        h, w = (int(s) for s in size)
    except (TypeError, ValueError):
        raise TrackInputError(f"{name}: expected (H, W), two positive integers, "
                              f"got {size!r}") from None
    if h < 3 or w < 3:
        raise TrackInputError(f"{name}: expected (H, W) with H, W >= 3, got {(h, w)}")
    return h, w


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    if value not in choices:
        raise TrackInputError(f"{name}: expected one of {', '.join(choices)}, got {value!r}")
    return value


def check_device(x: Tensor, name: str, ref: Tensor) -> None:
    if x.device != ref.device:
        raise TrackInputError(f"{name}: on {x.device}, but the tracker is on {ref.device} "
                              f"(move one of them with .to())")


def finite_or_raise(x: Tensor, name: str) -> None:
    """Raise if ``x`` holds NaN or inf (use at the boundary only: it syncs on CUDA)."""
    if not bool(torch.isfinite(x).all()):
        raise TrackInputError(f"{name}: contains NaN or inf")
