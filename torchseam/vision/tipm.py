"""TIPM: the weld feature point in a clean laser-stripe frame (METHOD.md section 1).

Pipeline: red-stripe recognition (``R - max(G, B)``: the 650 nm stripe is red, arc light that
saturates all channels is not; minus its local vertical mean, so broad glare drops out) ->
threshold -> connected-area filtering (drop small blobs) -> dilation (close breaks) -> centre
line -> feature point.

Centre line: the paper thins the mask to a one-pixel skeleton (``centre_line="thinning"``, kept
for comparison and for the overlay); the default is a sub-pixel grey-gravity centre per column
(the accepted improvement of METHOD.md), weighed by the ridge response rather than the raw red
one, so that glare under the stripe does not pull it, and refined over the response within a few
rows of it, so that a stripe saturated on glare (its response split into two ridges) does not
leave it on one of them.

Feature point: the stripe is split into its two arms at the column that best explains it as two
lines (an exhaustive two-line least-squares search, O(N) with cumulative sums); each arm is then
fitted with a quadratic ``v = a + b u + c u^2`` over a window next to the corner (skipping the
few columns at the corner where the two arms blur together), and the feature point is where the
two quadratics meet (the windows move there and the arms are refitted, up to three times; fits
that still meet inside one arm's window give no point). A frame without a usable stripe gives
``ok=False`` and a reason, never a garbage point.

Arm prior (optional, for a tracker that has seen the previous frames): each arm's slope at the
corner and its curvature change little from frame to frame, while an arm with a gap next to the
corner or spatter on it lets a free quadratic bend and slide the corner several px along the
stripe. ``prior`` (see :func:`arm_shape`) adds ridge terms pulling slope and curvature toward the
previous frame's (a MAP fit); without it the fit is the plain least squares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from torchseam.core.checks import InputError, check_shape
from torchseam.core.config import config_field, config_path, load_config
from torchseam.core.dataset import check_frame
from torchseam.core.kernels import load_kernels
from torchseam.core.orient import BRIGHTNESS, FrameView
from torchseam.core.overlay import put_label
from torchseam.vision.axis import stripe_axis

# the shared quadratic fit, re-exported for the tracker and tools that take it from here
from torchseam.vision.quadfit import power_sums as power_sums
from torchseam.vision.quadfit import quad_normal_adjugate as quad_normal_adjugate


@dataclass(frozen=True)
class TipmConfig:
    """Parameters of TIPM (``configs/tipm.yaml``)."""

    min_red: float = config_field(lo=0.0)
    noise_k: float = config_field(lo=0.0)
    rel_threshold: float = config_field(lo=0.0, hi=1.0)
    ridge_px: int = config_field(lo=3)
    min_area: int = config_field(lo=0)
    dilate_px: int = config_field(lo=0)
    centre_half_px: float = config_field(lo=0.0, lo_open=True)
    centre_passes: int = config_field(lo=0)
    path_step_px: float = config_field(lo=0.0, lo_open=True)
    path_step_cost: float = config_field(lo=0.0)
    corner_gap_px: float = config_field(lo=0.0)
    fit_window_px: float = config_field(lo=0.0, lo_open=True)
    min_points_per_arm: int = config_field(lo=3)
    max_rms_px: float = config_field(lo=0.0, lo_open=True)
    min_corner_deg: float = config_field(lo=0.0, hi=180.0)
    max_saturated_fraction: float = config_field(lo=0.0, hi=1.0)
    max_red_clipped_fraction: float = config_field(lo=0.0, hi=1.0)
    white_core_fraction: float = config_field(lo=0.0, hi=1.0)
    smooth_px: int = config_field(lo=1)
    lobe_ridge: float = config_field(lo=0.0, hi=1.0)
    lobe_dip: float = config_field(lo=0.0, hi=1.0)
    lobe_columns: float = config_field(lo=0.0, hi=1.0)
    lobe_tol_px: float = config_field(lo=0.0)

    @property
    def lobes(self) -> LobeRule:
        """The two-lobed stripe rule of these settings (:func:`two_lobe_centres`)."""
        return LobeRule(self.lobe_ridge, self.lobe_dip, self.lobe_columns, self.lobe_tol_px)


@dataclass(frozen=True)
class LobeRule:
    """When a stripe is two-lobed (:func:`two_lobe_centres`; ``lobe_*`` in
    ``configs/tipm.yaml``): a cross-section holds two ridges when each stands at least
    ``ridge`` times its peak and the light between them falls to ``dip`` times the weaker;
    the stripe is two-lobed when at least ``columns`` of its cross-sections do, and then those
    whose ridges lie within ``tol_px`` of the median distance apart are centred between them."""

    ridge: float
    dip: float
    columns: float
    tol_px: float


def two_lobe_centres(prof: np.ndarray, first_row: np.ndarray, rule: LobeRule) -> np.ndarray:
    """(N,) centres of a two-lobed stripe's cross-sections, NaN where the centroid stands.

    Why: a laser diode running in two modes (or a stripe split by glare) draws two parallel
    lobes of unequal brightness; the centroid of the cross-section leans toward the brighter
    by a constant fraction of their distance, the corner with it (a constant offset that
    no amount of averaging removes). The light plane's middle is between the lobes. A
    cross-section with a second ridge from a spatter dot is not taken for a lobed stripe:
    the rule needs lobes a steady distance apart along much of the stripe.

    Args:
        prof: (N, K) cross-sections of the stripe (one per column), background removed.
        first_row: (N,) the row of each cross-section's first sample.
        rule: the thresholds (:class:`LobeRule`).

    Example:
        >>> x = np.arange(13.0)
        >>> lobes = np.exp(-(x - 4) ** 2 / 2) + 0.6 * np.exp(-(x - 8) ** 2 / 2)
        >>> c = two_lobe_centres(np.tile(lobes, (20, 1)), np.full(20, 100.0),
        ...                      LobeRule(0.15, 0.7, 0.5, 1.0))
        >>> bool(np.all(np.abs(c - 106.0) < 0.1))
        True
    """
    check_shape(prof, "N K", "prof", kind="array")
    if np.shape(first_row) != (len(prof),):
        raise InputError(f"first_row: expected shape ({len(prof)},), one row per cross-section, "
                         f"got {np.shape(first_row)}")
    return _lobe_centres(np.ascontiguousarray(prof, dtype=np.float64), first_row, rule,
                         load_kernels(__package__))


def _lobe_centres(prof: np.ndarray, first_row: np.ndarray, rule: LobeRule, k) -> np.ndarray:
    """:func:`two_lobe_centres` of checked arguments (``prof`` (N, K) float64, C order; ``k``
    TIPM's kernels): what :meth:`Tipm.centre` calls on every frame."""
    out = np.full(len(prof), np.nan)
    if prof.shape[1] < 3 or not len(prof):
        return out
    ridges = k.two_ridges(prof, float(rule.ridge), float(rule.dip))
    two = np.isfinite(ridges[:, 0])
    if two.sum() < max(1, rule.columns * len(prof)):
        return out
    ok = two & (np.abs(ridges[:, 0] - np.median(ridges[two, 0])) <= rule.tol_px)
    out[ok] = np.asarray(first_row, float)[ok] + ridges[ok, 1]
    return out


def red_response(frame: np.ndarray, with_green: bool = False,
                 out: list[np.ndarray] | None = None):
    """Stripe response (H, W) uint8 of a frame: ``R - max(G, B)`` of a BGR (H, W, 3) frame, the
    intensity itself of a mono (H, W) one.

    The 650 nm stripe is red; arc light bright enough to saturate the sensor is white, so in
    colour the red excess tells the stripe from the arc. A mono camera has a band-pass filter
    in front of it that did that work optically: what passes is the laser's wavelength (and
    the arc's light in that band, which the ridge filter of :meth:`Tipm.stripe_mask` takes
    away where it is broad). This is also the grey image the trackers work on.

    With ``with_green`` also returns the plane that tells saturation by arc light: G of a
    colour frame (the stripe saturates R only, white arc light G as well), the intensity of
    a mono one. ``out``: three (H, W) uint8 buffers to reuse (B, G, R planes; the response
    goes into the first), because allocating fresh frame-sized planes costs more than the
    arithmetic.

    Example:
        >>> red_response(np.full((2, 2), 7, np.uint8))[0, 0]
        np.uint8(7)
    """
    if frame.ndim == 2:
        if out is None:
            red = frame
        else:
            np.copyto(out[0], frame)
            red = out[0]
        return (red, frame) if with_green else red
    if out is None:
        b, g, r = cv2.split(frame)
        red = cv2.subtract(r, cv2.max(g, b))
    else:
        b, g, r = cv2.split(frame, out)
        red = cv2.subtract(r, cv2.max(g, b, dst=b), dst=b)
    return (red, g) if with_green else red


def load_tipm_config(path: str | Path | None = None) -> TipmConfig:
    """Read ``configs/tipm.yaml`` (or ``path``)."""
    return load_config(TipmConfig, path or config_path("tipm.yaml"))


def load_tipm(path: str | Path | None = None, centre_line: str = "subpixel") -> Tipm:
    """The shipped seam finder: :class:`Tipm` with ``configs/tipm.yaml`` (or ``path``). For
    the command line and scripts; library code takes the :class:`Tipm` as an argument."""
    return Tipm(load_tipm_config(path), centre_line)


@dataclass
class TipmResult:
    """Outcome of TIPM on one frame.

    Attributes:
        ok: a feature point was found.
        uv: (2,) feature pixel (u, v), NaN when not ``ok``.
        reason: why not, when not ``ok`` (e.g. ``"no stripe found"``).
        centre: (N, 2) centre-line points (u, v) used.
        arms: ((3,), (3,)) quadratic coefficients (a, b, c) of each arm in ``u - u0``, or None.
        u0: the column the arm fits are centred on.
        corner_deg: angle between the two arms' directions at the corner (180 = straight).
        rms_px: RMS residual of the arm fits over every centre-line point in their windows
            (the worse arm): how clean the stripe is; TIPM refuses a corner above
            ``max_rms_px``.
        inlier_rms_px: the same over the points the fits' robust pass kept: how well the
            arm lines are placed, the noise of the corner as a measurement (the live tracker
            weighs a fix by it).
        mask: (H, W) uint8 stripe mask after filtering (for the overlay).
        first_look: the planes :meth:`Tipm.find` gave with it are its first look's
            (:meth:`Tipm.stripe_mask` of the frame as given), not a second look's.
    """

    ok: bool
    uv: np.ndarray
    reason: str = ""
    centre: np.ndarray | None = None
    arms: tuple[np.ndarray, np.ndarray] | None = None
    u0: float = 0.0
    corner_deg: float = float("nan")
    rms_px: float = float("nan")
    mask: np.ndarray | None = None
    inlier_rms_px: float = float("nan")
    first_look: bool = True


#: the failure reason of a frame blinded by arc light
SATURATED = "frame saturated by arc light"
#: a pixel at or above this (uint8) is clipped: the level of the saturation rules of
#: :meth:`Tipm.stripe_mask` (white arc light: G of a colour frame, a mono frame's intensity)
CLIPPED = 250


def beside_clipped(frame: np.ndarray, pts: np.ndarray, reach: int) -> np.ndarray:
    """(N,) bool: centre-line points ``pts`` (N, 2) (u, v) of a frame read by its brightness
    (``frame`` (H, W) uint8: a mono camera's, or a colour camera's intensity view) whose column
    is clipped (at or above :data:`CLIPPED`) ``reach`` rows above or below them, or whose
    ``reach`` leaves the frame. There the ridge (the response less its vertical mean over
    ``2 reach + 1`` rows, :meth:`Tipm.stripe_mask`, ``reach = ridge_px // 2``) takes in light
    of unknown level, and a clipped region's edge passes it as a line: the rim of a saturated
    glare core (bright inside, darker outside) is read as a stripe. (A colour frame's red
    excess has no such rim: white clipped light has no red excess.) The same reason leaves
    out the columns next to the frame's top and bottom rows (:meth:`Tipm.centre`). A colour
    ``frame`` (H, W, 3) is judged by its G, the plane of the saturation rule.

    Example:
        >>> f = np.zeros((40, 10), np.uint8); f[:12] = 255          # a clipped blob above
        >>> beside_clipped(f, np.array([[5.0, 14.0], [5.0, 30.0]]), 5).tolist()
        [True, False]
    """
    plane = frame[..., 1] if frame.ndim == 3 else frame
    h = plane.shape[0]
    u = np.clip(np.rint(pts[:, 0]).astype(np.intp), 0, plane.shape[1] - 1)
    v = np.rint(pts[:, 1]).astype(np.intp)
    up, down = v - reach, v + reach
    out = (up < 0) | (down >= h)
    inside = ~out
    out[inside] = ((plane[up[inside], u[inside]] >= CLIPPED)
                   | (plane[down[inside], u[inside]] >= CLIPPED))
    return out


def thin_clipped_runs(plane: np.ndarray, max_rows: int, min_area: int = 0) -> np.ndarray:
    """(H, W) uint8 mask (255) of the column runs of clipped pixels (at or above
    :data:`CLIPPED`) of ``plane`` (H, W) uint8 (a frame read by its brightness) at most
    ``max_rows`` tall and bounded by unclipped pixels above and below (not the plane's edge),
    in connected areas (8-connected) of ``min_area`` px at least: a line clipped across its
    width, the stripe where it runs over bright glare. There its ridge (the response less its
    vertical mean) is a few grey levels and passes no threshold, but its cross-section is
    symmetric, so the clipped run's middle is its centre. A glare core's runs are taller than
    a stripe is thick, except in the few columns at its sides; where noise clips a nearly
    clipped halo in specks, a column holds several thin runs (none is kept there) and what is
    left of them are areas smaller than ``min_area`` (TIPM's spatter rule).

    Example:
        >>> f = np.zeros((40, 6), np.uint8); f[10:14] = 255; f[20:38, :3] = 255
        >>> m = thin_clipped_runs(f, 10); int(m[:, 0].sum() // 255), int(m[:, 5].sum() // 255)
        (4, 4)
    """
    if plane.dtype != np.uint8 or plane.ndim != 2:
        raise ValueError(f"thin_clipped_runs: expected an (H, W) uint8 plane, got {plane.dtype} "
                         f"{plane.shape}")
    out = np.zeros(plane.shape, np.uint8)
    # compiled: a column's runs in one pass, the areas summed along chains of runs (the numpy
    # and connected-components version took ~1 ms on the tracker's window, issue 35)
    load_kernels(__package__).thin_clipped_runs(np.ascontiguousarray(plane), CLIPPED,
                                                int(max_rows), int(min_area), out)
    return out


def _centred_runs(kernel: np.ndarray) -> np.ndarray | None:
    """(2 d + 1,) int64 half-widths of a structuring element (2 d + 1, 2 d + 1) whose every
    row is a run centred on its middle column (an ellipse's: ``cv2.MORPH_ELLIPSE``), or None
    (another shape)."""
    k = np.asarray(kernel) != 0
    if k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 == 0:
        return None
    d = k.shape[0] // 2
    reach = np.empty(k.shape[0], np.int64)
    for i, row in enumerate(k):
        cols = np.flatnonzero(row)
        half = d - int(cols[0]) if len(cols) else -1
        if half < 0 or not np.array_equal(cols, np.arange(d - half, d + half + 1)):
            return None
        reach[i] = half
    return reach


def _fail(reason: str, mask: np.ndarray | None = None, centre: np.ndarray | None = None
          ) -> TipmResult:
    return TipmResult(False, np.full(2, np.nan), reason, centre=centre, mask=mask)


class Tipm:
    """Classic stripe image processing for the weld feature point.

    Example:
        >>> tipm = Tipm(load_tipm_config())
        >>> res = tipm(np.zeros((492, 656, 3), np.uint8))
        >>> res.ok, res.reason
        (False, 'no stripe found (no red pixels above threshold)')
    """

    def __init__(self, cfg: TipmConfig, centre_line: str = "subpixel") -> None:
        if centre_line not in ("subpixel", "thinning"):
            raise ValueError(f"centre_line must be 'subpixel' or 'thinning', got {centre_line!r}")
        self.cfg = cfg
        self.centre_line = centre_line
        k = 2 * self.cfg.dilate_px + 1
        self._kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        # the brightest of the two pixels ridge_px // 2 rows above and below (see find)
        self._sides = np.zeros((2 * (cfg.ridge_px // 2) + 1, 1), np.uint8)
        self._sides[[0, -1]] = 1
        self._ws: dict[tuple, np.ndarray] = {}  # reused frame-sized planes (see _plane)
        self._stat_bufs: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # see _stats
        # cv2.blur's mean of a sum of ridge_px uint8 values (an odd count: the nearest
        # integer, never a tie), as a table for the compiled ridge (_stripe_mask_fused)
        k = int(cfg.ridge_px)
        self._mean_of: np.ndarray | None = (
            ((2 * np.arange(255 * k + 1) + k) // (2 * k)).astype(np.uint8)
            if k % 2 and 255 * k < 2**16 else None)
        # the same table for the second look's blur along the rows (smooth_px columns)
        k = int(cfg.smooth_px)
        self._smooth_of: np.ndarray | None = (
            ((2 * np.arange(255 * k + 1) + k) // (2 * k)).astype(np.uint8)
            if k % 2 and k > 1 else None)
        self._k = load_kernels(__package__)  # compiled (or loaded) now, not on the first frame
        self._lobes = cfg.lobes  # (a property that builds a LobeRule each time)
        self._reach = _centred_runs(self._kernel)  # the dilation's rows (see _mask)
        # _threshold compiled: numpy 2 multiplies float32 by a Python float in float32 (the
        # kernel's arithmetic; numpy 1 did it in float64)
        self._fast_threshold = (0.9 * np.float32(3.0)).dtype == np.float32
        self._runs = np.empty((4, 0), np.int64)  # the blobs' runs (reused, grown as needed)
        # the last mask _mask made and its bounding box (x, y, w, h), for centre()
        self._mask_rect: tuple[np.ndarray, tuple[int, ...]] | None = None

    def _plane(self, name: str, shape: tuple[int, int]) -> np.ndarray:
        """A reused uint8 work plane: fresh frame-sized arrays cost page faults on every frame,
        more than TIPM's arithmetic."""
        key = (name, shape)
        buf = self._ws.get(key)
        if buf is None:
            if len(self._ws) > 64:  # ROI sizes vary at the image border: keep the cache small
                self._ws.clear()
            buf = self._ws[key] = np.empty(shape, np.uint8)
        return buf

    # ------------------------------------------------------------------ stages
    def stripe_mask(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
        """Stripe response (H, W) uint8, filtered + dilated mask (H, W) uint8, failure reason.

        The stripe response is the ridge: the red response minus its local vertical mean, i.e.
        the stripe with the glare under it taken away. The centre line and ECAL weigh pixels
        by it: weighed by the raw red response, a glare halo's slope across the stripe pulls
        each column's centre toward the glare, and the corner with it; a frame refused as
        saturated
        gives the raw red response (and an empty mask). It lives in a work plane of this
        ``Tipm``: valid until its next call.
        """
        cfg = self.cfg
        hw = frame.shape[:2]
        planes = [self._plane(c, hw) for c in "bgr"]
        if self._mean_of is not None and frame.dtype == np.uint8 and frame.flags.c_contiguous and (
                frame.ndim == 2 or frame.shape[2] == 3):
            return self._stripe_mask_fused(frame, planes)
        red, g = red_response(frame, with_green=True, out=planes)
        # OpenCV takes a scalar src2; its stubs allow arrays only
        if frame.ndim == 3:
            # an arc flash that clips R nearly everywhere: the stripe can raise only G and B
            # there, so the red excess dips where the stripe is and its edges pass as stripe
            r = planes[2]  # R (red_response split the frame into the planes)
            clip = cv2.compare(r, 250, cv2.CMP_GE, dst=r)  # type: ignore[call-overload]
            if cv2.countNonZero(clip) > cfg.max_red_clipped_fraction * red.size:
                return red, np.zeros_like(red), SATURATED
        # the stripe saturates R only; white arc light saturates G as well
        sat = cv2.compare(g, 250, cv2.CMP_GE, dst=planes[2])  # type: ignore[call-overload]
        if cv2.countNonZero(sat) > cfg.max_saturated_fraction * red.size:
            return red, np.zeros_like(red), SATURATED
        # ridge: red minus its local vertical mean, so broad red glare does not pass as stripe
        # (a 3-column box is cheaper but lets more spatter through under heavy arc)
        ridge = cv2.blur(red, (1, cfg.ridge_px), dst=planes[1])
        ridge = cv2.subtract(red, ridge, dst=ridge)
        mask, why = self._mask(ridge, planes[2])
        return ridge, mask, why

    def _stripe_mask_fused(self, frame: np.ndarray, planes: list[np.ndarray]
                           ) -> tuple[np.ndarray, np.ndarray, str]:
        """:meth:`stripe_mask` of a uint8 frame with the red response, the saturation counts,
        the ridge and its statistics in one compiled pass (:func:`~torchseam.vision._kernels.
        colour_ridge`: the numbers of the OpenCV calls, to the bit; these were ~60 % of TIPM's
        time on the tracker's window)."""
        cfg = self.cfg
        assert self._mean_of is not None  # the caller checked
        red, ridge = planes[0], planes[1]
        hist, colmax = self._stats(frame.shape[1])
        if frame.ndim == 3:
            n_clip, n_sat = self._k.colour_ridge(frame, int(cfg.ridge_px), self._mean_of, red,
                                                 ridge, hist, colmax)
            if n_clip > cfg.max_red_clipped_fraction * red.size:
                return red, np.zeros_like(red), SATURATED
        else:
            n_sat = self._k.mono_ridge(frame, int(cfg.ridge_px), self._mean_of, red, ridge,
                                       hist, colmax)
        if n_sat > cfg.max_saturated_fraction * red.size:
            return red, np.zeros_like(red), SATURATED
        mask, why = self._mask(ridge, planes[2], (hist, colmax))
        return ridge, mask, why

    def _stats(self, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Reused (256,) int64 histogram and (width,) uint8 column-maximum buffers."""
        bufs = self._stat_bufs.get(width)
        if bufs is None:
            if len(self._stat_bufs) > 64:
                self._stat_bufs.clear()
            bufs = self._stat_bufs[width] = (np.zeros(256, np.int64), np.zeros(width, np.uint8))
        return bufs

    def _mask(self, ridge: np.ndarray, work: np.ndarray,
              stats: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, str]:
        """The stripe mask (H, W) uint8 of a ridge (H, W) uint8: thresholded (the frame's own
        level, :meth:`_threshold`), blobs under ``min_area`` dropped, dilated; and the failure
        reason. ``work``: a reused plane of the ridge's size for the binary image; ``stats``:
        the ridge's histogram and column maxima when they are known (else counted here)."""
        cfg = self.cfg
        thr = self._threshold(ridge, stats)
        if (self._reach is not None and cfg.min_area > 0 and ridge.dtype == np.uint8
                and ridge.flags.c_contiguous and 0.0 <= thr < 2**31):
            # threshold, blobs, dilation and bounding box in one compiled pass (the same
            # mask to the bit: a uint8 pixel is above thr where it is above floor(thr))
            h, w = ridge.shape
            need = h * ((w + 1) // 2) + 1  # (_kernels.runs_cap)
            if self._runs.shape[1] < need:
                self._runs = np.empty((4, need), np.int64)
            mask = np.zeros_like(ridge)
            above, kept, *rect = self._k.stripe_blobs(ridge, math.floor(thr),
                                                      int(cfg.min_area), self._reach,
                                                      self._runs, mask)
            if above == 0:
                return mask, "no stripe found (no red pixels above threshold)"
            if kept == 0:
                return mask, "no stripe found (only small blobs)"
            self._mask_rect = (mask, tuple(rect))
            return mask, ""
        _, binary = cv2.threshold(ridge, thr, 255, cv2.THRESH_BINARY, dst=work)
        bx, by, bw, bh = cv2.boundingRect(binary)
        if bw == 0:
            return np.zeros_like(ridge), "no stripe found (no red pixels above threshold)"
        # label and dilate only the box that holds anything (the stripe is a thin band), with a
        # margin for the dilation
        d = cfg.dilate_px
        h, w = binary.shape
        roi = (slice(max(by - d, 0), min(by + bh + d, h)),
               slice(max(bx - d, 0), min(bx + bw + d, w)))
        mask = np.zeros_like(binary)
        if cfg.min_area <= 0:  # every blob is kept: nothing to label (the profiles' Tipm)
            mask[roi] = cv2.dilate(binary[roi], self._kernel) if d else binary[roi]
            return mask, ""
        # the blobs of min_area px at least (one compiled pass: the mask of
        # cv2.connectedComponentsWithStats's blobs to the bit at a third of its time), dilated
        # in the same pass where the structuring element's rows are centred runs, with the
        # bounding box centre() asks cv2.boundingRect for
        binary = np.ascontiguousarray(binary)
        (ya, yb), (xa, xb) = (roi[0].start, roi[0].stop), (roi[1].start, roi[1].stop)
        if self._reach is not None:
            need = (yb - ya) * ((xb - xa + 1) // 2) + 1  # (_kernels.runs_cap)
            if self._runs.shape[1] < need:
                self._runs = np.empty((4, need), np.int64)
            kept, *rect = self._k.large_blobs_dilated(binary, ya, yb, xa, xb,
                                                      int(cfg.min_area), self._reach,
                                                      self._runs, mask)
            if kept == 0:
                return mask, "no stripe found (only small blobs)"
            self._mask_rect = (mask, tuple(rect))
            return mask, ""
        box = np.empty((yb - ya, xb - xa), np.uint8)
        _, kept = self._k.large_blobs(binary, ya, yb, xa, xb, int(cfg.min_area), box)
        if kept == 0:
            return mask, "no stripe found (only small blobs)"
        mask[roi] = cv2.dilate(box, self._kernel)
        return mask, ""

    def _threshold(self, ridge: np.ndarray,
                   stats: tuple[np.ndarray, np.ndarray] | None = None) -> float:
        """The stripe threshold of one frame's ridge (H, W) uint8, from the frame's own
        statistics rather than absolute grey levels (a faint stripe under room light and a
        lit stripe behind a band-pass filter differ by 10x in level): the largest of

        - the noise: ``noise_k`` times the ridge's 90th percentile (the stripe covers a few %
          of the frame; the rest is texture, speckle and read noise);
        - ``rel_threshold`` times the stripe's level, the median of the column maxima that
          rise above that noise (its typical brightness, which one brighter spatter streak or
          specular highlight does not move; a global maximum does);
        - ``min_red``.
        """
        cfg = self.cfg
        if stats is None:  # one compiled pass (cv2.calcHist and cv2.reduce took ~0.13 ms)
            ridge = np.ascontiguousarray(ridge, dtype=np.uint8)
            stats = self._stats(ridge.shape[1])
            self._k.ridge_stats(ridge, *stats)
        counts, colmax = stats
        if self._fast_threshold and ridge.size < 2**24:
            # the arithmetic below in one compiled pass (its float32 sums are exact there)
            return self._k.stripe_threshold(counts, colmax, float(cfg.noise_k),
                                            float(cfg.min_red), float(cfg.rel_threshold))
        # float32 counts, as cv2.calcHist gives them (the same cumulative sums to the bit)
        hist = counts.astype(np.float32)
        cdf = np.cumsum(hist)
        noise = cfg.noise_k * max(float(np.searchsorted(cdf, 0.9 * cdf[-1])), 1.0)
        strong = np.sort(colmax[colmax > noise])
        # np.median's value (the middle one, or the mean of the middle two in float64: exact
        # for these integers) without its overhead
        n = len(strong)
        level = (0.0 if not n else float(strong[n // 2]) if n % 2
                 else (float(strong[n // 2 - 1]) + float(strong[n // 2])) / 2.0)
        return max(cfg.min_red, noise, cfg.rel_threshold * level)

    def mask_around(self, frame: np.ndarray, uv: np.ndarray, radius: int
                    ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """Stripe response and mask (see :meth:`stripe_mask`) in the square ROI of ``radius``
        around ``uv``.

        What ECAL needs in the live loop, at a fraction of the full-frame cost. Returns
        ``(response, mask, (x0, y0))`` with the ROI's top-left corner.
        """
        h, w = frame.shape[:2]
        x0, y0 = max(0, int(uv[0]) - radius), max(0, int(uv[1]) - radius)
        x1, y1 = min(w, int(uv[0]) + radius + 1), min(h, int(uv[1]) + radius + 1)
        if x1 <= x0 or y1 <= y0:
            z = np.zeros((1, 1), np.uint8)
            return z, z, (x0, y0)
        red, mask, _ = self.stripe_mask(np.ascontiguousarray(frame[y0:y1, x0:x1]))
        return red, mask, (x0, y0)

    def centre(self, response: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """(N, 2) centre-line points (u, v) of the masked stripe: per column the centroid of
        ``response`` (the stripe response of :meth:`stripe_mask`) within one run of the mask.
        Which run, and which columns: the stripe is the longest smooth path of runs across
        the columns (``path_step_px``, ``path_step_cost``; a dynamic programme, see
        ``_kernels.stripe_path``). A spatter streak or a reflection beside the stripe, or a
        streak alone in the columns of a dropout of it, is off that path and gives no point:
        in a mono frame nothing tells them from the stripe by colour, a streak can be the
        brighter, and beside a long one no column holds the stripe alone.

        Columns where the stripe comes within the ridge filter's reach of the top or bottom
        row of the image (or of the window the tracker cut) are left out: the border skews the
        filter's vertical mean there, the mask ends short of the stripe's cross-section, so
        its centre leans inward, and those are the arm ends that bend a quadratic fit most
        (at a deep V they move the corner on clean frames).

        Each column's centroid is then moved to the centroid of the response within
        ``centre_half_px`` rows of it, mask or not (``centre_passes`` times). Why: where the
        stripe runs over arc glare its red channel saturates while green rises with the glare,
        so ``R - max(G, B)`` dips at the stripe's middle and its cross-section splits into two
        ridges 4-8 px apart, each near the threshold. The mask then holds one of them in some
        columns and the masked centroid sits on it, off the stripe's middle; next to the
        corner such columns slide the corner along the stripe while the arm fits stay tight
        (docs/benchmarks.md, "Figures behind design choices"). The window takes both ridges.
        """
        mask = np.ascontiguousarray(mask, dtype=np.uint8)
        reach = self.cfg.ridge_px // 2 + 1  # the ridge filter's: its mean is skewed there
        if self.centre_line == "thinning":
            v, u = np.nonzero(cv2.ximgproc.thinning(mask))
            order = np.argsort(u, kind="stable")
            pts = np.stack([u[order], v[order]], axis=1).astype(float)
            return pts[~self._k.border_columns(mask, reach)[u[order]]]
        response = np.ascontiguousarray(response, dtype=np.uint8)
        known = self._mask_rect
        # the runs are counted in the mask's bounding box only (known when _mask made it)
        x, y, bw, bh = (known[1] if known is not None and known[0] is mask
                        else cv2.boundingRect(mask))
        pts = self._k.centre_line(response, mask, float(self.cfg.centre_half_px),
                                  int(self.cfg.centre_passes), reach, float(self.cfg.path_step_px),
                                  float(self.cfg.path_step_cost),
                                  np.array([x, y, x + bw, y + bh], np.int64))
        if len(pts):
            half = int(self.cfg.centre_half_px)
            mid = _lobe_centres(self._k.cross_sections(response, pts, half),
                                np.rint(pts[:, 1]) - half, self._lobes, self._k)
            pts[:, 1] = np.where(np.isfinite(mid), mid, pts[:, 1])
        return pts

    # ------------------------------------------------------------------ main
    def __call__(self, frame: np.ndarray, prior: np.ndarray | None = None) -> TipmResult:
        """Find the feature point in one frame: BGR (H, W, 3) or mono (H, W), 8 or 16 bit, any
        size (``prior``: see :meth:`corner`)."""
        return self.find(check_frame(frame), prior)[0]

    def find(self, frame: np.ndarray, prior: np.ndarray | None = None
             ) -> tuple[TipmResult, np.ndarray, np.ndarray]:
        """The feature point of a checked frame (or window) with the stripe response and mask
        it was found on: ``(result, response (H, W) uint8, mask (H, W) uint8)``, the two
        planes valid until this ``Tipm``'s next call.

        A frame where no corner is found is looked at a second time, with the mask thresholded
        on the ridge averaged over ``smooth_px`` columns along the stripe; the centre line is
        still taken on the ridge itself. Why: in fume, or on a dim stripe in read noise, the
        stripe's ridge stands barely above the pixel noise, the per-pixel threshold breaks it
        into blobs and short arms, and no corner is found in frames where the eye sees the V
        clearly; averaging along the stripe lowers the noise by about the square root of
        ``smooth_px`` and leaves the stripe's level and its position across the stripe as they
        are. Only a failed frame gets the second look: where the stripe is strong, the
        threshold follows the stripe's own level, and the averaged mask only shortens the
        stripe next to gaps and lets dots of spatter through (docs/benchmarks.md). A frame
        saturated by arc light is not looked at again.

        A colour frame in which the red excess gives no corner is then looked at by its
        brightness (the mean of its channels, :data:`~torchseam.core.orient.BRIGHTNESS`), as
        a mono frame is, where it is a line: brighter than the light ``ridge_px // 2`` rows
        above and below it. Why: the red excess tells the stripe from white arc light, but it
        fails where the light around the stripe is itself red: under glare that clips R (and
        G) the stripe's excess is nil while it still shows, brighter, in the channels that
        have not clipped; in red-tinted fume the background's excess matches the stripe's.
        Brightness also shows the part's own lit faces, whose edges the ridge (a one-sided
        step passes it) would take for a stripe's arms; an edge's bright side stays bright,
        a line's two sides do not. The returned planes are the red excess's when this look
        finds no corner either: with no corner found they are the first look's (of
        :meth:`stripe_mask` of ``frame``), as with a corner ``first_look`` (the tracker
        reuses them, issue 35).
        """
        red, mask, why = self.stripe_mask(frame)
        res = _fail(why, mask) if why else self.corner(self.centre(red, mask), mask, prior)
        k = self.cfg.smooth_px
        if res.ok:
            return res, red, mask
        if k > 1 and why != SATURATED:
            smooth = self._plane("smooth", red.shape)
            if self._smooth_of is not None and red.flags.c_contiguous:
                self._k.row_box(red, int(k), self._smooth_of, smooth)  # (cv2.blur's plane)
            else:
                cv2.blur(red, (k, 1), dst=smooth)
            mask2, why2 = self._mask(smooth, self._plane("binary", red.shape))
            if not why2:
                res2 = self.corner(self.centre(red, mask2), mask2, prior)
                if res2.ok:
                    res2.first_look = False
                    return res2, red, mask2
        if frame.ndim == 3:
            # the red excess found no corner: look at the frame's brightness as at a mono frame
            # (see find's docstring); the red excess's planes are kept for a failure
            first = self._plane("first", red.shape)
            np.copyto(first, red)
            red = first
            # a line, not an edge: the ridge where the light ridge_px // 2 rows above AND
            # below it is darker by half of it at least (an edge's bright side stays bright)
            if self._mean_of is not None and frame.dtype == np.uint8 and frame.flags.c_contiguous:
                # the OpenCV calls below in one compiled pass (the same plane to the bit)
                look = self._plane("look", red.shape)
                self._k.brightness_line(frame, int(self.cfg.ridge_px), self._mean_of,
                                        self._plane("grey", red.shape), look)
            else:
                grey = (cv2.transform(frame, BRIGHTNESS, dst=self._plane("grey", red.shape))
                        if frame.dtype == np.uint8 else cv2.transform(frame, BRIGHTNESS))
                line = cv2.subtract(grey, cv2.dilate(grey, self._sides))
                ridge = cv2.subtract(grey, cv2.blur(grey, (1, self.cfg.ridge_px)))
                look = cv2.min(ridge, cv2.add(line, line))
            res3, red3, mask3 = self.find(look, prior)
            if res3.ok:
                res3.first_look = False
                return res3, red3, mask3
        return res, red, mask

    def corner(self, pts: np.ndarray, mask: np.ndarray | None = None,
               prior: np.ndarray | None = None) -> TipmResult:
        """Feature point from centre-line points (N, 2), sorted by u.

        ``prior``: (2, 4) rows (slope at the corner, curvature, weight of the slope, weight of
        the curvature) for the left and right arm; a weight is the squared point noise over the
        prior's variance (px^2 per slope^2, resp. per curvature^2). None: plain fit."""
        cfg = self.cfg
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"TIPM corner: centre-line points must be (N, 2) (u, v), got shape "
                             f"{pts.shape}")
        if prior is not None and np.shape(prior) != (2, 4):
            raise ValueError(f"TIPM corner: the arm prior must be (2, 4) (see arm_shape), got "
                             f"shape {np.shape(prior)}")
        if len(pts) < 2 * cfg.min_points_per_arm:
            return _fail(f"no stripe found ({len(pts)} centre-line points)", mask, pts)
        arms = np.empty((2, 3))
        k = self._k
        code, count, u0, x, rms, rms_in, v, corner = k.corner(
            pts, float(cfg.corner_gap_px), float(cfg.fit_window_px),
            int(cfg.min_points_per_arm), k.NO_PRIOR if prior is None else
            np.ascontiguousarray(prior, dtype=np.float64), arms)
        if code:
            return _fail(k.CORNER_FAILS[code].format(count=count), mask, pts)
        if abs(x) > cfg.corner_gap_px:
            # the arms meet inside one arm's fitted span: that fit ran over the corner (glare
            # hid or bent the stripe next to it) and the refits did not settle
            return _fail(f"no corner: the arm fits do not settle ({abs(x):.1f} px apart)",
                         mask, pts)
        if rms > cfg.max_rms_px:
            return _fail(f"no clean stripe: arm fit residual {rms:.2f} px", mask, pts)
        if 180.0 - corner < cfg.min_corner_deg:
            return _fail(f"no corner: the stripe is straight ({corner:.1f} deg)", mask, pts)
        return TipmResult(True, np.array([u0 + x, v]), "", pts, (arms[0], arms[1]), u0, corner,
                          rms, mask, rms_in)


def arm_shape(res: TipmResult) -> np.ndarray:
    """(2, 2) slope at the corner and curvature of the left and right arm of a found corner
    (what :meth:`Tipm.corner` takes as a prior)."""
    assert res.arms is not None
    x = res.uv[0] - res.u0
    return np.array([[a[1] + 2 * a[2] * x, a[2]] for a in res.arms])


def _quadfit(x: np.ndarray, y: np.ndarray, prior: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares (a, b, c) of y = a + b x + c x^2 (x (N,) centred on the corner already)
    and the residuals (N,). ``prior`` (b0, c0, w_b, w_c) adds w_b (b - b0)^2 + w_c (c - c0)^2
    to the squared error. (What the corner search runs compiled, for tests and tools.)"""
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    p = np.zeros(4) if prior is None else np.ascontiguousarray(prior, dtype=np.float64)
    k = np.array(load_kernels(__package__).quad_fit(x, y, np.ones(x.size, np.bool_), p))
    return k, y - (k[0] + k[1] * x + k[2] * x * x)


def draw_overlay(frame: np.ndarray, res: TipmResult, truth: np.ndarray | None = None
                 ) -> np.ndarray:
    """Frame with the stripe centre line (green), arm fits (blue) and feature point (yellow);
    a mono frame is drawn on in colour."""
    out = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR) if frame.ndim == 2 else frame.copy()
    if res.centre is not None and len(res.centre):
        for u, v in res.centre[:: max(1, len(res.centre) // 400)].astype(int):
            cv2.circle(out, (int(u), int(v)), 0, (0, 255, 0), -1)
    if res.ok and res.arms is not None:
        for side, coef in zip((-1, 1), res.arms, strict=True):
            x = np.linspace(0, 150, 40) * side + (res.uv[0] - res.u0)
            y = np.polynomial.polynomial.polyval(x, coef)
            poly = np.stack([x + res.u0, y], axis=1)
            cv2.polylines(out, [np.round(poly * 16).astype(np.int32)], False, (255, 128, 0), 1,
                          cv2.LINE_AA, 4)
        c = tuple(int(round(x * 16)) for x in res.uv)
        cv2.circle(out, c, 8 * 16, (0, 255, 255), 1, cv2.LINE_AA, 4)
        cv2.drawMarker(out, tuple(int(round(x)) for x in res.uv), (0, 255, 255),
                       cv2.MARKER_CROSS, 18, 1, cv2.LINE_AA)
    label = f"TIPM ({res.uv[0]:.1f}, {res.uv[1]:.1f})" if res.ok else f"TIPM: {res.reason}"
    put_label(out, label, (8, 20), 0.5)
    if truth is not None:
        cv2.drawMarker(out, tuple(int(round(x)) for x in truth), (0, 255, 0),
                       cv2.MARKER_TILTED_CROSS, 12, 1, cv2.LINE_AA)
    return out


def white_core(frame: np.ndarray, res: TipmResult) -> float:
    """Fraction of a found stripe's centre-line points (``res`` of TIPM on BGR ``frame``)
    where the stripe is overexposed into white: R clipped (>= 250) and G or B above half of
    it. There the red excess ``R - max(G, B)`` falls as the stripe gets brighter (more light
    raises only G and B), so it no longer tells the stripe from arc light."""
    if frame.ndim != 3 or res.centre is None or not len(res.centre):
        return 0.0
    h, w = frame.shape[:2]
    u = np.clip(np.rint(res.centre[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(res.centre[:, 1]).astype(int), 0, h - 1)
    px = frame[v, u].astype(int)  # (N, 3) B, G, R
    return float(np.mean((px[:, 2] >= 250) & (px[:, :2].max(axis=1) > 125)))


def find_view(frame: np.ndarray, tipm: Tipm, axis: str = "auto",
              response: str = "auto") -> FrameView | None:
    """How to look at a stream, from one clean camera frame (H, W[, 3]) and ``tipm``: which
    way the stripe runs (``axis``: rows, columns or auto) and, for a colour camera, which
    response shows it (``response``: red, intensity or auto; see
    :mod:`torchseam.core.orient`).

    Auto axis: the way the stripe itself runs (:func:`~torchseam.vision.axis.stripe_axis`:
    the view whose centre line covers more columns), never the view that happens to yield a
    corner (a groove's flank or a bright edge beside the stripe can). Auto response: the
    red excess, unless the stripe TIPM found is overexposed into white on more than
    ``white_core_fraction`` of its centre line (:func:`white_core`), or only the red channel
    shows a corner. None: no corner in any view allowed (not a clean stripe frame: try the
    next one).

    Example:
        >>> find_view(np.zeros((64, 64), np.uint8), load_tipm()) is None
        True
    """
    frame = check_frame(frame)
    responses = ("red", "intensity") if response == "auto" else (response,)
    for resp in responses:
        best: tuple[float, FrameView, TipmResult] | None = None
        along = stripe_axis(frame, tipm, resp) if axis == "auto" else axis
        for name in () if along is None else (along,):
            view = FrameView(name, frame.shape[0], resp)
            res = tipm(np.ascontiguousarray(view.frame(frame)))
            if res.ok and (best is None or res.rms_px < best[0]):
                best = (res.rms_px, view, res)
        if best is None:
            continue
        _, view, res = best
        if (response == "auto" and resp == "red" and frame.ndim == 3
                and white_core(np.ascontiguousarray(FrameView(view.axis, frame.shape[0]).frame(
                    frame)), res) > tipm.cfg.white_core_fraction):
            return FrameView(view.axis, frame.shape[0], "intensity")
        return view
    return None
