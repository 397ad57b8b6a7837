"""The shared boundary checks (torchseam.core.checks): one error type, one message form."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchseam.core import checks
from torchseam.core.checks import InputError, check_shape
from torchseam.core.errors import TorchseamError
from torchseam.track import TrackInputError


def test_shape_ok_returns_input_in_both_forms() -> None:
    x = torch.zeros(2, 5, 7)
    assert check_shape(x, "B H W", "frames") is x
    assert check_shape(x, ["B", "H", "W"], "frames") is x
    assert check_shape(x, ("B", 5, 7), "frames") is x
    assert check_shape(x, "B 5 7", "frames") is x  # digits in the string form are fixed sizes
    assert check_shape(torch.zeros(3, 4, 4), "... 4 4", "T") is not None
    assert check_shape(torch.zeros(4, 4), "... 4 4", "T") is not None  # "..." may be empty


def test_error_type_names_argument_expected_and_actual() -> None:
    with pytest.raises(InputError, match=r"^uv: expected shape \(N, 2\), got \(4, 3\)$") as e:
        check_shape(torch.zeros(4, 3), "N 2", "uv")
    assert isinstance(e.value, TorchseamError) and isinstance(e.value, ValueError)
    assert InputError is TrackInputError  # the tracker's name still catches it


def test_wrong_ndim_and_wrong_fixed_size() -> None:
    with pytest.raises(InputError, match=r"frames: expected shape \(B, H, W\), got \(5, 7\)"):
        check_shape(torch.zeros(5, 7), "B H W", "frames")
    with pytest.raises(InputError, match=r"x: expected shape \(\.\.\., 3\), got \(\)"):
        check_shape(torch.zeros(()), "... 3", "x")
    with pytest.raises(InputError, match=r"T: expected shape \(\.\.\., 4, 4\), got \(2, 4, 3\)"):
        check_shape(torch.zeros(2, 4, 3), "... 4 4", "T")
    with pytest.raises(InputError, match=r"dist: expected shape \(5,\), got \(4,\)"):
        check_shape(torch.zeros(4), (5,), "dist")


def test_named_sizes_must_agree() -> None:
    assert check_shape(torch.zeros(3, 3), "N N", "R") is not None
    with pytest.raises(InputError, match=r"R: expected shape \(N, N\), got \(3, 4\)"):
        check_shape(torch.zeros(3, 4), "N N", "R")


def test_type_and_numpy_arrays() -> None:
    with pytest.raises(InputError, match=r"uv: expected a torch.Tensor of shape \(N, 2\), "
                                         r"got list"):
        check_shape([[1.0, 2.0]], "N 2", "uv")  # type: ignore[type-var]
    with pytest.raises(InputError, match="expected a torch.Tensor"):
        check_shape(np.zeros((4, 2)), "N 2", "uv")
    a = np.zeros((6, 8, 3), np.uint8)
    assert check_shape(a, "H W 3", "frame", kind="array") is a
    assert check_shape(a, "H W 3", "frame", kind="any") is a
    assert check_shape(torch.zeros(6, 8, 3), "H W 3", "frame", kind="any") is not None
    with pytest.raises(InputError, match=r"frame: expected shape \(H, W, 3\), got \(6, 8\)"):
        check_shape(np.zeros((6, 8)), "H W 3", "frame", kind="array")
    with pytest.raises(InputError, match="expected a numpy array"):
        check_shape(torch.zeros(6, 8, 3), "H W 3", "frame", kind="array")


def test_batch_size_dtype_choice_device() -> None:
    checks.check_batch(torch.zeros(2, 3), "frames", 2)
    with pytest.raises(InputError, match=r"frames: expected batch size 2 \(the tracker's B\), "
                                         r"got 3"):
        checks.check_batch(torch.zeros(3, 3), "frames", 2)
    like = torch.zeros(1, dtype=torch.float64)
    frames = torch.ones(2, 2, dtype=torch.uint8)
    assert checks.as_float(frames, like).dtype == torch.float64
    assert checks.as_float(like, like) is like
    assert checks.check_size([8, 9], "window") == (8, 9)
    with pytest.raises(InputError, match=r"window: expected \(H, W\) with H, W >= 3"):
        checks.check_size((2, 9), "window")
    with pytest.raises(InputError, match=r"window: expected \(H, W\), two positive integers"):
        checks.check_size("ab", "window")  # type: ignore[arg-type]
    assert checks.check_choice("soft", "peak", ("soft", "argmax")) == "soft"
    with pytest.raises(InputError, match="peak: expected one of soft, argmax, got 'x'"):
        checks.check_choice("x", "peak", ("soft", "argmax"))
    checks.check_device(torch.zeros(1), "uv", torch.zeros(1))


def test_leading_ellipsis_only() -> None:
    with pytest.raises(ValueError, match="may only lead"):
        check_shape(torch.zeros(2, 2), "2 ... 2", "x")
