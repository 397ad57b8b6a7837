"""Boundary checks of tensors and arrays: one error type, one message form.

A public function checks its inputs once, where they enter, and names the argument, the
expected shape and the actual one, so that a wrong input fails there and not as an unreadable
broadcasting error deep inside (the idea of kornia's ``KORNIA_CHECK_SHAPE``)::

    check_shape(frames, "B H W", "frames")       # three dims, any sizes
    check_shape(uv, ("B", 2), "uv")              # names are free sizes, ints fixed ones
    check_shape(T, "... 4 4", "T")               # "..." : any number of leading dims

Every check raises :class:`InputError` (a :class:`~torchseam.core.errors.TorchseamError` and a
``ValueError``), e.g. ``uv: expected shape (B, 2), got (5, 3)``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Literal, TypeVar

import numpy as np
from torch import Tensor

from torchseam.core.errors import TorchseamError

__all__ = ["InputError", "as_float", "check_batch", "check_choice", "check_device",
           "check_shape", "check_size"]

Dims = str | Sequence[str | int]
A = TypeVar("A", Tensor, np.ndarray)

_KIND_TYPES: dict[str, tuple[type, ...]] = {
    "tensor": (Tensor,), "array": (np.ndarray,), "any": (Tensor, np.ndarray)}
_KIND_TEXT = {"tensor": "a torch.Tensor", "array": "a numpy array",
              "any": "a torch.Tensor or numpy array"}


class InputError(TorchseamError, ValueError):
    """An input has the wrong type, shape, size, device or value (the message names it)."""


@functools.lru_cache(maxsize=256)
def _parse(dims: str | tuple[str | int, ...]) -> tuple[tuple[str | int, ...], bool, str]:
    """``dims`` as (fixed-or-named sizes after any leading "...", whether "..." leads, the
    shape as the message shows it)."""
    items = dims.split() if isinstance(dims, str) else list(dims)
    out: list[str | int] = []
    for d in items:
        if isinstance(d, str) and d.isdigit():
            d = int(d)
        out.append(d)
    ellipsis = bool(out) and out[0] == "..."
    if "..." in out[1:]:
        raise ValueError(f"check_shape: '...' may only lead the shape, got {dims!r}")
    shown = "(" + ", ".join(str(d) for d in out) + ("," if len(out) == 1 else "") + ")"
    return tuple(out[1:] if ellipsis else out), ellipsis, shown


def check_shape(x: A, dims: Dims, name: str,
                kind: Literal["tensor", "array", "any"] = "tensor") -> A:
    """Check that ``x`` is a tensor (or numpy array, per ``kind``) of shape ``dims``.

    ``dims`` is a sequence or a space-separated string of sizes: an int (or a string of
    digits) must match exactly, a name matches any size but the same name must have the same
    size everywhere in ``dims``, and a leading ``"..."`` matches any number of leading dims.

    Returns ``x`` unchanged. Raises :class:`InputError` naming ``name``, the expected and the
    actual shape (or the type, when ``x`` is not a tensor / array).

    Example:
        >>> import torch
        >>> check_shape(torch.zeros(4, 2), "N 2", "uv").shape
        torch.Size([4, 2])
        >>> check_shape(torch.zeros(4, 3), ("N", 2), "uv")
        Traceback (most recent call last):
        ...
        torchseam.core.checks.InputError: uv: expected shape (N, 2), got (4, 3)
    """
    want, ellipsis, shown = _parse(dims if isinstance(dims, str) else tuple(dims))
    if not isinstance(x, _KIND_TYPES[kind]):
        raise InputError(f"{name}: expected {_KIND_TEXT[kind]} of shape {shown}, "
                         f"got {type(x).__name__}")
    shape = tuple(x.shape)
    if len(shape) < len(want) if ellipsis else len(shape) != len(want):
        raise InputError(f"{name}: expected shape {shown}, got {shape}")
    seen: dict[str, int] = {}
    for s, d in zip(shape[len(shape) - len(want):], want, strict=True):
        if isinstance(d, int):
            ok = s == d
        else:
            ok = seen.setdefault(d, s) == s
        if not ok:
            raise InputError(f"{name}: expected shape {shown}, got {shape}")
    return x


def check_batch(x: Tensor | np.ndarray, name: str, batch: int, of: str = "the tracker's B"
                ) -> None:
    """Check that the leading dimension of ``x`` is ``batch`` (``of``: whose batch it is)."""
    if x.shape[0] != batch:
        raise InputError(f"{name}: expected batch size {batch} ({of}), got {x.shape[0]}")


def as_float(x: Tensor, like: Tensor) -> Tensor:
    """``x`` in ``like``'s (floating) dtype: integer and uint8 inputs, e.g. frames, are
    converted; ``x`` itself is returned when the dtypes agree."""
    return x if x.dtype == like.dtype else x.to(like.dtype)


def check_size(size: Sequence[int], name: str, minimum: int = 3) -> tuple[int, int]:
    """A (H, W) window size of two ints, each at least ``minimum``."""
    try:
        h, w = (int(s) for s in size)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected (H, W), two positive integers, "
                         f"got {size!r}") from None
    if h < minimum or w < minimum:
        raise InputError(f"{name}: expected (H, W) with H, W >= {minimum}, got {(h, w)}")
    return h, w


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """``value`` when it is one of ``choices``."""
    if value not in choices:
        raise InputError(f"{name}: expected one of {', '.join(choices)}, got {value!r}")
    return value


def check_device(x: Tensor, name: str, ref: Tensor, owner: str = "the tracker") -> None:
    """Check that ``x`` is on the device of ``ref`` (a parameter of ``owner``)."""
    if x.device != ref.device:
        raise InputError(f"{name}: on {x.device}, but {owner} is on {ref.device} "
                         f"(move one of them with .to())")

