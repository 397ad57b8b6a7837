"""Frame transforms for benchmarks: other cameras and other mountings of the same scene.

:func:`to_mono` turns a simulated colour frame into what a monochrome camera behind the same
650 nm band-pass delivers, at 8 or 16 bits. :func:`rotate90` turns frame and labels by 90
degrees, as a sensor mounted with the laser line running vertically sees the joint;
:func:`rotate90_uv` and :func:`unrotate90_uv` map points to and from the rotated image.

Pixel coordinates are (u, v) = (column, row), pixel centres at integers.
"""

from __future__ import annotations

import cv2
import numpy as np

from torchseam.core.checks import check_shape

#: Mono sensor response behind the 650 nm band-pass, as weights of the colour frame's
#: (B, G, R): essentially the red channel's light, plus the little that the Bayer filter's
#: green and blue passed of the same band.
MONO_BGR_WEIGHTS = (0.05, 0.10, 0.85)
#: 8-bit to 16-bit scale: 255 -> 65535.
SCALE_16 = 257


def to_mono(frame_bgr: np.ndarray, bits: int = 8, noise_lsb: float = 0.3,
            rng: np.random.Generator | int | None = 0) -> np.ndarray:
    """Single-channel intensity of an (H, W, 3) BGR frame: (H, W) uint8 or uint16.

    The intensity is ``MONO_BGR_WEIGHTS`` . (B, G, R). At 16 bits it is scaled to the full range
    (x 257) and gets Gaussian noise of ``noise_lsb`` 8-bit steps, the low bits a deeper
    converter fills in (``rng``: a generator or a seed, for reproducible frames).

    Example:
        >>> f = np.zeros((4, 5, 3), np.uint8); f[..., 2] = 200
        >>> to_mono(f).dtype, int(to_mono(f)[0, 0]), to_mono(f, bits=16).shape
        (dtype('uint8'), 170, (4, 5))
    """
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    check_shape(frame_bgr, "H W 3", "frame_bgr", kind="array")
    w = np.asarray(MONO_BGR_WEIGHTS, np.float32)[None, :]
    y = cv2.transform(frame_bgr.astype(np.float32), w)
    if y.ndim == 3:
        y = y[..., 0]
    if bits == 8:
        return np.clip(np.rint(y), 0, 255).astype(np.uint8)
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    y = y * np.float32(SCALE_16)
    if noise_lsb > 0:
        y += gen.standard_normal(y.shape, dtype=np.float32) * np.float32(noise_lsb * SCALE_16)
    return np.clip(np.rint(y), 0, 65535).astype(np.uint16)


def rotate90_uv(uv: np.ndarray, width: int) -> np.ndarray:
    """Points (..., 2) of an image ``width`` pixels wide -> the same points in that image
    turned 90 degrees counter-clockwise (``np.rot90``): ``(u', v') = (v, width - 1 - u)``."""
    uv = np.asarray(uv, dtype=float)
    return np.stack([uv[..., 1], (width - 1) - uv[..., 0]], axis=-1)


def unrotate90_uv(uv_rot: np.ndarray, width: int) -> np.ndarray:
    """Inverse of :func:`rotate90_uv` (``width`` of the original, unrotated image):
    ``(u, v) = (width - 1 - v', u')``."""
    uv_rot = np.asarray(uv_rot, dtype=float)
    return np.stack([(width - 1) - uv_rot[..., 1], uv_rot[..., 0]], axis=-1)


def rotate90(frame: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame (H, W[, C]) and its label points (..., 2) turned 90 degrees counter-clockwise.

    Returns the (W, H[, C]) frame (contiguous) and the points in it: pixel (u, v) goes to
    (v, W - 1 - u); NaN labels stay NaN.

    Example:
        >>> f = np.zeros((3, 4), np.uint8); f[0, 3] = 9      # row 0, column 3: (u, v) = (3, 0)
        >>> r, p = rotate90(f, np.array([3.0, 0.0]))
        >>> r.shape, p.tolist(), int(r[int(p[1]), int(p[0])])
        ((4, 3), [0.0, 0.0], 9)
    """
    return np.ascontiguousarray(np.rot90(frame)), rotate90_uv(uv, frame.shape[1])


#: glare over the corner: (B, G, R) of its core (white, saturating) and of its halo (arc light)
CORNER_GLARE_CORE = np.array([255.0, 255.0, 255.0], np.float32)
CORNER_GLARE_HALO = np.array([0.45, 0.55, 1.0], np.float32)


def glare_over_corner(frame: np.ndarray, uv: np.ndarray, radius_px: float = 35.0,
                      gain: float = 1.0) -> np.ndarray:
    """The frame (H, W, 3) uint8 with the arc's glare over the feature point ``uv``: a
    saturated white core of ``radius_px`` that hides the corner and a red halo three times as
    wide, what a weld pool flaring up the groove does for tens of frames (beyond the noise
    model's ``heavy``). ``gain`` scales the halo. The stripe is not drawn over it: nothing of
    the corner is left to see.

    Example:
        >>> f = glare_over_corner(np.zeros((100, 100, 3), np.uint8), np.array([50.0, 50.0]))
        >>> int(f[50, 50, 1]), int(f[50, 95, 2]) > 0
        (255, True)
    """
    h, w = frame.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    d2 = (xx - np.float32(uv[0])) ** 2 + (yy - np.float32(uv[1])) ** 2
    halo = gain * 255.0 * np.exp(-d2 / np.float32(2 * (1.5 * radius_px) ** 2))
    out = frame.astype(np.float32) + halo[..., None] * CORNER_GLARE_HALO
    core = d2 <= radius_px ** 2
    out[core] = CORNER_GLARE_CORE
    return np.clip(out, 0, 255).astype(np.uint8)


#: (start as a fraction of the sequence, frames) of each stretch of :func:`hide_corner`
HIDE = ((0.3, 30), (0.65, 60))


def hide_corner(frames: list[np.ndarray], labels: np.ndarray,
                stretches: tuple[tuple[float, int], ...] = HIDE
                ) -> tuple[list[np.ndarray], np.ndarray]:
    """Frames with the corner hidden under :func:`glare_over_corner` for ``stretches``
    ((start as a fraction of the sequence, frames) each), and the (N,) mask of hidden frames:
    the benchmarks' level ``beyond``.

    Example:
        >>> f = [np.zeros((60, 80, 3), np.uint8)] * 10
        >>> out, hidden = hide_corner(f, np.full((10, 2), 30.0), ((0.2, 3),))
        >>> hidden.nonzero()[0].tolist()
        [2, 3, 4]
    """
    n = len(frames)
    hidden = np.zeros(n, bool)
    for start, length in stretches:
        hidden[int(start * n):int(start * n) + length] = True
    out = [glare_over_corner(f, uv) if h else f
           for f, uv, h in zip(frames, labels, hidden, strict=True)]
    return out, hidden
