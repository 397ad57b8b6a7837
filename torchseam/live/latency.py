"""``torchseam calibrate latency``: the camera's latency (exposure -> arrival at the PC) against
the controller's fed-back motion.

With EGM guiding (RAPID hands a motion over, phase GUIDED), the robot moves the sensor up and
down along the torch axis over the part, a sine of ``amplitude_mm`` and ``period_s``: the laser
stripe moves across the image with the height (triangulation). Each frame gives the stripe's
row (the median over the columns of each column's brightest row of the stripe response, to a
sub-pixel by a parabola), its exposure time on the camera's clock and its arrival on the PC's;
the controller gives the torch's height along its axis on the PC's clock (its fed-back poses).

The latency the weld needs is the *least* delay from exposure to arrival (its clock offset is
the smallest ``arrival - exposure`` less that delay). So each frame's exposure time is put on
the PC's clock as if it had arrived with the least delay seen, and the latency ``L`` is the
shift back from there that makes the stripe's row an affine function of the height: the one
with the smallest median absolute residual of the straight-line fit over a grid of shifts,
refined by a parabola through the best three. Frames delivered late (a busy camera PC) change
nothing: their exposure times are their own.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from torchseam.core.errors import TorchseamError
from torchseam.core.transforms import matrix_to_quat
from torchseam.robot.egm import rapid_data as rd


@dataclass
class LatencyResult:
    latency_ms: float
    residual_px: float        # median absolute residual of the fit at the latency found
    px_per_mm: float          # the stripe's motion per mm of height
    frames: int
    curve: np.ndarray         # (K, 2): shift ms, residual px (the grid)


def stripe_row(image: np.ndarray) -> float:
    """The stripe's row: the median over the columns of each column's brightest row of the
    stripe response (red excess for colour, intensity for mono), columns whose peak is at least
    half the frame's; NaN when no column has the stripe."""
    img = np.asarray(image)
    if img.ndim == 3:
        b, g, r = (img[..., k].astype(np.int32) for k in range(3))
        resp = r - np.maximum(g, b)
    else:
        resp = img.astype(np.int32)
    peak = resp.max(axis=0)
    top = int(peak.max())
    if top <= 0:
        return float("nan")
    cols = np.flatnonzero(peak >= 0.5 * top)
    if len(cols) < 10:
        return float("nan")
    sub = resp[:, cols].astype(float)
    k = sub.argmax(axis=0)
    kk = np.clip(k, 1, len(sub) - 2)
    j = np.arange(len(cols))
    ym, y0, yp = sub[kk - 1, j], sub[kk, j], sub[kk + 1, j]
    den = ym - 2 * y0 + yp
    frac = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    return float(np.median(kk + np.clip(frac, -0.5, 0.5)))


