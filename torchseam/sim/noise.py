"""Arc-noise model: what the welding arc adds to a laser-stripe frame.

Terms (amplitudes from ``configs/noise.yaml``, each scaled by the level in [0, MAX_NOISE_LEVEL];
1 is the amplitudes as written, above 1 heavier arc than that):
arc glare around the torch tip (below the stripe), flickering frame to frame; the arc mirrored
by the groove (a bright band up the seam towards the feature point); spatter streaks
flying out of the arc, with Markov bursts; slow-drifting specular reflections on the pipes;
occasional whole-frame flashes; stripe dropouts (gaps along the stripe, sometimes at the
feature point); sensor read noise. The state (flicker, burst, reflections) carries over frames,
so a sequence has the temporal structure a tracker meets in a real cell.

The appearance family (:class:`~torchseam.core.config.AppearanceFamily`) sets the shapes: the
glare's aspect, tilt, offset and core/halo mix; spatter as streaks (with or without bright
heads) or round dots; the fume veil; saturated row bands of flashes caught by a rolling
shutter. Family ``sim`` leaves every extra off, and its random stream is the historical one.
The arc's specular glint on the main pipe (``GlareLook.glint``) needs the scene's geometry: the
renderer adds it to the glare layer (:meth:`~torchseam.sim.sensor.LaserSensor.arc_glint`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from torchseam.core.config import MAX_NOISE_LEVEL, AppearanceFamily, NoiseConfig
from torchseam.core.kernels import load_kernels

# Colours of the ``sim`` family (``configs/noise.yaml`` holds every family's): arc light behind
# the 650 nm band-pass, as seen through the Bayer filter (B, G, R): the core saturates white,
# the fringe stays red. Kept here for renderers without families (the calibration board).
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
    ``haze`` (fume density in [0, 1]) and ``rows`` (per-row exposure gain, (H,) float32) are
    None unless the appearance family has fume or rolling-shutter bands.
    """

    glare: np.ndarray      # arc glare, reflections and flashes (the family's glare colour)
    spatter: np.ndarray    # spatter streaks or dots (the family's spatter colour)
    gaps: list[tuple[float, float]]
    flags: NoiseFlags
    haze: np.ndarray | None = None
    rows: np.ndarray | None = None


