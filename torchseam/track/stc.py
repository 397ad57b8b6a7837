"""STC: spatio-temporal context tracking (Zhang et al., ECCV 2014), batched and differentiable.

METHOD.md section 2. Everything works on (B, H, W) context windows: B sequences step together,
with no Python loop over the batch. Small functional ops (kornia style) plus the :class:`STC`
module that holds the learnable parameters alpha, beta, rho, sigma (positive ones stored as logs,
rho as a logit) and runs the tracker.

Window convention: a context window of size (H, W) around the centre (u, v) holds image pixel
(row v - H//2 + i, column u - W//2 + j) at index (i, j), so the centre sits at index
(H//2, W//2), which is where the confidence map of eq. 1 peaks. Pixel coordinates are
(u, v) = (column, row) with pixel centres at integers (OpenCV). Offsets returned by
:func:`locate_peak` are (du, dv) from that centre index.

Equations (METHOD.md numbering), all in the ``rfft2`` half spectrum (identical to ``fft2`` for
real signals, half the work):

- eq. 1   confidence map ``c(x) = b exp(-|x / alpha|^beta)``, normalised to sum 1 (that is b);
- eq. 4-5 context prior ``(I(z) - mean I) * w_sigma(z)``, ``w_sigma = a exp(-|z|^2 / sigma^2)``
  times a Hamming window, normalised to sum 1 (that is a);
- eq. 8   ``h_sc = IFFT(FFT(c) / (FFT(prior) + eps))``;
- eq. 9   ``H_stc <- (1 - rho) H_stc + rho h_sc``, ``H_stc = h_sc`` on the first frame;
- eq. 10  ``c_t(x) = IFFT(FFT(H_stc) FFT(prior_t))``, the location is its peak.

Reference-implementation details kept (the authors' MATLAB ``STC.m``): the patch mean is
subtracted and the window applied after it, both maps are normalised to sum 1, sigma starts at
the mean target side, eps is added in the division, the context is re-cropped at the new
location for learning, border pixels are replicated, and the optional scale update
``sigma <- sigma * s`` every frame with ``s <- (1 - lambda) s + lambda mean_5 sqrt(c_max[t] /
c_max[t-1])`` every ``num + 2`` frames (lambda = 0.25, num = 5). Deliberate differences: the
exponents follow METHOD.md (the MATLAB has ``exp(-0.5 r / alpha)`` and ``exp(-0.5 r^2 /
sigma^2)``, i.e. alpha and sigma^2 doubled), the Hamming window is applied on both axes (the
MATLAB uses ``hamming`` on rows and ``hann`` on columns), and the window centre is index H//2
(the MATLAB's is H/2 - 1, 1-based H/2): a pure convention, it moves no result.

Sub-pixel extension (the reference is integer throughout): with ``peak="subpixel"`` or
``"soft"`` the location is fractional; the window is still an integer crop at the rounded
location, and the confidence map learnt there is moved by the fractional remainder with a
Fourier phase ramp (:func:`fourier_shift`), so the model is not biased toward the pixel grid.
With ``peak="argmax"`` the ramp is exactly 1 and the tracker is the reference's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import Tensor, nn

from torchseam.core.checks import (
    InputError,
    as_float,
    check_batch,
    check_choice,
    check_device,
    check_shape,
    check_size,
)
from torchseam.track.config import MATLAB_EPS, TrackerConfig

__all__ = [
    "PEAK_MODES",
    "CROP_MODES",
    "STC",
    "STCDetection",
    "STCState",
    "confidence_map",
    "context_prior",
    "extract_windows",
    "fourier_shift",
    "hamming_window_2d",
    "learn_spatial_context",
    "learn_spatial_context_reg",
    "locate_peak",
    "peak_quality",
    "stc_response",
    "update_context_model",
    "weight_window",
]

PEAK_MODES = ("subpixel", "soft", "argmax")
CROP_MODES = ("nearest", "bilinear")
_D = TrackerConfig()  # the defaults


def _offsets(n: int, ref: Tensor) -> Tensor:
    """Index minus centre index, ``arange(n) - n // 2``, on ``ref``'s device and dtype."""
    return torch.arange(n, device=ref.device, dtype=ref.dtype) - (n // 2)


_INDEX_CACHE: dict[tuple, Tensor] = {}


def cached(key: tuple, make: Callable[[], Tensor]) -> Tensor:
    """Small constant index tensors, built once per (kind, sizes, device): saves tiny ops."""
    t = _INDEX_CACHE.get(key)
    if t is None:
        if len(_INDEX_CACHE) > 256:
            _INDEX_CACHE.clear()
        # made outside inference mode even when first asked for inside it: an inference
        # tensor in the cache would break every later call that needs gradients (fitting)
        with torch.inference_mode(False):
            t = _INDEX_CACHE[key] = make()
    return t


def _window_index(h: int, w: int, wi: int, device: torch.device) -> Tensor:
    """(h, w) flat offsets ``(i - h//2) * wi + (j - w//2)`` of a window in a frame of width wi."""
    return cached(("win", h, w, wi, device), lambda: (
        (torch.arange(h, device=device) - h // 2)[:, None] * wi
        + (torch.arange(w, device=device) - w // 2)[None, :]))


def _scalar(x: float | Tensor, ref: Tensor | None = None) -> Tensor:
    if isinstance(x, Tensor):
        return x
    if ref is None:
        return torch.tensor(float(x))
    return torch.tensor(float(x), device=ref.device, dtype=ref.dtype)


# --------------------------------------------------------------------------- windows and maps

def hamming_window_2d(size: Sequence[int], *, device: torch.device | str | None = None,
                      dtype: torch.dtype | None = None) -> Tensor:
    """Separable symmetric Hamming window ``hamming(H)[:, None] * hamming(W)[None, :]``.

    Args:
        size: (H, W).

    Returns:
        (H, W) tensor, 1 at the centre for odd sizes, 0.08 at the corners.

    Example:
        >>> hamming_window_2d((5, 5))[2, 2].item()
        1.0
    """
    h, w = check_size(size, "size")
    dtype = dtype or torch.get_default_dtype()
    wh = torch.hamming_window(h, periodic=False, device=device, dtype=dtype)
    ww = torch.hamming_window(w, periodic=False, device=device, dtype=dtype)
    return wh[:, None] * ww[None, :]


def confidence_map(size: Sequence[int], alpha: float | Tensor, beta: float | Tensor, *,
                   device: torch.device | str | None = None,
                   dtype: torch.dtype | None = None) -> Tensor:
    """Target confidence map of eq. 1, ``exp(-|x / alpha|^beta)`` normalised to sum 1.

    Args:
        size: (H, W); the map peaks at index (H//2, W//2).
        alpha, beta: positive scalars (floats or 0-dim tensors; gradients flow to tensors).

    Returns:
        (H, W) tensor summing to 1.

    Example:
        >>> c = confidence_map((64, 64), 2.25, 1.0)
        >>> tuple(c.shape), int(c.argmax()) == 32 * 64 + 32
        ((64, 64), True)
    """
    h, w = check_size(size, "size")
    ref = alpha if isinstance(alpha, Tensor) else beta if isinstance(beta, Tensor) else None
    if ref is not None:
        device, dtype = device or ref.device, dtype or ref.dtype
    dtype = dtype or torch.get_default_dtype()
    proto = torch.empty(0, device=device, dtype=dtype)
    r2 = _offsets(h, proto)[:, None] ** 2 + _offsets(w, proto)[None, :] ** 2
    pos = r2 > 0
    r = torch.sqrt(torch.where(pos, r2, torch.ones_like(r2)))  # safe at 0 for the gradient
    alpha, beta = _scalar(alpha, proto), _scalar(beta, proto)
    e = torch.where(pos, (r / alpha) ** beta, torch.zeros_like(r))
    c = torch.exp(-e)
    return c / c.sum()


def weight_window(size: Sequence[int], sigma: float | Tensor, *, hamming: bool = True,
                  device: torch.device | str | None = None,
                  dtype: torch.dtype | None = None) -> Tensor:
    """Focus window of eq. 5, ``exp(-|z|^2 / sigma^2)`` times a Hamming window, sum 1.

    Args:
        size: (H, W).
        sigma: a positive scalar (float or 0-dim tensor) or a (B,) tensor, one per sequence.
        hamming: multiply by :func:`hamming_window_2d` (reference implementation: yes).

    Returns:
        (H, W) for a scalar sigma, (B, H, W) for a (B,) sigma; each map sums to 1.

    Example:
        >>> weight_window((64, 64), torch.tensor([16.0, 32.0])).shape
        torch.Size([2, 64, 64])
    """
    h, w = check_size(size, "size")
    if isinstance(sigma, Tensor):
        if sigma.ndim > 1:
            raise InputError(
                f"sigma: expected a scalar or shape (B,), got {tuple(sigma.shape)}")
        device, dtype = device or sigma.device, dtype or sigma.dtype
    dtype = dtype or torch.get_default_dtype()
    proto = torch.empty(0, device=device, dtype=dtype)
    r2 = _offsets(h, proto)[:, None] ** 2 + _offsets(w, proto)[None, :] ** 2
    sigma = _scalar(sigma, proto)
    s2 = (sigma**2).reshape(sigma.shape + (1, 1))
    win = torch.exp(-r2 / s2)
    if hamming:
        win = win * hamming_window_2d((h, w), device=proto.device, dtype=dtype)
    return win / win.sum(dim=(-2, -1), keepdim=True)


def extract_windows(frames: Tensor, centres: Tensor, size: Sequence[int], *,
                    mode: str = "nearest", dtype: torch.dtype | None = None) -> Tensor:
    """Crop (H, W) context windows around (u, v) centres, replicating border pixels.

    ``mode="nearest"``: the centre is rounded to the nearest pixel and the window is an integer
    gather (exact pixel values, like the reference ``get_context``); no gradient w.r.t. the
    centres. ``mode="bilinear"``: an (H+1, W+1) integer gather at ``floor(centre)`` blended with
    the fractional offset, i.e. bilinear sampling at exactly ``centre + offset`` (what
    ``grid_sample(align_corners=True, padding_mode="border")`` gives, without turning the whole
    frame into floats); differentiable w.r.t. the centres and the frames. Both crop only the
    window, so uint8 frames stay cheap: only the (B, H, W) crop is converted.

    Args:
        frames: (B, Himg, Wimg) grey frames, any real dtype (uint8 is fine).
        centres: (B, 2) float (u, v) = (column, row) window centres; any value (outside the
            image the window replicates the border).
        size: (H, W) of the window.
        mode: ``"nearest"`` or ``"bilinear"``.
        dtype: output dtype; default the frames' dtype if floating, else the centres' dtype.

    Returns:
        (B, H, W); pixel (i, j) samples the image at (row v - H//2 + i, column u - W//2 + j).

    Example:
        >>> img = torch.arange(100.0).reshape(1, 10, 10)
        >>> extract_windows(img, torch.tensor([[4.0, 3.0]]), (3, 3))[0]
        tensor([[23., 24., 25.],
                [33., 34., 35.],
                [43., 44., 45.]])
    """
    check_shape(frames, ("B", "Himg", "Wimg"), "frames")
    check_shape(centres, (frames.shape[0], 2), "centres")
    check_device(centres, "centres", frames)
    check_choice(mode, "mode", CROP_MODES)
    h, w = check_size(size, "size")
    if dtype is None:
        dtype = frames.dtype if frames.is_floating_point() else (
            centres.dtype if centres.is_floating_point() else torch.get_default_dtype())
    if mode == "nearest":
        return _gather_windows(frames, torch.floor(centres.detach() + 0.5).long(), h, w
                               ).to(dtype)
    c0 = torch.floor(centres.detach())
    frac = (centres - c0).to(dtype)  # (B, 2), carries the gradient w.r.t. the centres
    # window pixel (i, j) samples centre + (j - w//2, i - h//2): blend p[i, j] .. p[i+1, j+1]
    shift = cached(("bshift", h, w, c0.device), lambda: torch.tensor(
        [(w + 1) // 2 - w // 2, (h + 1) // 2 - h // 2], device=c0.device))
    p = _gather_windows(frames, c0.long() + shift, h + 1, w + 1).to(dtype)  # (B, H+1, W+1)
    fu = frac[:, 0, None, None]
    fv = frac[:, 1, None, None]
    top = p[:, :-1, :-1] + fu * (p[:, :-1, 1:] - p[:, :-1, :-1])
    bot = p[:, 1:, :-1] + fu * (p[:, 1:, 1:] - p[:, 1:, :-1])
    return top + fv * (bot - top)


def _gather_windows(frames: Tensor, c: Tensor, h: int, w: int) -> Tensor:
    """Integer crops (B, h, w) whose index (h//2, w//2) is pixel c (B, 2) long (u, v); border
    pixels replicated. A single flat gather when no window touches the border."""
    B, hi, wi = frames.shape
    u, v = c[:, 0], c[:, 1]
    inside = ((u >= w // 2) & (u < wi - (w - 1 - w // 2)) & (v >= h // 2)
              & (v < hi - (h - 1 - h // 2)))
    if frames.is_contiguous() and frames.device.type == "cpu" and bool(inside.all()):
        idx = (v * wi + u)[:, None, None] + _window_index(h, w, wi, frames.device)
        return frames.reshape(B, hi * wi).gather(1, idx.reshape(B, h * w)).reshape(B, h, w)
    ar_h = cached(("ar", h, frames.device), lambda: torch.arange(h, device=frames.device))
    ar_w = cached(("ar", w, frames.device), lambda: torch.arange(w, device=frames.device))
    rows = (v[:, None] + (ar_h - h // 2)).clamp_(0, hi - 1)
    cols = (u[:, None] + (ar_w - w // 2)).clamp_(0, wi - 1)
    bidx = cached(("b", B, frames.device), lambda: torch.arange(B, device=frames.device))
    return frames[bidx[:, None, None], rows[:, :, None], cols[:, None, :]]


def context_prior(windows: Tensor, weight: Tensor) -> Tensor:
    """Context prior of eq. 4: ``(I - mean(I)) * w_sigma`` per window.

    Args:
        windows: (B, H, W) grey context windows.
        weight: (H, W) or (B, H, W) focus window (:func:`weight_window`).

    Returns:
        (B, H, W).

    Example:
        >>> context_prior(torch.ones(2, 8, 8), weight_window((8, 8), 4.0)).abs().max().item()
        0.0
    """
    check_shape(windows, ("B", "H", "W"), "windows")
    if weight.shape[-2:] != windows.shape[-2:] or weight.ndim not in (2, 3):
        raise InputError(f"weight: expected shape {tuple(windows.shape[-2:])} or "
                         f"(B, {windows.shape[-2]}, {windows.shape[-1]}), "
                         f"got {tuple(weight.shape)}")
    return (windows - windows.mean(dim=(-2, -1), keepdim=True)) * weight


def learn_spatial_context(conf_f: Tensor, prior_f: Tensor, eps: float = MATLAB_EPS) -> Tensor:
    """Spatial context model of eq. 8 in the frequency domain: ``FFT(c) / (FFT(prior) + eps)``.

    Args:
        conf_f: (H, W//2+1) ``rfft2`` of the confidence map (:func:`confidence_map`).
        prior_f: (B, H, W//2+1) ``rfft2`` of the context priors (:func:`context_prior`).
        eps: added to the denominator (the reference adds MATLAB's eps).

    Returns:
        (B, H, W//2+1) complex, ``rfft2(h_sc)``.

    Example:
        >>> c_f = torch.fft.rfft2(confidence_map((8, 8), 2.25, 1.0))
        >>> p_f = torch.fft.rfft2(torch.randn(1, 8, 8, dtype=torch.float64).float())
        >>> learn_spatial_context(c_f, p_f).shape
        torch.Size([1, 8, 5])
    """
    return conf_f / (prior_f + eps) if eps else conf_f / prior_f


def learn_spatial_context_reg(conf_f: Tensor, prior_f: Tensor, reg: Tensor | float,
                              eps: float = MATLAB_EPS) -> Tensor:
    """Regularised (Wiener) spatial context model: eq. 8 with a noise floor in the division,
    ``FFT(c) conj(FFT(prior)) / (|FFT(prior)|^2 + reg * mean |FFT(prior)|^2 + eps)``.

    Eq. 8 divides by ``FFT(prior)``: at the frequencies where a clean window (a thin stripe on a
    dark background) has almost no energy the model's gain is huge, so the arc's noise there
    dominates the next response, and the context model learns its own error. ``reg`` is the
    floor relative to the window's mean spectral power (scale-free; 0 gives eq. 8 without eps).

    Args:
        conf_f: (H, W//2+1) or (B, H, W//2+1) ``rfft2`` of the confidence map.
        prior_f: (B, H, W//2+1) ``rfft2`` of the context priors.
        reg: >= 0 scalar (float or 0-dim tensor, gradients flow to it).
        eps: added to the denominator (a flat window, e.g. a saturated arc flash, has no power
            at all: the model then learns 0 instead of NaN).

    Returns:
        (B, H, W//2+1) complex, ``rfft2(h_sc)``.

    Example:
        >>> c_f = torch.fft.rfft2(confidence_map((8, 8), 2.25, 1.0))
        >>> p_f = torch.fft.rfft2(torch.randn(1, 8, 8))
        >>> torch.allclose(learn_spatial_context_reg(c_f, p_f, 0.0), c_f / p_f, atol=1e-4)
        True
    """
    check_shape(prior_f, ("B", "H", "W2"), "prior_f")
    power = prior_f.real.square() + prior_f.imag.square()
    floor = power.mean(dim=(-2, -1), keepdim=True) * reg
    return conf_f * prior_f.conj() / (power + floor + eps)


def fourier_shift(shift: Tensor, size: Sequence[int]) -> Tensor:
    """Phase ramp that moves a map by ``shift`` (du, dv) px when multiplied onto its rfft2.

    ``irfft2(rfft2(m) * fourier_shift(d, m.shape))`` is ``m`` circularly shifted by the
    (sub-pixel) offset d, band-limited interpolation; a zero shift gives exactly 1. The tracker
    uses it to centre the confidence map of eq. 1 on a sub-pixel target in an integer crop.

    Args:
        shift: (B, 2) offsets (du, dv), real.
        size: (H, W) of the maps.

    Returns:
        (B, H, W//2+1) complex.

    Example:
        >>> m = confidence_map((16, 16), 2.25, 1.0)
        >>> r = torch.fft.irfft2(torch.fft.rfft2(m) * fourier_shift(torch.tensor([[2.0, -1.0]]),
        ...                      (16, 16)), s=(16, 16))
        >>> torch.allclose(r[0], m.roll((-1, 2), (0, 1)), atol=1e-6)
        True
    """
    h, w = check_size(size, "size")
    check_shape(shift, ("B", 2), "shift")
    fy, fx = cached(("freq", h, w, shift.device, shift.dtype), lambda: torch.cat([
        torch.fft.fftfreq(h, device=shift.device, dtype=shift.dtype),
        torch.fft.rfftfreq(w, device=shift.device, dtype=shift.dtype)]) * (-2.0 * math.pi)
                     ).split([h, w // 2 + 1])
    ay, ax = shift[:, 1:2] * fy, shift[:, 0:1] * fx  # (B, H), (B, W//2+1)
    py, px = torch.polar(torch.ones_like(ay), ay), torch.polar(torch.ones_like(ax), ax)
    return py[:, :, None] * px[:, None, :]


def update_context_model(H_f: Tensor, h_f: Tensor, rho: Tensor | float) -> Tensor:
    """Temporal update of eq. 9: ``(1 - rho) H_stc + rho h_sc`` (in the frequency domain).

    Args:
        H_f: (B, H, W//2+1) current spatio-temporal model.
        h_f: (B, H, W//2+1) spatial model of this frame (:func:`learn_spatial_context`).
        rho: learning rate, a scalar or (B,) (e.g. scaled per sequence by the fusion's trust).

    Returns:
        (B, H, W//2+1).

    Example:
        >>> update_context_model(torch.zeros(1, 2, 2), torch.ones(1, 2, 2), 0.25).sum().item()
        1.0
    """
    if isinstance(rho, Tensor):
        rho = (rho[:, None, None] if rho.ndim == 1 else rho).to(H_f.dtype)
        return torch.lerp(H_f, h_f, rho)  # one pass (this runs on every frame)
    return H_f + rho * (h_f - H_f)


def stc_response(H_f: Tensor, prior_f: Tensor, size: Sequence[int]) -> Tensor:
    """Confidence map of a new frame, eq. 10: ``IFFT(FFT(H_stc) FFT(prior))``.

    Args:
        H_f: (B, H, W//2+1) spatio-temporal model.
        prior_f: (B, H, W//2+1) ``rfft2`` of the new frame's context prior.
        size: (H, W) of the windows (needed to invert the half spectrum).

    Returns:
        (B, H, W) real confidence map; the target is at its peak.

    Example:
        >>> c = confidence_map((8, 8), 2.25, 1.0)
        >>> p_f = torch.fft.rfft2(torch.randn(1, 8, 8))
        >>> r = stc_response(learn_spatial_context(torch.fft.rfft2(c), p_f), p_f, (8, 8))
        >>> torch.allclose(r[0], c, atol=1e-5)
        True
    """
    return torch.fft.irfft2(H_f * prior_f, s=tuple(size))


# --------------------------------------------------------------------------- peaks

def _block_max(x: Tensor) -> Tensor:
    """(B, H/2, W/2) maxima of the 2x2 blocks of (B, H, W) ``x`` (H, W even).

    Without a gradient to carry, the maximum of the even and odd columns, then of the even and
    odd rows: the values of ``x.reshape(B, H/2, 2, W/2, 2).amax(dim=(2, 4))``, whose strided
    reduction took ~8x the time (1.4 ms of a B = 64 step). With one, ``amax`` itself (it splits
    the gradient evenly among tied maxima, two ``maximum`` calls would not)."""
    B, h, w = x.shape
    if x.requires_grad:
        return x.reshape(B, h // 2, 2, w // 2, 2).amax(dim=(2, 4))
    c = torch.maximum(x[:, :, 0::2], x[:, :, 1::2])
    return torch.maximum(c[:, 0::2], c[:, 1::2])


def _interior_local_max(x: Tensor) -> Tensor:
    """(B, H-2, W-2) values of x's interior where they are 3x3 local maxima, -inf elsewhere
    (separable running maximum without padding: cheaper than max_pool2d)."""
    m = torch.maximum(torch.maximum(x[:, :-2], x[:, 1:-1]), x[:, 2:])
    m = torch.maximum(torch.maximum(m[:, :, :-2], m[:, :, 1:-1]), m[:, :, 2:])
    inner = x[:, 1:-1, 1:-1]
    return torch.where(inner >= m, inner, -torch.inf)


def _peak_tables(h: int, w: int, exclude: int, device: torch.device, dtype: torch.dtype
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor, int, int]:
    """Lookup tables indexed by the flat argmax of an (h, w) map, built once (a few MB):

    - ``area`` (h w, P): flat indices of the circular (2 e + 1)^2 area around each position
      (e = max(exclude, 1));
    - ``base`` (h w, 2): the position's (du, dv) offset from the centre index, in ``dtype``;
    - ``nb`` (4,): positions of the 4 neighbours (left, right, up, down) inside ``area``;
    - ``barea`` (h w, P2): indices into the searched interior of the 2x2-block map (see
      :func:`_analyse`) of the blocks near each position; ``n_in`` (an extra, dummy slot) for
      blocks outside it. Also returns the block map's (bh, bw).
    """
    def make() -> Tensor:
        e = max(exclude, 1)
        n = 2 * e + 1
        r = torch.arange(-e, e + 1)
        ii = torch.arange(h * w) // w
        jj = torch.arange(h * w) % w
        area = ((ii[:, None, None] + r[None, :, None]) % h * w
                + (jj[:, None, None] + r[None, None, :]) % w).reshape(h * w, n * n)
        c = e * n + e
        nb = torch.tensor([c - 1, c + 1, c - n, c + n])
        base = torch.stack([jj - w // 2, ii - h // 2], dim=1)
        if h % 2 or w % 2:
            bh, bw, bi, bj, eb = h, w, ii, jj, exclude
        else:
            bh, bw, bi, bj, eb = h // 2, w // 2, ii // 2, jj // 2, (exclude + 1) // 2
        rb = torch.arange(-eb, eb + 1)
        rr = (bi[:, None, None] + rb[None, :, None]) % bh - 1
        cc = (bj[:, None, None] + rb[None, None, :]) % bw - 1
        inside = (rr >= 0) & (rr < bh - 2) & (cc >= 0) & (cc < bw - 2)
        n_in = (bh - 2) * (bw - 2)
        barea = torch.where(inside, rr * (bw - 2) + cc, n_in).reshape(h * w, -1)
        return torch.cat([area, barea, base.to(area.dtype), nb[None].expand(h * w, 4)],
                         dim=1).to(device)
    t = cached(("peak", h, w, exclude, device), make)
    bh, bw = (h, w) if h % 2 or w % 2 else (h // 2, w // 2)
    p = (2 * max(exclude, 1) + 1) ** 2
    p2 = t.shape[1] - p - 6
    area = cached(("peakarea", h, w, exclude, device), lambda: t[:, :p].contiguous())
    barea = cached(("peakbarea", h, w, exclude, device), lambda: t[:, p:p + p2].contiguous())
    nb = cached(("peaknb", h, w, exclude, device), lambda: t[0, p + p2 + 2:].contiguous())
    base = cached(("peakbase", h, w, exclude, device, dtype),
                   lambda: t[:, p + p2:p + p2 + 2].to(dtype).contiguous())
    return area, base, nb, barea, bh, bw


def _analyse(response: Tensor, mode: str, temperature: float | Tensor, exclude: int,
             quality: bool) -> tuple[Tensor, dict[str, Tensor]]:
    """Peak offset (B, 2) and, if asked, the quality dict; one argmax shared by both."""
    B, h, w = response.shape
    flat = response.reshape(B, h * w)
    peak, idx = flat.max(dim=1)
    area_t, base_t, nb, barea_t, bh, bw = _peak_tables(h, w, exclude, response.device,
                                                       response.dtype)
    area = area_t.index_select(0, idx)  # (B, P), circular like the map
    av = flat.gather(1, area)
    base = base_t.index_select(0, idx)
    if mode == "argmax":
        off = base
    elif mode == "soft":
        mean = flat.mean(dim=1, keepdim=True)
        m = (flat - mean) / (peak[:, None] - mean).clamp_min(torch.finfo(flat.dtype).tiny)
        p = torch.softmax(m / temperature, dim=1).reshape(B, h, w)
        du = (p.sum(dim=1) * _offsets(w, flat)).sum(dim=1)
        dv = (p.sum(dim=2) * _offsets(h, flat)).sum(dim=1)
        off = torch.stack([du, dv], dim=1)
    else:  # subpixel: a parabola through the peak and its two neighbours, per axis
        v = av.index_select(1, nb).reshape(B, 2, 2)  # [[left, right], [up, down]]
        den = v[:, :, 0] + v[:, :, 1] - 2.0 * peak[:, None]
        ok = den < 0
        d = 0.5 * (v[:, :, 0] - v[:, :, 1]) / torch.where(ok, den, -1.0)
        off = base + torch.where(ok, d, 0.0).clamp(-0.5, 0.5)
    if not quality:
        return off, {}
    # sidelobe = the map outside the (2 exclude + 1)^2 area around the peak
    N, P = h * w, area.shape[1]
    var_all, mean_all = torch.var_mean(flat, dim=1, correction=0)
    mean_s = (mean_all * N - av.sum(dim=1)) / (N - P)
    var_s = ((var_all + mean_all * mean_all) * N - (av * av).sum(dim=1)) / (N - P) \
        - mean_s * mean_s
    tiny = torch.finfo(response.dtype).tiny
    height = peak - mean_s
    psr = height / torch.sqrt(var_s.clamp_min(tiny))
    # competing peaks: local maxima of the 2x2-block maxima (a quarter of the map), outside the
    # peak area (blocks within ceil(exclude / 2) blocks of the peak's block, circularly)
    blocks = response if bh == h else _block_max(response)
    cand = _interior_local_max(blocks).reshape(B, (bh - 2) * (bw - 2))
    cand = torch.cat([cand, cand.new_full((B, 1), -torch.inf)], dim=1)  # + a dummy slot
    cand = cand.scatter(1, barea_t.index_select(0, idx), -torch.inf)
    second = torch.maximum(cand.amax(dim=1), mean_s)  # no candidate at all: ratio 0
    height = height.clamp_min(tiny)
    second_ratio = ((second - mean_s) / height).clamp(0.0, 1.0)
    n_peaks = 1 + (cand > (mean_s + 0.5 * height)[:, None]).sum(dim=1)
    return off, {"peak": peak, "psr": psr, "second_ratio": second_ratio, "n_peaks": n_peaks}


def locate_peak(response: Tensor, mode: str = "subpixel",
                temperature: float | Tensor = 0.05) -> Tensor:
    """Peak of (B, H, W) confidence maps as (du, dv) offsets from the centre index (H//2, W//2).

    Modes:
        ``"argmax"``: integer argmax (eq. 11, the reference); no gradient.
        ``"subpixel"``: argmax refined by a 1-D parabola through the peak and its two neighbours
            on each axis (neighbours wrap, like the circular map), clamped to +-0.5 px;
            differentiable w.r.t. the map values (inference default, also fine for training).
        ``"soft"``: soft-argmax, the expectation of the offset under ``softmax(m / T)`` over the
            whole map normalised as ``m = (c - mean) / (max - mean)`` (T is scale-free: T = 0.05
            puts the peak 20 logits above the mean; T -> 0 gives the argmax); fully
            differentiable, also w.r.t. T, and it spreads gradients over competing peaks.

    Args:
        response: (B, H, W) confidence maps.
        mode: see above.
        temperature: T > 0 for ``"soft"`` (float or 0-dim tensor, learnable).

    Returns:
        (B, 2) float offsets (du, dv) in pixels.

    Example:
        >>> c = confidence_map((16, 16), 2.25, 1.0).roll((2, -3), (0, 1))[None]
        >>> locate_peak(c, "argmax")
        tensor([[-3.,  2.]])
    """
    check_shape(response, ("B", "H", "W"), "response")
    check_choice(mode, "mode", PEAK_MODES)
    return _analyse(response, mode, temperature, 1, quality=False)[0]


def peak_quality(response: Tensor, exclude: int = 5) -> dict[str, Tensor]:
    """Peak-quality scores of (B, H, W) confidence maps (the drift guard's inputs).

    - ``peak``: the maximum value.
    - ``psr``: peak-to-sidelobe ratio ``(peak - mean_s) / std_s`` over the sidelobe, i.e. the
      map outside the (2 exclude + 1)^2 square around the peak (taken circularly, like the
      map; sharpness, scale-free).
    - ``second_ratio``: ``(c2 - mean_s) / (peak - mean_s)`` clamped to [0, 1], where c2 is the
      highest local maximum outside that square: ~0 for one clean peak, ~1 when another peak
      competes (the multi-peak failure of METHOD.md section 2). For speed the local maxima
      are taken on the 2x2-block maxima of the map (3x3 blocks, so peaks closer than ~2 px
      merge), the square is rounded up to whole blocks (maps with an odd side: per pixel)
      and the outermost ring of blocks is not searched.
    - ``n_peaks``: such local maxima above half the peak height (counted from mean_s), the
      main peak included (int64, no gradient).

    ``peak``, ``psr`` and ``second_ratio`` are differentiable almost everywhere.

    Args:
        response: (B, H, W) confidence maps.
        exclude: half-size of the square around the peak left out of the sidelobe.

    Returns:
        dict of (B,) tensors.

    Example:
        >>> q = peak_quality(confidence_map((32, 32), 2.25, 1.0)[None])
        >>> bool(q["psr"] > 10), q["n_peaks"].tolist()
        (True, [1])
    """
    check_shape(response, ("B", "H", "W"), "response")
    return _analyse(response, "argmax", 1.0, exclude, quality=True)[1]


# --------------------------------------------------------------------------- module

@dataclass
class STCState:
    """Per-batch tracker state (all tensors batched over B sequences).

    Attributes:
        H_f: (B, H, W//2+1) complex, rfft2 of the spatio-temporal context model H_stc.
        pos: (B, 2) current (u, v) location.
        sigma: (B,) current focus width (changes only with the scale update).
        scale: (B,) scale factor s of the scale update.
        maxconf: (B, n) the last n <= num + 1 values of c_max (scale update only).
        frame: number of frames learned so far (the reference's 1-based frame index).
        window: (H, W) or (B, H, W) focus window w_sigma (cached, derived from sigma).
        conf_f: (H, W//2+1) rfft2 of the confidence map (cached, derived from alpha, beta).
        H_ref: (B, H, W//2+1) complex start model (mean of H_stc over the first
            ``anchor_frames`` frames) when the module anchors detection, else None.
    """

    H_f: Tensor
    pos: Tensor
    sigma: Tensor
    scale: Tensor
    maxconf: Tensor
    frame: int
    window: Tensor
    conf_f: Tensor
    H_ref: Tensor | None = None

    def detach(self) -> STCState:
        """A copy cut from the autograd graph (truncated BPTT). Cached parameter-derived
        tensors must be rebuilt afterwards: use :meth:`STC.detach_state`."""
        kw: dict[str, Any] = {f.name: (v.detach() if isinstance(v, Tensor) else v)
                              for f in fields(self) for v in [getattr(self, f.name)]}
        return STCState(**kw)


@dataclass
class STCDetection:
    """Result of :meth:`STC.detect` on one frame.

    Attributes:
        uv: (B, 2) located (u, v) (crop centre + peak offset).
        centre: (B, 2) the centre the window was cropped at (rounded in ``"nearest"`` mode).
        response: (B, H, W) confidence map (eq. 10).
        quality: :func:`peak_quality` of the response.
    """

    uv: Tensor
    centre: Tensor
    response: Tensor
    quality: dict[str, Tensor]


class STC(nn.Module):
    """Batched spatio-temporal context tracker (METHOD.md section 2).

    Functional core: :meth:`init_state`, :meth:`detect` (eq. 10-11), :meth:`learn` (eq. 8-9,
    scale update), :meth:`track` (plain STC: detect at the last location, learn at the new one).
    Stateful convenience: :meth:`init`, :meth:`step`; whole sequences: :meth:`forward`.

    Parameters (0-dim; ``nn.Parameter`` when ``learnable`` else buffers), read through the
    properties ``alpha``, ``beta``, ``rho``, ``sigma``, ``temperature``: stored as
    ``log_alpha``, ``log_beta``, ``logit_rho``, ``log_sigma``, ``log_temperature`` so that
    gradient steps keep them positive (rho in (0, 1)).

    For inference wrap the calls in ``torch.inference_mode()`` (no autograd bookkeeping).

    Args:
        window: (H, W) context window, twice the target (METHOD.md).
        target: (h, w) target size; sigma defaults to its mean side.
        alpha, beta: confidence map shape (eq. 1); paper 2.25, 1.
        rho: learning rate (eq. 9); paper 0.075.
        sigma: initial focus width (eq. 5); default ``mean(target)``.
        eps: added in the eq. 8 division.
        reg: > 0: eq. 8 regularised (:func:`learn_spatial_context_reg`, ``eps`` added too),
            learnable (``log_reg``); 0: eq. 8 as the paper.
        anchor: in [0, 1): detection (eq. 10) with ``(1 - anchor) H_stc + anchor H_ref``,
            ``H_ref`` the model of the first ``anchor_frames`` frames (the clean start, learnt
            at TIPM's point): an absolute reference that the context model's own drift does
            not move; learnable (``logit_anchor``); 0: off (the paper).
        anchor_frames: frames averaged into ``H_ref``.
        scale_update: enable the reference's scale update (lambda ``scale_lambda`` over
            ``scale_frames`` frames).
        peak: ``"subpixel"`` | ``"soft"`` | ``"argmax"`` (:func:`locate_peak`).
        temperature: soft-argmax temperature.
        crop: ``"nearest"`` | ``"bilinear"`` (:func:`extract_windows`).
        exclude: half-size of the peak area left out of the sidelobe (:func:`peak_quality`).
        learnable: register alpha, beta, rho, sigma, temperature as parameters.

    Example:
        >>> frames = torch.rand(2, 5, 120, 160)
        >>> uv, q = STC(window=(32, 32), target=(16, 16))(frames, torch.tensor([[80., 60.]] * 2))
        >>> tuple(uv.shape), tuple(q["psr"].shape)
        ((2, 5, 2), (2, 5))
    """

    # the raw parameters (registered as parameters or buffers in __init__)
    log_alpha: Tensor
    log_beta: Tensor
    logit_rho: Tensor
    log_sigma: Tensor
    log_temperature: Tensor
    log_reg: Tensor
    logit_anchor: Tensor

    def __init__(self, window: Sequence[int] = _D.window, target: Sequence[int] = _D.target, *,
                 alpha: float = _D.alpha, beta: float = _D.beta, rho: float = _D.rho,
                 sigma: float | None = _D.sigma, eps: float = _D.eps,
                 scale_update: bool = _D.scale_update, scale_lambda: float = _D.scale_lambda,
                 scale_frames: int = _D.scale_frames, peak: str = _D.peak,
                 temperature: float = _D.temperature, crop: str = _D.crop,
                 exclude: int = _D.exclude, reg: float = _D.reg, anchor: float = _D.anchor,
                 anchor_frames: int = _D.anchor_frames,
                 learnable: bool = _D.learnable) -> None:
        super().__init__()
        self.window_size = check_size(window, "window")
        self.target_size = tuple(int(t) for t in target)
        if len(self.target_size) != 2 or min(self.target_size) < 1:
            raise InputError(f"target: expected (h, w), two positive integers, got {target!r}")
        self.peak = check_choice(peak, "peak", PEAK_MODES)
        self.crop = check_choice(crop, "crop", CROP_MODES)
        if sigma is None:
            sigma = float(sum(target)) / len(target)
        for name, val in (("alpha", alpha), ("beta", beta), ("sigma", sigma),
                          ("temperature", temperature)):
            if not val > 0:
                raise InputError(f"{name}: expected > 0, got {val}")
        if not eps >= 0:
            raise InputError(f"eps: expected >= 0, got {eps}")
        if not 0.0 < rho < 1.0:
            raise InputError(f"rho: expected in (0, 1), got {rho}")
        if not reg >= 0:
            raise InputError(f"reg: expected >= 0, got {reg}")
        if not 0.0 <= anchor < 1.0:
            raise InputError(f"anchor: expected in [0, 1), got {anchor}")
        if anchor_frames < 1:
            raise InputError(f"anchor_frames: expected >= 1, got {anchor_frames}")
        if not 0.0 <= scale_lambda <= 1.0 or scale_frames < 1:
            raise InputError("scale_lambda must lie in [0, 1] and scale_frames be >= 1")
        self.eps = float(eps)
        self.scale_update = bool(scale_update)
        self.scale_lambda = float(scale_lambda)
        self.scale_frames = int(scale_frames)
        self.exclude = int(exclude)
        # the two extensions are structural: off (0) they hold no parameter and the tracker is
        # the paper's, numbers and state dict alike
        self.regularised = reg > 0
        self.anchored = anchor > 0
        self.anchor_frames = int(anchor_frames)
        raw = {"log_alpha": math.log(alpha), "log_beta": math.log(beta),
               "logit_rho": math.log(rho / (1.0 - rho)), "log_sigma": math.log(sigma),
               "log_temperature": math.log(temperature)}
        if self.regularised:
            raw["log_reg"] = math.log(reg)
        if self.anchored:
            raw["logit_anchor"] = math.log(anchor / (1.0 - anchor))
        for name, v in raw.items():
            t = torch.tensor(v, dtype=torch.get_default_dtype())
            if learnable:
                self.register_parameter(name, nn.Parameter(t))
            else:
                self.register_buffer(name, t)
        self.state: STCState | None = None

    # ------------------------------------------------------------------ parameters
    @property
    def alpha(self) -> Tensor:
        return self.log_alpha.exp()

    @property
    def beta(self) -> Tensor:
        return self.log_beta.exp()

    @property
    def rho(self) -> Tensor:
        return torch.sigmoid(self.logit_rho)

    @property
    def sigma(self) -> Tensor:
        return self.log_sigma.exp()

    @property
    def temperature(self) -> Tensor:
        return self.log_temperature.exp()

    @property
    def reg(self) -> Tensor:
        """Eq. 8 regulariser (0 when the module runs eq. 8 as the paper)."""
        return self.log_reg.exp() if self.regularised else self.log_alpha.new_zeros(())

    @property
    def anchor(self) -> Tensor:
        """Weight of the start model in detection (0 when off)."""
        return torch.sigmoid(self.logit_anchor) if self.anchored else \
            self.log_alpha.new_zeros(())

    def extra_repr(self) -> str:
        return (f"window={self.window_size}, target={self.target_size}, peak={self.peak!r}, "
                f"crop={self.crop!r}, scale_update={self.scale_update}, "
                f"regularised={self.regularised}, anchored={self.anchored}")

    # ------------------------------------------------------------------ functional core
    def _check_frames(self, frames: Tensor, name: str, batch: int | None = None) -> Tensor:
        check_shape(frames, ("B", "Himg", "Wimg"), name)
        check_device(frames, name, self.log_alpha)
        if batch is not None:
            check_batch(frames, name, batch)
        return frames

    def _window(self, sigma: Tensor) -> Tensor:
        ref = self.log_alpha
        return weight_window(self.window_size, sigma, device=ref.device, dtype=ref.dtype)

    def _prior_f(self, frames: Tensor, centres: Tensor, window: Tensor) -> tuple[Tensor, Tensor]:
        win = extract_windows(frames, centres, self.window_size, mode=self.crop,
                              dtype=self.log_alpha.dtype)
        return torch.fft.rfft2(context_prior(win, window)), win

    def init_state(self, frames0: Tensor, uv0: Tensor) -> STCState:
        """Learn the first model (H_stc = h_sc, eq. 9) on ``frames0`` at ``uv0``.

        Args:
            frames0: (B, Himg, Wimg) first grey frames (or crops containing the target).
            uv0: (B, 2) initial (u, v) of the target (e.g. from TIPM).

        Returns:
            The :class:`STCState` after frame 1.
        """
        self._check_frames(frames0, "frames0")
        B = frames0.shape[0]
        check_shape(uv0, (B, 2), "uv0")
        check_device(uv0, "uv0", self.log_alpha)
        ref = self.log_alpha
        uv0 = as_float(uv0, ref)
        sigma = self.sigma.expand(B)
        window = self._window(sigma if self.scale_update else self.sigma)
        conf_f = torch.fft.rfft2(confidence_map(self.window_size, self.alpha, self.beta))
        state = STCState(H_f=conf_f.new_zeros((B,) + conf_f.shape), pos=uv0, sigma=sigma,
                         scale=torch.ones(B, device=ref.device, dtype=ref.dtype),
                         maxconf=uv0.new_zeros((B, 0)), frame=0, window=window, conf_f=conf_f)
        return self.learn(state, frames0, uv0)

    def detect(self, state: STCState, frames: Tensor, centre: Tensor | None = None
               ) -> STCDetection:
        """Confidence map (eq. 10) of ``frames`` around ``centre`` and its peak (eq. 11).

        Args:
            state: current state.
            frames: (B, Himg, Wimg) new grey frames.
            centre: (B, 2) where to crop; default ``state.pos`` (plain STC).

        Returns:
            :class:`STCDetection` with ``uv`` (B, 2), ``response`` (B, H, W) and quality.
        """
        B = state.pos.shape[0]
        self._check_frames(frames, "frames", B)
        centre = state.pos if centre is None else centre
        check_shape(centre, (B, 2), "centre")
        prior_f, _ = self._prior_f(frames, centre, state.window)
        H_f = state.H_f
        if self.anchored and state.H_ref is not None:
            H_f = H_f + self.anchor * (state.H_ref - H_f)
        resp = stc_response(H_f, prior_f, self.window_size)
        off, quality = _analyse(resp, self.peak, self.log_temperature.exp(), self.exclude, True)
        base = torch.floor(centre.detach() + 0.5) if self.crop == "nearest" else centre
        base = as_float(base, resp)
        return STCDetection(uv=base + off, centre=base, response=resp, quality=quality)

    def learn(self, state: STCState, frames: Tensor, centre: Tensor,
              rho_scale: Tensor | None = None) -> STCState:
        """Learn h_sc at ``centre`` (eq. 8) and update H_stc (eq. 9); the reference's scale
        update when enabled.

        Args:
            state: current state.
            frames: (B, Himg, Wimg) grey frames (the same frame that was just detected in).
            centre: (B, 2) target location to learn at (the window is re-cropped there).
            rho_scale: optional (B,) factor in [0, 1] on rho (the fusion slows learning on
                distrusted frames); the first frame ignores it (H_stc = h_sc).

        Returns:
            The new state (``pos`` = ``centre``).
        """
        B = state.pos.shape[0]
        self._check_frames(frames, "frames", B)
        check_shape(centre, (B, 2), "centre")
        prior_f, _ = self._prior_f(frames, centre, state.window)
        f = state.frame + 1  # the reference's 1-based frame index
        scale, maxconf = state.scale, state.maxconf
        if self.scale_update and f > 1:
            mc = stc_response(state.H_f, prior_f, self.window_size).amax(dim=(1, 2))
            maxconf = torch.cat([maxconf, mc[:, None]], dim=1)[:, -(self.scale_frames + 1):]
            if f % (self.scale_frames + 2) == 0:
                m = maxconf.clamp_min(torch.finfo(mc.dtype).tiny)
                s = torch.sqrt(m[:, 1:] / m[:, :-1]).mean(dim=1)
                scale = (1.0 - self.scale_lambda) * scale + self.scale_lambda * s
        conf_f = state.conf_f
        if self.crop == "nearest":  # target at centre - round(centre) in the window
            conf_f = conf_f * fourier_shift(centre - torch.floor(centre.detach() + 0.5),
                                            self.window_size)
        if self.regularised:
            h_f = learn_spatial_context_reg(conf_f, prior_f, self.reg, self.eps)
        else:
            h_f = learn_spatial_context(conf_f, prior_f, self.eps)
        if f == 1:
            H_f = h_f
        else:
            rho = self.rho if rho_scale is None else self.rho * rho_scale
            H_f = update_context_model(state.H_f, h_f, rho)
        H_ref = state.H_ref
        if self.anchored and f <= self.anchor_frames:  # running mean of the start models
            if f == 1:
                H_ref = H_f
            else:
                assert H_ref is not None  # kept since frame 1
                H_ref = H_ref + (H_f - H_ref) / f
        sigma, window = state.sigma, state.window
        if self.scale_update:  # sigma <- sigma * s at the start of the next frame
            sigma = sigma * scale
            window = self._window(sigma)
        return STCState(H_f=H_f, pos=centre, sigma=sigma, scale=scale, maxconf=maxconf,
                        frame=f, window=window, conf_f=state.conf_f, H_ref=H_ref)

    def track(self, state: STCState, frames: Tensor
              ) -> tuple[STCState, Tensor, dict[str, Tensor]]:
        """One plain-STC step: detect around ``state.pos``, learn at the new location.

        Args:
            state: current state.
            frames: (B, Himg, Wimg) new grey frames.

        Returns:
            (new state, uv (B, 2), quality dict of (B,) tensors).
        """
        det = self.detect(state, frames)
        return self.learn(state, frames, det.uv), det.uv, det.quality

    def detach_state(self, state: STCState) -> STCState:
        """Cut ``state`` from the graph and rebuild its cached window / confidence spectrum
        from the current parameters (call between truncated-BPTT chunks and after an
        optimiser step)."""
        s = state.detach()
        s.sigma = s.sigma * (self.sigma / self.sigma.detach())  # keep the scale history
        s.window = self._window(s.sigma if self.scale_update else self.sigma)
        s.conf_f = torch.fft.rfft2(confidence_map(self.window_size, self.alpha, self.beta))
        return s

    # ------------------------------------------------------------------ stateful API
    def init(self, frames0: Tensor, uv0: Tensor) -> None:
        """Start tracking B sequences (see :meth:`init_state`); keeps the state."""
        self.state = self.init_state(frames0, uv0)

    def step(self, frames: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """Track one frame (plain STC); returns (uv (B, 2), quality dict of (B,))."""
        if self.state is None:
            raise InputError("STC.step: call init(frames0, uv0) first")
        self.state, uv, q = self.track(self.state, frames)
        return uv, q

    def forward(self, frames: Tensor, uv0: Tensor, detach_every: int | None = None
                ) -> tuple[Tensor, dict[str, Tensor]]:
        """Plain STC over whole sequences.

        Args:
            frames: (B, T, Himg, Wimg) grey frames.
            uv0: (B, 2) target location in frame 0.
            detach_every: cut the graph every this many frames (truncated BPTT).

        Returns:
            uv (B, T, 2) with ``uv[:, 0] = uv0``; quality dict of (B, T) tensors (frame 0: the
            quality of the model's response to its own training frame).
        """
        check_shape(frames, ("B", "T", "Himg", "Wimg"), "frames")
        B, T = frames.shape[:2]
        state = self.init_state(frames[:, 0], uv0)
        prior0, _ = self._prior_f(frames[:, 0], state.pos, state.window)
        q0 = peak_quality(stc_response(state.H_f, prior0, self.window_size), self.exclude)
        uvs, qs = [state.pos], [q0]
        for t in range(1, T):
            if detach_every and t % detach_every == 0:
                state = self.detach_state(state)
            state, uv, q = self.track(state, frames[:, t])
            uvs.append(uv)
            qs.append(q)
        return torch.stack(uvs, dim=1), {k: torch.stack([q[k] for q in qs], dim=1) for k in q0}

