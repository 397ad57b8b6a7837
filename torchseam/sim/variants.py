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


def kink_deg(uv: np.ndarray, arm_uv: np.ndarray) -> float:
    """How far from collinear the stripe's two arms are at the feature point ``uv`` (2,), in
    degrees (0: a straight stripe), from a point on each arm ``arm_uv`` (2, 2) (the
    simulator's :attr:`~torchseam.sim.sequence.FrameTruth.arm_uv`): 180 minus the angle
    between the chords from the corner to the two points.

    Example:
        >>> round(kink_deg(np.array([0.0, 0.0]), np.array([[-10.0, 1.0], [10.0, 1.0]])), 2)
        11.42
    """
    a, b = np.asarray(arm_uv, float) - np.asarray(uv, float)
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return 180.0 - float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _arm_slopes(uv: np.ndarray, arm_uv: np.ndarray) -> tuple[float, float]:
    """dv/du of the chords from the corner to the arm point left of it and right of it."""
    pts = sorted((np.asarray(p, float) for p in arm_uv), key=lambda p: float(p[0]))
    (lu, lv), (ru, rv) = pts[0] - uv, pts[1] - uv
    return float(lv / lu), float(rv / ru)


def kink_shift(uv: np.ndarray, arm_uv: np.ndarray, kink: float, width: int) -> np.ndarray:
    """(width,) vertical shift per column that turns the arms about the corner ``uv`` until
    they are ``kink`` degrees from collinear (:func:`kink_deg` of the result), the bisector's
    direction and the side the stripe bends to kept: column ``u`` moves by
    ``(s' - s) (u - u_c)``, ``s`` and ``s'`` the old and new chord slope of the arm on that
    side. Zero at the corner: the feature point stays where it is."""
    s_left, s_right = _arm_slopes(uv, arm_uv)
    t_left, t_right = np.arctan(s_left), np.arctan(s_right)
    mid, bend = 0.5 * (t_left + t_right), np.sign(t_right - t_left) or 1.0
    half = 0.5 * np.radians(kink) * bend
    x = np.arange(width, dtype=np.float64) - float(uv[0])
    new = np.where(x < 0, np.tan(mid - half), np.tan(mid + half))
    old = np.where(x < 0, s_left, s_right)
    return np.asarray((new - old) * x)


