"""ECAL: expanding circle, arc length (METHOD.md section 5) -> the arm points p1t, p2t.

On the binarised stripe frame, a circle of radius R around the feature point crosses the stripe
once on each arm. Walking round the circle, the mask switches background -> stripe -> background
at the two boundaries of an arm: such a pair of crossings whose arc between them is stripe and
whose outer arcs are background, and whose arc length is a stripe width, is one arm crossing; its
midpoint (refined by the grey-level centroid along the arc when an intensity image is given) is
the arm point. Crossings from spatter and other blobs are rejected: a crossing must be a stripe
width long and joined to the feature point by stripe along the radius, and the two crossings
of a pair must leave the corner at least ``min_arm_separation_deg`` apart (two crossings of one
arm split by a dark streak are not the V). The circle grows from
``r_min`` until both arms are found and keeps growing (more leverage for the torch frame) while
both stay clean, up to ``r_max``.

Occluded arm (fallback): when only one arm is found at every radius and the previous frame's
arm directions are given, the missing arm point is placed at the found arm's radius along the
previous direction turned by minus the found arm's turn since then (the V opens and closes about
a steady bisector along the saddle, so the two arms' image angles change in opposite ways; held
instead, the hidden arm lags the seam more and more: docs/benchmarks.md, "Figures behind design
choices"), and the result is flagged ``fallback``; with no previous
directions, or with no arm at all, the result is not ``ok`` and says why (the caller then makes
no pose).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import overload

import numpy as np

from torchseam.core.config import config_path, load_config
from torchseam.core.kernels import load_kernels

ARC_STEP_PX = 1.5     # sampling step along the largest circle (all circles share the angles)
RADIAL_STEP_PX = 2.0  # ring spacing of the polar resampling
# the two arms leave the corner at least this far apart (the V of a 60-90 degree joint opens
# well over 90 degrees in the image; two crossings of one arm are a few degrees apart)


@dataclass(frozen=True)
class EcalConfig:
    r_min_px: float
    r_max_px: float
    r_step_px: float
    min_width_px: float
    max_width_px: float
    min_connected: float
    min_arm_separation_deg: float  # two crossings closer than this are one arm, not a pair
    min_extrapolation_circles: int  # fewer clean circles: mean arm angle, no extrapolation
    tipm_agreement_deg: float  # a tracker's fitted arm directions are used within this of ECAL's


def load_ecal_config(path: str | Path | None = None) -> EcalConfig:
    """Read ``configs/ecal.yaml`` (or ``path``)."""
    return load_config(EcalConfig, path or config_path("ecal.yaml"))


def load_ecal(path: str | Path | None = None) -> Ecal:
    """The shipped arm finder: :class:`Ecal` with ``configs/ecal.yaml`` (or ``path``). For the
    command line and scripts; library code takes the :class:`Ecal` as an argument."""
    return Ecal(load_ecal_config(path))


@dataclass
class EcalResult:
    """Arm points of one frame.

    Attributes:
        ok: both arm points are available (found, or one by fallback).
        p: (2, 2) pixels of p1t (the left arm, smaller u) and p2t; NaN when missing.
        angles: (2,) direction of each arm from the feature point (rad, image frame).
        radius: circle radius used (px).
        p_tangent: (2, 2) points on the arms' tangents at the corner, ``radius`` out: the
            chord to a curved arm leans by r / (2 rho); with at least
            ``min_extrapolation_circles`` clean circles the arm angle measured on each is
            extrapolated linearly to r = 0, with fewer their mean angle is used. Equals ``p``
            with one circle.
        fallback: one arm point came from the previous frame's direction.
        rejected: crossings rejected on the circles tried (spatter, other blobs).
        reason: why not ``ok``.
        circles: ``(radii (n,), angles (n, 2))`` of the clean circles ``p_tangent`` is made
            from (a found pair of arms; None otherwise). With ``Ecal(..., tangents=False)``
            ``p_tangent`` is left None and :meth:`Ecal.tangents` makes it when asked.
    """

    ok: bool
    p: np.ndarray
    angles: np.ndarray
    radius: float = float("nan")
    p_tangent: np.ndarray | None = None
    fallback: bool = False
    rejected: int = 0
    reason: str = ""
    circles: tuple[np.ndarray, np.ndarray] | None = None


class Ecal:
    """Expanding-circle arc-length arm finder.

    Example:
        >>> import cv2
        >>> mask = np.zeros((200, 200), np.uint8)
        >>> _ = cv2.line(mask, (100, 100), (10, 60), 255, 5)
        >>> _ = cv2.line(mask, (100, 100), (190, 60), 255, 5)
        >>> res = Ecal(load_ecal_config())(mask, np.array([100.0, 100.0]))
        >>> res.ok, bool(res.p[0, 0] < 100 < res.p[1, 0])
        (True, True)
    """

    def __init__(self, cfg: EcalConfig) -> None:
        self.cfg = cfg
        n = max(64, int(np.ceil(2 * np.pi * cfg.r_max_px / ARC_STEP_PX)))
        self._theta = np.arange(n) * (2 * np.pi / n)
        self._cos, self._sin = np.cos(self._theta), np.sin(self._theta)
        # rings every RADIAL_STEP_PX out to r_max (the circles ECAL tries are among them)
        self.ring_radii = np.ascontiguousarray(np.arange(cfg.r_max_px, 0.0, -RADIAL_STEP_PX)[::-1])
        self._ru = self.ring_radii[:, None] * np.cos(self._theta)
        self._rv = self.ring_radii[:, None] * np.sin(self._theta)
        self._fu, self._fv = np.empty_like(self._ru), np.empty_like(self._rv)  # polar's work
        self.circles = self.ring_radii[np.unique(np.argmin(np.abs(
            self.ring_radii[:, None] - np.arange(cfg.r_min_px, cfg.r_max_px + 1e-9,
                                                 cfg.r_step_px)[None]), axis=0))]
        self._circle_rows = np.searchsorted(self.ring_radii, self.circles).astype(np.int64)
        self._k = load_kernels(__package__)  # compiled (or loaded) now, not on the first frame

    def polar(self, mask: np.ndarray, uv: np.ndarray, intensity: np.ndarray | None
              ) -> tuple[np.ndarray, np.ndarray | None]:
        """Mask (and intensity) resampled on rings ``self.ring_radii`` around ``uv``: (R, N).

        One gather gives every circle (a row) and every radius from the feature point out to a
        crossing (a column), which is what the connectivity test walks along.
        """
        h, w = mask.shape
        r = self.cfg.r_max_px + 1
        inside = None
        if (r <= uv[0] < w - r and r <= uv[1] < h - r and mask.dtype == np.uint8
                and (intensity is None or (intensity.dtype == np.uint8
                                           and intensity.shape == mask.shape))):
            # the rings inside the image: the gather below in one compiled pass
            on = np.empty(self._ru.shape, np.bool_)
            val = np.empty(self._ru.shape) if intensity is not None else None
            self._k.polar(mask, mask if intensity is None else intensity,
                          intensity is not None, self._ru, self._rv, float(uv[0]), float(uv[1]),
                          on, _NO_VAL if val is None else val)
            return on, val
        if r <= uv[0] < w - r and r <= uv[1] < h - r:
            # one flat gather per image (2-D fancy indexing costs more); the pixel index
            # v * w + u formed in float64 (exact: whole numbers far below 2^53) and cast once
            fu, fv = self._fu, self._fv
            np.add(self._ru, uv[0], out=fu)
            np.rint(fu, out=fu)
            np.add(self._rv, uv[1], out=fv)
            np.rint(fv, out=fv)
            fv *= w
            fv += fu
            flat = fv.astype(np.intp)
        else:  # near the border: clip, mark
            iu = np.rint(uv[0] + self._ru).astype(np.intp)
            iv = np.rint(uv[1] + self._rv).astype(np.intp)
            inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
            iu *= inside
            iv *= inside
            flat = iv * w + iu
        on = mask.reshape(-1)[flat] > 0
        val = intensity.reshape(-1)[flat].astype(float) if intensity is not None else None
        if inside is not None:
            on &= inside
            if val is not None:
                val *= inside
        return on, val

    def crossings(self, on: np.ndarray, val: np.ndarray | None, uv: np.ndarray
                  ) -> list[tuple[list[_Crossing], int]]:
        """Accepted arm crossings on every circle of ``self.circles`` from a :meth:`polar`
        sampling: per circle ``([(angle, pixel)], number rejected)``.

        All circles in one compiled pass (:func:`torchseam.geometry._kernels.crossings`; this
        runs on every frame): a run of stripe along a circle is a crossing when its arc length
        is a stripe width and stripe joins it to the feature point along the radius at its
        (grey-weighted) mean angle.
        """
        cfg = self.cfg
        circle, ang, rejected = self._k.crossings(
            np.ascontiguousarray(on, dtype=np.bool_),
            _NO_VAL if val is None else np.ascontiguousarray(val, dtype=np.float64),
            self._circle_rows, self.ring_radii,
            self._cos, self._sin, float(cfg.min_width_px), float(cfg.max_width_px),
            float(cfg.min_connected))
        r = self.circles[circle]
        px = np.empty((len(ang), 2))  # uv + r * (cos, sin), column by column
        np.add(uv[0], r * np.cos(ang), out=px[:, 0])
        np.add(uv[1], r * np.sin(ang), out=px[:, 1])
        out: list[tuple[list[_Crossing], int]] = [([], int(x)) for x in rejected]
        for i, c in enumerate(circle.tolist()):
            out[c][0].append((float(ang[i]), px[i]))
        return out

    def __call__(self, mask: np.ndarray, uv: np.ndarray, intensity: np.ndarray | None = None,
                 prev_angles: np.ndarray | None = None, tangents: bool = True) -> EcalResult:
        """Arm points around feature pixel ``uv`` (2,) on the stripe ``mask`` (H, W) uint8.

        Args:
            mask: binarised stripe frame (non-zero = stripe).
            uv: (2,) feature point.
            intensity: optional (H, W) grey/red image for sub-pixel arm centres.
            prev_angles: (2,) arm directions of the previous frame (rad), for choosing among
                several candidates and for the occluded-arm fallback.
            tangents: make ``p_tangent`` now (False: when asked, :meth:`tangents`; the live
                locator needs it only where the tracker lends no arm directions).
        """
        if mask.ndim != 2:
            raise ValueError(f"mask: expected (H, W), got {mask.shape}")
        uv = np.asarray(uv, dtype=float)
        nan2 = np.full((2, 2), np.nan)
        if not np.isfinite(uv).all():
            return EcalResult(False, nan2, np.full(2, np.nan), reason="no feature point")
        # the pair of arms at a clean circle: (p1, a1, p2, a2, radius, rejected so far); the
        # result is made of the one kept only
        best: tuple[np.ndarray, float, np.ndarray, float, float, int] | None = None
        single: tuple[float, float, np.ndarray] | None = None
        radii: list[float] = []
        arm_angles: list[np.ndarray] = []
        rejected_total = 0
        kept: list[tuple[np.ndarray, float, np.ndarray, float, float, int]] = []
        on, val = self.polar(mask, uv, intensity)
        for r, (cands, rejected) in zip(self.circles, self.crossings(on, val, uv), strict=True):
            rejected_total += rejected
            pair = _pick_pair(cands, prev_angles, self.cfg.min_arm_separation_deg)
            if pair is None:
                if len(cands) == 1 and single is None:
                    single = (float(r), cands[0][0], cands[0][1])
                if best is not None:
                    # the arms stop being clean further out. The circle just inside, where an
                    # arm is about to vanish (hidden by the other pipe, glare), is deflected
                    # (its image angles jump, then the occluded-arm fallback copies them):
                    # keep the clean circle before it
                    if len(radii) >= 2:
                        radii.pop()
                        arm_angles.pop()
                        best = kept[-2]
                    break
                continue
            (a1, p1), (a2, p2) = pair
            prev_angles = np.array([a1, a2])  # follow the arms outwards
            radii.append(float(r))
            arm_angles.append(prev_angles)
            best = (p1, a1, p2, a2, float(r), rejected_total)
            kept.append(best)
        if best is not None:
            p1, a1, p2, a2, r_best, rejected_best = best
            res = EcalResult(True, np.stack([p1, p2]), np.array([a1, a2]), r_best,
                             rejected=rejected_best)
            res.circles = (np.array(radii), np.array(arm_angles))
            if tangents:
                self.tangents(res, uv)
            return res
        if single is not None and prev_angles is not None:
            r, a, p = single
            k = int(np.argmin(np.abs(_wrap(prev_angles - a))))
            # the hidden arm mirrors the seen one's turn about the previous bisector
            other = float(prev_angles[1 - k] - _wrap(a - prev_angles[k]))
            q = uv + r * np.array([np.cos(other), np.sin(other)])
            pts = [(a, p), (other, q)] if k == 0 else [(other, q), (a, p)]
            p = np.stack([pts[0][1], pts[1][1]])
            return EcalResult(True, p, np.array([pts[0][0], pts[1][0]]), r, p_tangent=p,
                              fallback=True)
        why = "one arm only (occluded) and no previous arm directions" if single else (
            "no arm crossings around the feature point")
        return EcalResult(False, nan2, np.full(2, np.nan), reason=why)


    def tangents(self, res: EcalResult, uv: np.ndarray) -> np.ndarray | None:
        """``res.p_tangent`` (made from ``res.circles`` and kept, if not made yet) of a result
        of this ECAL around ``uv`` (the feature point it was called with)."""
        if res.p_tangent is None and res.circles is not None:
            radii, arm_angles = res.circles
            res.p_tangent = _tangent_points(np.asarray(uv, dtype=float), radii, arm_angles,
                                            res.radius, self.cfg.min_extrapolation_circles)
        return res.p_tangent


_NO_VAL = np.zeros((0, 0))  # no grey levels: the kernel weighs every sample alike


def _tangent_points(uv: np.ndarray, radii: np.ndarray, angles: np.ndarray, r_ref: float,
                    min_circles: int) -> np.ndarray:
    """Arm directions at the corner, as points ``r_ref`` from it, (2, 2).

    ``radii`` (n,), ``angles`` (n, 2): the arm angles on each clean circle. With at least
    ``min_extrapolation_circles`` circles the angle is extrapolated linearly to r = 0 (the
    chord to a curved arm leans by r / (2 rho)); with fewer, the extrapolation from a short
    span of radii multiplies the angle noise several times (on heavy-arc frames enough to turn
    the torch axis by many degrees), so the mean angle is used: its lean is small at the small
    radii of a short span.
    """
    out = np.empty((2, 2))
    unwrapped = np.unwrap(angles, axis=0)  # each arm's column on its own, in one call
    fit = len(radii) >= min_circles
    if fit:
        r_mean = radii.mean()
        rc = radii - r_mean
        rr = rc @ rc
    for i in range(2):
        a = np.ascontiguousarray(unwrapped[:, i])
        if fit:
            # intercept of the least-squares line a(r) (closed form: polyfit costs 10x more)
            a0 = a.mean() - (rc @ a) / rr * r_mean
        else:
            a0 = float(np.mean(a))
        out[i] = uv + r_ref * np.array([np.cos(a0), np.sin(a0)])
    return out


@overload
def _wrap(a: float) -> float: ...
@overload
def _wrap(a: np.ndarray) -> np.ndarray: ...
def _wrap(a: float | np.ndarray) -> float | np.ndarray:
    """Angle(s) wrapped into [-pi, pi)."""
    if isinstance(a, float):  # (np.float64 too) Python's float % is numpy's remainder, to the
        return (float(a) + math.pi) % (2 * math.pi) - math.pi  # bit, without its ~3 us
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


_Crossing = tuple[float, np.ndarray]  # (angle around the corner, pixel)


def _pick_pair(cands: list[_Crossing], prev: np.ndarray | None, min_separation_deg: float
               ) -> tuple[_Crossing, _Crossing] | None:
    """Two arm crossings, ordered left arm (smaller u) first."""
    if len(cands) < 2:
        return None
    if len(cands) == 2:
        pair = cands
    elif prev is not None:
        # the candidates nearest the previous arm directions
        def nearest(a: float) -> _Crossing:
            return min(cands, key=lambda c: abs(_wrap(c[0] - a)))

        pair = [nearest(a) for a in prev]
        if pair[0] is pair[1]:
            return None
    else:
        # the two most opposed crossings: arms leave the corner on opposite sides
        best: tuple[_Crossing, _Crossing] | None = None
        score = -1.0
        for i in range(len(cands)):
            for j in range(i + 1, len(cands)):
                s = abs(_wrap(cands[i][0] - cands[j][0]))
                if s > score:
                    best, score = (cands[i], cands[j]), s
        assert best is not None  # three or more crossings: some pair scores >= 0
        pair = list(best)
    if abs(_wrap(pair[0][0] - pair[1][0])) < math.radians(min_separation_deg):  # (np.radians')
        return None  # both on one arm (a gap or a dark streak splits it): not a pair
    pair = sorted(pair, key=lambda c: c[1][0])
    return pair[0], pair[1]