def fit_latency(t_arrival: np.ndarray, row: np.ndarray, height_at: Any,
                max_ms: float = 200.0, step_ms: float = 0.25) -> LatencyResult:
    """The shift (ms) that best relates the stripe's rows to the heights (see the module).

    Args:
        t_arrival: (N,) frame arrival times, PC clock s.
        row: (N,) the stripe's row per frame (NaN: none).
        height_at: ``height_at(t (M,)) -> (M,)`` the torch's height, NaN where unknown.
    """
    t_arrival = np.asarray(t_arrival, float)
    row = np.asarray(row, float)
    shifts = np.arange(0.0, max_ms + step_ms / 2, step_ms)
    res = np.full(len(shifts), np.inf)
    slopes = np.zeros(len(shifts))
    n_used = 0
    for i, L in enumerate(shifts):
        h = height_at(t_arrival - L / 1e3)
        ok = np.isfinite(h) & np.isfinite(row)
        if ok.sum() < 20:
            continue
        A = np.stack([np.ones(ok.sum()), h[ok]], axis=1)
        coef, *_ = np.linalg.lstsq(A, row[ok], rcond=None)
        r = row[ok] - A @ coef
        res[i] = float(np.median(np.abs(r)))
        slopes[i] = coef[1]
        n_used = max(n_used, int(ok.sum()))
    if not np.isfinite(res).any():
        raise TorchseamError("latency: too few frames with both a stripe and a fed-back pose "
                             "(need 20)")
    k = int(np.argmin(res))
    best = float(shifts[k])
    if 0 < k < len(shifts) - 1 and np.isfinite(res[k - 1]) and np.isfinite(res[k + 1]):
        y0, y1, y2 = res[k - 1], res[k], res[k + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            best += 0.5 * step_ms * (y0 - y2) / den
    return LatencyResult(best, float(res[k]), float(slopes[k]), n_used,
                         np.stack([shifts, res], axis=1))


def measure_latency(runner: Any, duration_s: float, amplitude_mm: float, period_s: float,
                    progress: Any = print) -> LatencyResult:
    """Drive the sensor up and down over the part through EGM and fit the latency.

    ``runner``: a :class:`~torchseam.live.weld.WeldRunner` whose link and camera are open
    (:meth:`~torchseam.live.weld.WeldRunner.open`); RAPID must hand a motion over (phase
    GUIDED), as the virtual cell's ``--program latency`` does and the RAPID module's latency
    routine does."""
    view, link, cam = runner.view, runner.link, runner.cam
    deadline = time.monotonic() + runner.wait_rapid_s
    while True:
        runner.check_signal()   # Ctrl-C: nothing moved yet
        r = view.rapid
        if r is not None and r.phase == rd.RapidPhase.GUIDED:
            break
        if time.monotonic() > deadline:
            raise TorchseamError(f"latency: RAPID did not hand a motion over to EGM within "
                                 f"{runner.wait_rapid_s:g} s (run its latency routine)")
        time.sleep(0.01)
    number = r.segment
    runner.reply.set(False, number, rd.SensorState.TRACKING)
    time.sleep(0.3)
    newest = view.poses.newest
    if newest is None:
        raise TorchseamError("latency: no fed-back pose from the controller")
    t_start, T0 = newest
    z0 = T0[:3, 2]
    q0 = matrix_to_quat(T0[:3, :3])
    progress(f"calibrate latency: the sensor moves {amplitude_mm:g} mm up and down along the "
             f"torch axis, period {period_s:g} s, for {duration_s:g} s")
    times: list[float] = []
    exposed: list[float] = []
    rows: list[float] = []
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < duration_s:
            runner.check_signal()
            f = cam.get(1.0)
            now = time.monotonic()
            phase = (now - t0) / period_s
            # the sine ramps in over its first period (no jump at the start)
            a = amplitude_mm * min(1.0, phase) * math.sin(2 * math.pi * phase)
            link.set_target(T0[:3, 3] + a * z0, q0, measured_at=now)
            if f is None:
                continue
            times.append(f.t_arrival_s)
            exposed.append(f.t_exp_s)
            rows.append(stripe_row(f.image))
    except BaseException:
        # interrupted (Ctrl-C, SIGTERM) or failed mid-motion: the sensor back where it
        # started, the motion aborted towards RAPID, and the reason on up
        link.set_target(T0[:3, 3], q0, measured_at=time.monotonic())
        runner.reply.set(False, number, rd.SensorState.ABORT)
        raise
    link.set_target(T0[:3, 3], q0, measured_at=time.monotonic())
    time.sleep(0.5)
    runner.reply.set(False, number, rd.SensorState.DONE)
    time.sleep(0.2)

    def height_at(t: np.ndarray) -> np.ndarray:
        return (view.poses.positions_at(t) - T0[:3, 3]) @ z0

    # the frames' exposure times (camera clock) put on the PC's clock as if each had arrived
    # with the least delay seen: the latency found is that least delay, the one the weld's
    # clock offset assumes; a frame delivered late (a busy camera) changes nothing
    t_cam, t_arr = np.asarray(exposed), np.asarray(times)
    if len(t_cam) < 20:
        raise TorchseamError(f"latency: only {len(t_cam)} frames arrived in {duration_s:g} s")
    base = t_cam + float(np.min(t_arr - t_cam))
    # only frames exposed once the sensor stood at its start: the camera's queue still holds
    # frames of RAPID's move there (tens of mm away, the stripe elsewhere on the part), which
    # would pull the straight line off the motion
    since = base >= t_start
    if since.sum() < 20:
        raise TorchseamError(f"latency: only {int(since.sum())} frames exposed during the "
                             f"motion arrived in {duration_s:g} s")
    return fit_latency(base[since], np.asarray(rows)[since], height_at)