def flatten_kink(frame: np.ndarray, uv: np.ndarray, arm_uv: np.ndarray, kink: float
                 ) -> np.ndarray:
    """The frame (H, W[, C]) with its columns moved vertically (:func:`kink_shift`) so that
    the stripe's arms are ``kink`` degrees from collinear at the feature point ``uv`` (2,)
    (``arm_uv`` (2, 2): a point on each arm, the simulator's), the corner itself unmoved: the
    view of a saddle where the dihedral angle between the pipes makes the stripe nearly
    straight. Everything in a column (arc light, spatter, noise) moves with it (bilinear,
    the frame's edge replicated).

    Example:
        >>> f = np.zeros((60, 80, 3), np.uint8)
        >>> uv, arms = np.array([40.0, 30.0]), np.array([[20.0, 20.0], [60.0, 20.0]])
        >>> g = flatten_kink(f, uv, arms, 5.0)
        >>> g.shape == f.shape
        True
    """
    h, w = frame.shape[:2]
    dv = kink_shift(uv, arm_uv, kink, w).astype(np.float32)
    map_x = np.broadcast_to(np.arange(w, dtype=np.float32), (h, w))
    map_y = np.arange(h, dtype=np.float32)[:, None] - dv[None, :]
    return cv2.remap(frame, np.ascontiguousarray(map_x), map_y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


#: spatter on the corner: (B, G, R) of its streaks (hot droplets, white-yellow)
CORNER_SPATTER = np.array([150.0, 215.0, 255.0], np.float32)


def glare_on_corner(frame: np.ndarray, uv: np.ndarray, rng: np.random.Generator,
                    radius_px: float = 25.0, gain: float = 1.0, streaks: int = 6
                    ) -> np.ndarray:
    """The frame (H, W, 3) uint8 with strong arc glare and spatter on the feature point
    ``uv``: a red-heavy halo (sigma 1.5 ``radius_px``, ``gain`` x 255 at the corner: the red
    clips there and the stripe's red excess sinks below the background's) and ``streaks``
    spatter streaks (8-40 px, any direction) starting within 2 ``radius_px`` of the corner.
    Unlike :func:`glare_over_corner` there is no white core: the arms show up to the glare
    and the corner lies under it, readable only from the arms.

    Example:
        >>> f = glare_on_corner(np.zeros((100, 100, 3), np.uint8), np.array([50.0, 50.0]),
        ...                     np.random.default_rng(0))
        >>> int(f[50, 50, 2]) > 200
        True
    """
    h, w = frame.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    d2 = (xx - np.float32(uv[0])) ** 2 + (yy - np.float32(uv[1])) ** 2
    halo = gain * 255.0 * np.exp(-d2 / np.float32(2 * (1.5 * radius_px) ** 2))
    out = frame.astype(np.float32) + halo[..., None] * CORNER_GLARE_HALO
    for _ in range(streaks):
        r, phi = 2.0 * radius_px * np.sqrt(rng.random()), rng.uniform(0, 2 * np.pi)
        p0 = np.asarray(uv, float) + r * np.array([np.cos(phi), np.sin(phi)])
        d = rng.uniform(0, 2 * np.pi)
        p1 = p0 + rng.uniform(8.0, 40.0) * np.array([np.cos(d), np.sin(d)])
        colour = tuple(float(c) for c in CORNER_SPATTER * rng.uniform(0.6, 1.0))
        cv2.line(out, (int(p0[0]), int(p0[1])), (int(p1[0]), int(p1[1])), colour,
                 int(rng.integers(1, 3)), cv2.LINE_AA)
    return np.clip(out, 0, 255).astype(np.uint8)


#: the shallow-kink stretch of level ``shallow``: (start as a fraction of the sequence,
#: frames to turn the arms flat, frames flat, frames to turn them back)
SHALLOW = (0.3, 15, 110, 15)
#: how far from collinear the arms are in the flat part, degrees: it swings between the two
#: (the saddle's dihedral angle changing along the seam) with this period in frames
SHALLOW_KINK = (3.0, 10.0, 90)


def shallow_schedule(n: int, stretch: tuple[float, int, int, int] = SHALLOW,
                     kink: tuple[float, float, int] = SHALLOW_KINK
                     ) -> tuple[np.ndarray, np.ndarray]:
    """For a sequence of ``n`` frames: (n,) the kink to show (degrees, NaN: the frame's own)
    and the weight (n,) in [0, 1] of that kink against the frame's own (0 outside the
    stretch, 1 in its flat part, a cosine ramp between).

    Example:
        >>> k, w = shallow_schedule(100, (0.2, 2, 5, 2), (3.0, 10.0, 10))
        >>> int(np.sum(w == 1.0)), float(k[22]), bool(np.isnan(k[0]))
        (5, 3.0, True)
    """
    start, ramp_in, flat, ramp_out = stretch
    lo, hi, period = kink
    k0 = int(start * n)
    kinks, weight = np.full(n, np.nan), np.zeros(n)
    for i in range(k0, min(n, k0 + ramp_in + flat + ramp_out)):
        t = i - k0
        if t < ramp_in:
            weight[i] = 0.5 - 0.5 * np.cos(np.pi * (t + 1) / (ramp_in + 1))
        elif t < ramp_in + flat:
            weight[i] = 1.0
        else:
            weight[i] = 0.5 + 0.5 * np.cos(np.pi * (t - ramp_in - flat + 1) / (ramp_out + 1))
        tf = max(t - ramp_in, 0)
        kinks[i] = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2 * np.pi * tf / period))
    return kinks, weight


def shallow_corner(frames: list[np.ndarray], labels: np.ndarray, arm_uv: np.ndarray,
                   seed: int = 0, stretch: tuple[float, int, int, int] = SHALLOW,
                   kink: tuple[float, float, int] = SHALLOW_KINK
                   ) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """The benchmarks' level ``shallow``: frames (H, W, 3) uint8 whose stripe flattens to a
    shallow kink (:func:`flatten_kink`, :func:`shallow_schedule`) for a stretch, with strong
    glare and spatter on the corner all through it (:func:`glare_on_corner`, its gain
    flickering 0.8-1.2 frame to frame). ``labels`` (N, 2) and ``arm_uv`` (N, 2, 2): the
    simulator's feature points and arm points. The labels are unchanged (the corner does not
    move).

    Returns:
        frames; (N,) bool the frames of the stretch; (N,) bool its flat part (the kink within
        ``kink``'s range and glare on the corner: no corner TIPM's usual rule would give).
    """
    n = len(frames)
    kinks, weight = shallow_schedule(n, stretch, kink)
    rng = np.random.default_rng(seed)
    out = []
    for i, f in enumerate(frames):
        if weight[i] <= 0 or not np.all(np.isfinite(labels[i])):
            out.append(f)
            continue
        own = kink_deg(labels[i], arm_uv[i])
        g = flatten_kink(f, labels[i], arm_uv[i], weight[i] * kinks[i] + (1 - weight[i]) * own)
        out.append(glare_on_corner(g, labels[i], rng, gain=float(rng.uniform(0.8, 1.2))))
    return out, weight > 0, weight >= 1.0