class ArcNoise:
    """Stateful arc-noise generator for one sequence.

    Args:
        cfg: the noise model; level: in [0, MAX_NOISE_LEVEL]; size: (width, height);
            seed: random seed.
        family: the appearance (None: ``cfg``'s default family).

    Example:
        >>> from torchseam.core.config import load_noise
        >>> noise = ArcNoise(load_noise(), level=1.0, size=(656, 492), seed=0)
        >>> layers = noise.next(np.array([330.0, 420.0]), np.array([330.0, 240.0]))
        >>> layers.glare.shape
        (492, 656)
    """

    def __init__(self, cfg: NoiseConfig, level: float, size: tuple[int, int], seed: int,
                 family: AppearanceFamily | None = None) -> None:
        if not 0.0 <= level <= MAX_NOISE_LEVEL:
            raise ValueError(f"noise level {level} must lie in [0, {MAX_NOISE_LEVEL:g}]")
        self.cfg = cfg
        self.look = cfg.appearance() if family is None else family
        self.level = float(level)
        self.w, self.h = size
        self.rng = np.random.default_rng(seed)
        self.flicker = 1.0
        self.burst_left = 0
        yy, xx = np.mgrid[0:self.h, 0:self.w].astype(np.float32)
        self._xx, self._yy = xx, yy
        # the pixel coordinates of a row and of a column (float32), and the blobs' and the
        # band's float64 work array (reused)
        self._xs, self._ys = np.ascontiguousarray(xx[0]), np.ascontiguousarray(yy[:, 0])
        self._work_buf = np.empty(self.h * self.w)
        self._blur_plane = np.empty((self.h, self.w), np.float32)
        self._planes: tuple[np.ndarray, np.ndarray] | None = None   # next(reuse=True)'s
        # the box of its spatter plane that holds every pixel the last call drew (None: none)
        self._spatter_drawn: tuple[slice, slice] | None = None
        self._k = load_kernels(__package__)
        self._ramp = 1.0 - 0.5 * yy / self.h
        # glare: saturated core plus a long halo, as a template pasted at the arc each frame
        g = self.look.glare
        rad = cfg.glare.radius_px * (0.6 + 0.4 * level) * g.size
        # the sim family's round template is computed exactly as it always was
        exact = g.aspect == 1.0 and g.tilt_deg == 0.0 and g.size == 1.0
        self._glare_t = _glare_template(rad, g.core, g.halo, g.aspect, g.tilt_deg, exact)
        self._offset = np.asarray(g.offset_px, float) if any(g.offset_px) else None
        self.reflections = [self._new_reflection() for _ in range(cfg.reflections.count)]
        hz = self.look.haze
        self._haze: np.ndarray | None = None
        self._haze_phase: np.ndarray | None = None
        if hz.amount > 0:   # own random streams: the main one stays the same as without fume
            self._haze = _haze_field(hz.scale_px, size, seed)
            self._haze_phase = np.random.default_rng(seed + 1).uniform(0, 2 * np.pi, 3)
        self._haze_k = 0

    def _new_reflection(self) -> np.ndarray:
        r = self.cfg.reflections
        (r0, r1), (b0, b1) = r.radius_px, r.brightness
        return np.array([self.rng.uniform(0, self.w), self.rng.uniform(0.2 * self.h, self.h),
                         self.rng.uniform(r0, r1), self.rng.uniform(r0, r1) * 0.4,
                         self.rng.uniform(0, np.pi), self.rng.uniform(b0, b1)])

    def next(self, arc_uv: np.ndarray, stripe_uv: np.ndarray, reuse: bool = False
             ) -> NoiseLayers:
        """Advance one frame.

        Args:
            arc_uv: (2,) pixel of the arc (torch tip), may lie outside the image.
            stripe_uv: (2,) pixel of the stripe's feature point (reflections gather near it).
            reuse: the glare and spatter layers are this generator's own two planes, zeroed
                and drawn again by the next call (a renderer that is done with them by then
                saves two fresh frame-sized planes, and their page faults, per frame).
        """
        L, cfg, rng, look = self.level, self.cfg, self.rng, self.look
        if L > 0.0 and self._offset is not None:
            # the arc light centre sits off the torch tip's pixel
            arc_uv = arc_uv + self._offset
        # the glare template pasted below writes every pixel it covers: the whole image, as
        # a rule (the template reaches 2 x its radius), and then the glare plane needs no
        # zeroing first
        covered = L > 0.0 and self._glare_box(arc_uv)[:4] == (0, self.w, 0, self.h)
        out = NoiseLayers(*self._zeroed_planes(reuse, glare=not covered), [], NoiseFlags())
        if L <= 0.0:
            return out
        flags, glare, spatter = out.flags, out.glare, out.spatter

        # Arc brightness: AR(1) flicker around 1.
        self.flicker = max(0.2, 0.7 * self.flicker + 0.3 + cfg.glare.flicker * rng.standard_normal()
                           * np.sqrt(1 - 0.7**2))
        self._paste_glare(glare, arc_uv, cfg.glare.peak * L * self.flicker, fresh=True)

        # The groove mirrors the arc: a bright band from the arc up the seam towards the stripe.
        gr = cfg.groove
        reach = rng.uniform(gr.reach[0], gr.reach[1])
        self._band(glare, arc_uv, arc_uv + reach * (stripe_uv - arc_uv), gr.width_px,
                   rng.uniform(gr.brightness[0], gr.brightness[1]) * L * self.flicker)

        # Reflections: slow random walk, brightness follows the arc.
        for i, ref in enumerate(self.reflections):
            ref[:2] += rng.normal(0, 2.0, 2)
            ref[4] += rng.normal(0, 0.02)
            if not (0 <= ref[0] < self.w and 0 <= ref[1] < self.h) or rng.random() < 0.01:
                self.reflections[i] = ref = self._new_reflection()
                ref[:2] = stripe_uv + rng.normal(0, [90.0, 60.0])
            self._blob(glare, ref, ref[5] * look.reflections_gain * L * self.flicker)

        # Spatter streaks, with Markov bursts.
        if self.burst_left > 0:
            self.burst_left -= 1
        elif rng.random() < cfg.spatter.burst_prob * L:
            self.burst_left = int(rng.geometric(1.0 / cfg.spatter.burst_frames))
        flags.burst = self.burst_left > 0
        rate = (cfg.spatter.burst_rate if flags.burst else cfg.spatter.rate) * L
        flags.spatter = int(rng.poisson(rate))
        drawn = self._spatter(spatter, arc_uv, flags.spatter)
        if reuse:
            self._spatter_drawn = drawn

        if rng.random() < cfg.flash.prob * L:
            flags.flash = True
            gain = rng.uniform(cfg.flash.brightness[0], cfg.flash.brightness[1])
            # half of the flashes light the lower part (nearer the arc) more
            glare += gain * (self._ramp if rng.random() < 0.5 else 1.0)

        if rng.random() < cfg.dropout.prob * look.dropout_gain * L:
            flags.dropout = True
            for _ in range(int(rng.integers(cfg.dropout.gaps[0], cfg.dropout.gaps[1] + 1))):
                length = rng.uniform(cfg.dropout.length_px[0], cfg.dropout.length_px[1])
                # a third of the gaps hide the feature point itself
                centre = rng.normal(0, 4.0) if rng.random() < 0.33 else rng.uniform(-250, 250)
                out.gaps.append((centre - length / 2, centre + length / 2))

        # Family extras, drawn after everything above (so the rest of the stream is unchanged).
        if self._haze is not None:
            out.haze = self._fume(L)
        ex = look.exposure
        if ex.band_prob > 0 and rng.random() < ex.band_prob * L:
            flags.flash = True
            out.rows = self._band_rows(ex.band_gain)
        return out

    def _spatter(self, spatter: np.ndarray, arc_uv: np.ndarray, n: int
                 ) -> tuple[slice, slice] | None:
        """Draw ``n`` spatter streaks (or dots) from the arc into the all-zero ``spatter`` and
        blur them; returns the box of the plane that holds every pixel drawn (None: none)."""
        box = None
        draw = self._dot if self.look.spatter.style == "dots" else self._streak
        for _ in range(n):
            box = _union(box, draw(spatter, arc_uv))
        if box is None:
            return None
        # blur only around the streaks (the rest is zero before and after; the margin
        # exceeds the kernel's reach, so the pixels are the full-frame blur's)
        x0, y0, x1, y1 = box
        m = SPATTER_BLUR_MARGIN_PX
        ys = slice(max(0, y0 - m), min(self.h, y1 + m))
        xs = slice(max(0, x0 - m), min(self.w, x1 + m))
        if not (ys.start < ys.stop and xs.start < xs.stop):
            return None   # the streaks lie outside the image: nothing drawn
        # (into a reused plane: a fresh one would cost its page faults every frame)
        blurred = self._blur_plane[:ys.stop - ys.start, :xs.stop - xs.start]
        spatter[ys, xs] = cv2.GaussianBlur(spatter[ys, xs], (0, 0), 0.8, dst=blurred)
        return ys, xs

    def _zeroed_planes(self, reuse: bool, glare: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Two all-zero float32 (H, W) planes: new ones, or (``reuse``) this generator's own:
        the glare plane zeroed (not with ``glare`` False: the caller writes every pixel of it),
        the spatter plane where the last call drew (the box round its streaks that it
        blurred; the rest of it is zero, and the renderer only reads it)."""
        if not reuse:
            return (np.zeros((self.h, self.w), np.float32),
                    np.zeros((self.h, self.w), np.float32))
        if self._planes is None:
            self._planes = (np.zeros((self.h, self.w), np.float32),
                            np.zeros((self.h, self.w), np.float32))
            return self._planes
        glare_plane, spatter = self._planes
        if glare:
            glare_plane.fill(0.0)
        if self._spatter_drawn is not None:
            spatter[self._spatter_drawn] = 0.0
            self._spatter_drawn = None
        return self._planes

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
        numbers as adding it, without a full-frame temporary: ``_kernels.paste_scaled``, each
        product in float64 rounded once to float32, as ``0 + peak * t`` stores).
        """
        t = self._glare_t
        r = t.shape[0] // 2
        x0, x1, y0, y1, cx, cy = self._glare_box(c)
        if x0 < x1 and y0 < y1:
            if fresh:
                self._k.paste_scaled(img, t, y0, x0, y0 - cy + r, x0 - cx + r, float(peak))
            else:
                img[y0:y1, x0:x1] += peak * t[y0 - cy + r:y1 - cy + r, x0 - cx + r:x1 - cx + r]

    def _glare_box(self, c: np.ndarray) -> tuple[int, int, int, int, int, int]:
        """The image box ``(x0, x1, y0, y1)`` the glare template covers centred (to the
        pixel) on ``c``, and that pixel ``(cx, cy)``."""
        r = self._glare_t.shape[0] // 2
        cx, cy = int(round(c[0])), int(round(c[1]))
        return (max(0, cx - r), min(self.w, cx + r + 1), max(0, cy - r), min(self.h, cy + r + 1),
                cx, cy)

    def _work(self, roi: tuple[slice, slice]) -> np.ndarray:
        """A reused float64 work array of a ROI's shape (a view of one frame-sized buffer)."""
        n = (roi[0].stop - roi[0].start) * (roi[1].stop - roi[1].start)
        return self._work_buf[:n].reshape(roi[0].stop - roi[0].start, -1)

    def _blob(self, img: np.ndarray, ref: np.ndarray, amp: float) -> None:
        # The same arithmetic, element for element, as numpy's passes on full (h, w)
        # coordinate grids (float64, in their order: ``_kernels.blob_arg``), the exponential
        # numpy's, the sum as ``img[roi] += p`` (``_kernels.add_scaled``): bit-identical pixels
        cx, cy, ra, rb, ang = ref[:5]
        roi = self._roi(cx, cy, 3 * ra)
        if roi is None:
            return
        ys, xs = roi
        p = self._work(roi)
        self._k.blob_arg(self._xs[xs], self._ys[ys], float(cx), float(cy),
                         float(np.cos(ang)), float(np.sin(ang)), float(ra), float(rb), p)
        np.exp(p, out=p)
        self._k.add_scaled(img, ys.start, xs.start, p, float(amp))

    def _band(self, img: np.ndarray, p0: np.ndarray, p1: np.ndarray, width: float,
              amp: float) -> None:
        """Gaussian band along the segment p0-p1, fading towards p1 (bit-identical to the
        full-grid arithmetic; see :meth:`_blob`: ``_kernels.band_arg`` and ``band_add``)."""
        d = p1 - p0
        length = float(np.hypot(*d))
        if length < 1.0 or amp <= 0:
            return
        mid = 0.5 * (p0 + p1)
        roi = self._roi(mid[0], mid[1], 0.5 * length + 3 * width)
        if roi is None:
            return
        ys, xs = roi
        xr, yc = self._xs[xs], self._ys[ys]
        geo = (float(p0[0]), float(p0[1]), float(d[0]), float(d[1]), length**2)
        e = self._work(roi)
        self._k.band_arg(xr, yc, *geo, 2 * width**2, e)
        np.exp(e, out=e)
        self._k.band_add(img, ys.start, xs.start, xr, yc, *geo, float(amp), e)

    def _launch(self) -> tuple[float, float]:
        """Direction and distance from the arc of one spatter droplet: mostly upwards (towards
        the stripe) and sideways."""
        rng = self.rng
        ang = rng.uniform(np.pi, 2 * np.pi) if rng.random() < 0.8 else rng.uniform(0, np.pi)
        return ang, rng.exponential(120.0)

    def _streak(self, img: np.ndarray, arc: np.ndarray) -> tuple[int, int, int, int]:
        """Draw one spatter streak (a droplet's flight during the exposure, optionally with a
        brighter head); returns the box (x0, y0, x1, y1) it may touch."""
        rng, sp, look = self.rng, self.cfg.spatter, self.look.spatter
        ang, dist = self._launch()
        # element by element, the numbers of the (2,) array arithmetic
        sx, sy = arc[0] + dist * np.cos(ang), arc[1] + dist * np.sin(ang)
        length = rng.uniform(sp.length_px[0], sp.length_px[1]) * look.length_scale
        dirn = ang + rng.normal(0, 0.3)
        ex, ey = sx + length * np.cos(dirn), sy + length * np.sin(dirn)
        p0, p1 = (int(sx * 16), int(sy * 16)), (int(ex * 16), int(ey * 16))
        # drawn in this order: the same random stream
        value = float(rng.uniform(sp.brightness[0], sp.brightness[1]))
        thick = int(rng.integers(look.size_px[0], look.size_px[1] + 1))
        cv2.line(img, p0, p1, value, thick, cv2.LINE_8, 4)
        r = thick + 1
        if look.head > 0:   # the droplet itself, at the end of its flight
            r = thick + 2
            cv2.circle(img, p1, 8 * (thick + 2), value * (1 + look.head), -1,
                       cv2.LINE_8, 4)
        # the pixels the line can touch (end points in 1/16 px, plus its thickness)
        return (min(p0[0], p1[0]) // 16 - r, min(p0[1], p1[1]) // 16 - r,
                max(p0[0], p1[0]) // 16 + r + 1, max(p0[1], p1[1]) // 16 + r + 1)

    def _dot(self, img: np.ndarray, arc: np.ndarray) -> tuple[int, int, int, int]:
        """Draw one round spatter droplet; returns the box (x0, y0, x1, y1) it may touch."""
        rng, sp, look = self.rng, self.cfg.spatter, self.look.spatter
        ang, dist = self._launch()
        c = arc + dist * np.array([np.cos(ang), np.sin(ang)])
        value = float(rng.uniform(sp.brightness[0], sp.brightness[1]))
        rad = float(rng.uniform(look.size_px[0], look.size_px[1]))
        p = tuple(int(v) for v in c * 16)
        cv2.circle(img, p, int(rad * 16), value, -1, cv2.LINE_AA, 4)
        r = int(rad) + 2
        return (p[0] // 16 - r, p[1] // 16 - r, p[0] // 16 + r + 1, p[1] // 16 + r + 1)

    def _fume(self, L: float) -> np.ndarray:
        """Fume density in [0, 1] this frame: the fixed fume field seen through a window that
        drifts on a slow Lissajous path, its density breathing with the arc."""
        hz, f = self.look.haze, self._haze
        k, ph = self._haze_k, self._haze_phase
        assert f is not None and ph is not None  # called only with a fume field (haze on)
        self._haze_k += 1
        px, py = f.shape[1] - self.w, f.shape[0] - self.h
        # angular rates so that the window moves about drift_px per frame
        wx, wy = 2 * hz.drift_px / max(px, 1), 1.4 * hz.drift_px / max(py, 1)
        x = int(round(0.5 * px * (1 + np.sin(wx * k + ph[0]))))
        y = int(round(0.5 * py * (1 + np.sin(wy * k + ph[1]))))
        dens = L * (0.75 + 0.25 * np.sin(0.05 * k + ph[2]))
        return f[y:y + self.h, x:x + self.w] * np.float32(dens)

    def _band_rows(self, gain: float) -> np.ndarray:
        """Per-row exposure gain (H,): a band of rows (a flash caught by the rolling shutter)
        at ``gain``, with edges a few rows soft."""
        rng = self.rng
        y0 = rng.uniform(-0.1, 0.9) * self.h
        y1 = y0 + rng.uniform(0.08, 0.35) * self.h
        y = np.arange(self.h, dtype=np.float32)
        edge = np.clip(np.minimum(y - y0, y1 - y) / 4.0 + 0.5, 0.0, 1.0)
        return (1.0 + (gain - 1.0) * edge).astype(np.float32)

    def sensor_sigma(self) -> float:
        """Grey-level read noise std at this level."""
        s = self.cfg.sensor
        return s.sigma_clean + s.sigma_arc * self.level


@functools.lru_cache(maxsize=32)
def _glare_template(rad: float, core: float, halo: float, aspect: float, tilt_deg: float,
                    exact: bool = True) -> np.ndarray:
    """Float32 glare template (saturated Gaussian core plus exponential halo), centre pixel in
    the middle, made once per set of arguments and shared (every renderer of a family and level
    pastes the same one): never written to (the compiled paste takes writeable arrays only).
    ``aspect`` != 1 stretches it along the (tilted) image vertical and shrinks it across,
    keeping its area. Without ``exact`` it is evaluated every other pixel and interpolated (a
    quarter of the work; the glare is smooth at that scale)."""
    s = np.sqrt(aspect)
    r = int(4 * rad * max(s, 1 / s))
    if exact and aspect == 1.0 and tilt_deg == 0.0:
        d = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]).astype(np.float32)
    else:
        step = 1 if exact else 2
        y, x = np.mgrid[-r:r + 1:step, -r:r + 1:step].astype(np.float32)
        t = np.deg2rad(tilt_deg)
        along = np.cos(t) * y + np.sin(t) * x     # the tilted long axis
        across = np.cos(t) * x - np.sin(t) * y
        d = np.hypot(along / s, across * s).astype(np.float32)
    t = core * np.exp(-(d**2) / (2 * (0.25 * rad) ** 2)) + halo * np.exp(-d / rad)
    if t.shape[0] != 2 * r + 1:
        t = cv2.resize(t, (2 * r + 1, 2 * r + 1), interpolation=cv2.INTER_LINEAR)
    return t


def _haze_field(scale_px: float, size: tuple[int, int], seed: int) -> np.ndarray:
    """Float32 fume field in [0, 1], larger than the frame (the window drifts over it): smooth
    noise at ``scale_px``, squared so that the fume gathers in patches."""
    w, h = size
    pad = int(2 * scale_px)
    W, H = w + pad, h + pad
    rng = np.random.default_rng(seed + 2)
    low = rng.random((int(H / scale_px) + 3, int(W / scale_px) + 3)).astype(np.float32)
    f: np.ndarray = cv2.resize(low, (W, H), interpolation=cv2.INTER_CUBIC)
    f -= f.min()
    f /= max(float(f.max()), 1e-6)
    return f * f
