"""Arc-noise model: what the welding arc adds to a laser-stripe frame.

Terms (amplitudes from ``configs/noise.yaml``, each scaled by the level in [0, 1]):
arc glare around the torch tip (below the stripe), flickering frame to frame; the arc mirrored
by the groove (a bright band up the seam towards the feature point); spatter streaks
flying out of the arc, with Markov bursts; slow-drifting specular reflections on the pipes;
occasional whole-frame flashes; stripe dropouts (gaps along the stripe, sometimes at the
feature point); sensor read noise. The state (flicker, burst, reflections) carries over frames,
so a sequence has the temporal structure a tracker meets in a real cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from torchseam.core.config import NoiseConfig

# Colour of arc light behind the 650 nm band-pass, as seen through the Bayer filter (B, G, R):
# the core saturates white, the fringe stays red.
ARC_BGR = np.array([0.45, 0.55, 1.0], np.float32)
SPATTER_BGR = np.array([0.35, 0.6, 1.0], np.float32)
STRIPE_BGR = np.array([0.18, 0.24, 1.0], np.float32)
SPATTER_BLUR_MARGIN_PX = 8  # > the reach of the spatter blur's kernel (3 px at sigma 0.8)


def _union(a: tuple[int, int, int, int] | None, b: tuple[int, int, int, int]
           ) -> tuple[int, int, int, int]:
    """Smallest box (x0, y0, x1, y1) holding boxes ``a`` (None: empty) and ``b``."""
    if a is None:
        return b
    return (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))


@dataclass
class NoiseFlags:
    """What the noise did in one frame (stored as ground truth)."""

    flash: bool = False
    burst: bool = False
    dropout: bool = False
    spatter: int = 0


@dataclass
class NoiseLayers:
    """One frame of arc light: grey (H, W) float32 layers and stripe gaps.

    ``gaps`` are (start, end) arc lengths in px along the stripe from the feature point.
    """

    glare: np.ndarray      # arc glare, reflections and flashes (colour ARC_BGR)
    spatter: np.ndarray    # spatter streaks (colour SPATTER_BGR)
    gaps: list[tuple[float, float]]
    flags: NoiseFlags


class ArcNoise:
    """Stateful arc-noise generator for one sequence.

    Example:
        >>> from torchseam.core.config import load_noise
        >>> noise = ArcNoise(load_noise(), level=1.0, size=(656, 492), seed=0)
        >>> layers = noise.next(np.array([330.0, 420.0]), np.array([330.0, 240.0]))
        >>> layers.glare.shape
        (492, 656)
    """

    def __init__(self, cfg: NoiseConfig, level: float, size: tuple[int, int], seed: int) -> None:
        if not 0.0 <= level <= 1.0:
            raise ValueError(f"noise level {level} must lie in [0, 1]")
        self.cfg = cfg
        self.level = float(level)
        self.w, self.h = size
        self.rng = np.random.default_rng(seed)
        self.flicker = 1.0
        self.burst_left = 0
        yy, xx = np.mgrid[0:self.h, 0:self.w].astype(np.float32)
        self._xx, self._yy = xx, yy
        self._ramp = 1.0 - 0.5 * yy / self.h
        # glare: saturated core plus a long halo, as a template pasted at the arc each frame
        rad = cfg.glare.radius_px * (0.6 + 0.4 * level)
        r = int(4 * rad)
        d = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]).astype(np.float32)
        self._glare_t = 1.6 * np.exp(-(d**2) / (2 * (0.25 * rad) ** 2)) + 0.8 * np.exp(-d / rad)
        self.reflections = [self._new_reflection() for _ in range(cfg.reflections.count)]

    def _new_reflection(self) -> np.ndarray:
        r = self.cfg.reflections
        return np.array([self.rng.uniform(0, self.w), self.rng.uniform(0.2 * self.h, self.h),
                         self.rng.uniform(*r.radius_px), self.rng.uniform(*r.radius_px) * 0.4,
                         self.rng.uniform(0, np.pi), self.rng.uniform(*r.brightness)])

    def next(self, arc_uv: np.ndarray, stripe_uv: np.ndarray) -> NoiseLayers:
        """Advance one frame.

        Args:
            arc_uv: (2,) pixel of the arc (torch tip), may lie outside the image.
            stripe_uv: (2,) pixel of the stripe's feature point (reflections gather near it).
        """
        L, cfg, rng = self.level, self.cfg, self.rng
        out = NoiseLayers(np.zeros((self.h, self.w), np.float32),
                          np.zeros((self.h, self.w), np.float32), [], NoiseFlags())
        if L <= 0.0:
            return out
        flags, glare, spatter = out.flags, out.glare, out.spatter

        # Arc brightness: AR(1) flicker around 1.
        self.flicker = max(0.2, 0.7 * self.flicker + 0.3 + cfg.glare.flicker * rng.standard_normal()
                           * np.sqrt(1 - 0.7**2))
        self._paste_glare(glare, arc_uv, cfg.glare.peak * L * self.flicker, fresh=True)

        # The groove mirrors the arc: a bright band from the arc up the seam towards the stripe.
        gr = cfg.groove
        reach = rng.uniform(*gr.reach)
        self._band(glare, arc_uv, arc_uv + reach * (stripe_uv - arc_uv), gr.width_px,
                   rng.uniform(*gr.brightness) * L * self.flicker)

        # Reflections: slow random walk, brightness follows the arc.
        for i, ref in enumerate(self.reflections):
            ref[:2] += rng.normal(0, 2.0, 2)
            ref[4] += rng.normal(0, 0.02)
            if not (0 <= ref[0] < self.w and 0 <= ref[1] < self.h) or rng.random() < 0.01:
                self.reflections[i] = ref = self._new_reflection()
                ref[:2] = stripe_uv + rng.normal(0, [90.0, 60.0])
            self._blob(glare, ref, ref[5] * L * self.flicker)

        # Spatter streaks, with Markov bursts.
        if self.burst_left > 0:
            self.burst_left -= 1
        elif rng.random() < cfg.spatter.burst_prob * L:
            self.burst_left = int(rng.geometric(1.0 / cfg.spatter.burst_frames))
        flags.burst = self.burst_left > 0
        rate = (cfg.spatter.burst_rate if flags.burst else cfg.spatter.rate) * L
        flags.spatter = int(rng.poisson(rate))
        box = None
        for _ in range(flags.spatter):
            box = _union(box, self._streak(spatter, arc_uv))
        if box is not None:
            # blur only around the streaks (the rest is zero before and after; the margin
            # exceeds the kernel's reach, so the pixels are the full-frame blur's)
            x0, y0, x1, y1 = box
            m = SPATTER_BLUR_MARGIN_PX
            ys = slice(max(0, y0 - m), min(self.h, y1 + m))
            xs = slice(max(0, x0 - m), min(self.w, x1 + m))
            if ys.start < ys.stop and xs.start < xs.stop:
                spatter[ys, xs] = cv2.GaussianBlur(spatter[ys, xs], (0, 0), 0.8)

        if rng.random() < cfg.flash.prob * L:
            flags.flash = True
            gain = rng.uniform(*cfg.flash.brightness)
            # half of the flashes light the lower part (nearer the arc) more
            glare += gain * (self._ramp if rng.random() < 0.5 else 1.0)

        if rng.random() < cfg.dropout.prob * L:
            flags.dropout = True
            for _ in range(int(rng.integers(cfg.dropout.gaps[0], cfg.dropout.gaps[1] + 1))):
                length = rng.uniform(*cfg.dropout.length_px)
                # a third of the gaps hide the feature point itself
                centre = rng.normal(0, 4.0) if rng.random() < 0.33 else rng.uniform(-250, 250)
                out.gaps.append((centre - length / 2, centre + length / 2))
        return out

    # ------------------------------------------------------------ primitives
    def _roi(self, cx: float, cy: float, r: float) -> tuple[slice, slice] | None:
        x0, x1 = int(max(0, cx - r)), int(min(self.w, cx + r + 1))
        y0, y1 = int(max(0, cy - r)), int(min(self.h, cy + r + 1))
        if x0 >= x1 or y0 >= y1:
            return None
        return slice(y0, y1), slice(x0, x1)

    def _paste_glare(self, img: np.ndarray, c: np.ndarray, peak: float,
                     fresh: bool = False) -> None:
        """Add the precomputed glare template, centred (to the pixel) on the arc.

        ``fresh``: ``img`` is all zeros, so the product is written straight into it (the same
        numbers as adding it, without a full-frame temporary).
        """
        t = self._glare_t
        r = t.shape[0] // 2
        cx, cy = int(round(c[0])), int(round(c[1]))
        x0, x1 = max(0, cx - r), min(self.w, cx + r + 1)
        y0, y1 = max(0, cy - r), min(self.h, cy + r + 1)
        if x0 < x1 and y0 < y1:
            src = t[y0 - cy + r:y1 - cy + r, x0 - cx + r:x1 - cx + r]
            if fresh:
                # peak (a float64 scalar) times the float32 template is computed in float64 and
                # rounded to float32 on the way out: exactly what 0 + peak * t stores
                np.multiply(src, peak, out=img[y0:y1, x0:x1], casting="same_kind")
            else:
                img[y0:y1, x0:x1] += peak * src

    def _axes(self, roi: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
        """Pixel x (1, w) and y (h, 1) coordinates of a ROI, float32 (broadcast, not tiled)."""
        return (self._xx[0, roi[1]][None, :], self._yy[roi[0], 0][:, None])

    def _blob(self, img: np.ndarray, ref: np.ndarray, amp: float) -> None:
        # The same arithmetic, element for element, as on full (h, w) coordinate grids, but
        # the coordinates broadcast from a row and a column and the work arrays are reused in
        # place: a third of the time, bit-identical pixels.
        cx, cy, ra, rb, ang = ref[:5]
        roi = self._roi(cx, cy, 3 * ra)
        if roi is None:
            return
        xs, ys = self._axes(roi)
        dx, dy = xs - cx, ys - cy
        ca, sa = np.cos(ang), np.sin(ang)
        p = np.add(ca * dx, sa * dy)
        np.divide(p, ra, out=p)
        q = np.add(-sa * dx, ca * dy)
        np.divide(q, rb, out=q)
        np.multiply(p, p, out=p)
        np.multiply(q, q, out=q)
        np.add(p, q, out=p)
        np.multiply(p, -0.5, out=p)
        np.exp(p, out=p)
        np.multiply(p, amp, out=p)
        img[roi] += p

    def _band(self, img: np.ndarray, p0: np.ndarray, p1: np.ndarray, width: float,
              amp: float) -> None:
        """Gaussian band along the segment p0-p1, fading towards p1 (bit-identical to the
        full-grid arithmetic; see :meth:`_blob`)."""
        d = p1 - p0
        length = float(np.hypot(*d))
        if length < 1.0 or amp <= 0:
            return
        roi = self._roi(*(0.5 * (p0 + p1)), 0.5 * length + 3 * width)
        if roi is None:
            return
        xs, ys = self._axes(roi)
        dx, dy = xs - p0[0], ys - p0[1]
        t = np.add(dx * d[0], dy * d[1])
        np.divide(t, length**2, out=t)
        np.clip(t, 0.0, 1.0, out=t)
        ex = np.multiply(t, d[0])
        np.subtract(dx, ex, out=ex)
        ey = np.multiply(t, d[1])
        np.subtract(dy, ey, out=ey)
        np.multiply(ex, ex, out=ex)
        np.multiply(ey, ey, out=ey)
        np.add(ex, ey, out=ex)
        np.negative(ex, out=ex)
        np.divide(ex, 2 * width**2, out=ex)
        np.exp(ex, out=ex)
        np.multiply(t, 0.6, out=t)
        np.subtract(1.0, t, out=t)
        np.multiply(t, amp, out=t)
        np.multiply(t, ex, out=t)
        img[roi] += t

    def _streak(self, img: np.ndarray, arc: np.ndarray) -> tuple[int, int, int, int]:
        """Draw one spatter streak; returns the box (x0, y0, x1, y1) it may touch."""
        rng, sp = self.rng, self.cfg.spatter
        # droplets fly out of the arc, mostly upwards (towards the stripe) and sideways
        ang = rng.uniform(np.pi, 2 * np.pi) if rng.random() < 0.8 else rng.uniform(0, np.pi)
        dist = rng.exponential(120.0)
        start = arc + dist * np.array([np.cos(ang), np.sin(ang)])
        length = rng.uniform(*sp.length_px)
        dirn = ang + rng.normal(0, 0.3)
        end = start + length * np.array([np.cos(dirn), np.sin(dirn)])
        p0, p1 = tuple(int(v) for v in start * 16), tuple(int(v) for v in end * 16)
        value = float(rng.uniform(*sp.brightness))   # drawn in this order: same random stream
        thick = int(rng.integers(1, 3))
        cv2.line(img, p0, p1, value, thick, cv2.LINE_8, 4)
        # the pixels the line can touch (end points in 1/16 px, plus its thickness)
        r = thick + 1
        return (min(p0[0], p1[0]) // 16 - r, min(p0[1], p1[1]) // 16 - r,
                max(p0[0], p1[0]) // 16 + r + 1, max(p0[1], p1[1]) // 16 + r + 1)

    def sensor_sigma(self) -> float:
        """Grey-level read noise std at this level."""
        s = self.cfg.sensor
        return s.sigma_clean + s.sigma_arc * self.level
