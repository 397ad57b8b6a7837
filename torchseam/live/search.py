"""Search for the seam from a start off the seam (``torchseam demo --start-offset-mm/
--start-angle-deg``), with the arc off.

:class:`SeamSearch` knows nothing of the simulator: it is given the start pose (the torch TCP
in the robot base, (4, 4) mm) and per camera frame whether TIPM found a stripe corner and
where; it answers with the next torch pose to command. The pattern is a zig-zag across the
seam that widens each leg (lateral offsets 0, +s, -s, +2s, -2s, ... up to ``max_extent_mm``,
``s = lateral_step_mm``); the move ``y`` across the seam is ``lateral(y)`` (the demo: along the
part's surfaces, :func:`across_seam`, so that the torch keeps its height over the plate or the
pipe it passes over; default along the start pose's y axis), at the start pose's stand-off;
when a sweep at one torch angle ends without the seam, the next sweep turns the torch about its
own axis by ``angle_step_deg`` (+, -, 2+, 2-, ... up to ``max_angle_deg``). Every pose of the
pattern lies within those bounds of the start pose (it moves between vertices in straight
lines); each one is ``speed_mm_s`` / ``turn_deg_s`` of one frame from the previous one, far
inside the EGM link's step limits, and the caller's reachability gate (``reachable``) is asked
first: an unreachable pose ends the leg there and the pattern goes on with the next one.

The stand-off is chosen per start from the part's geometry through the gate
(:func:`choose_standoff`): the lowest of ``standoff_mm``, ``+ standoff_step_mm``, ... up to
``max_standoff_mm`` at which every pose of the search's region passes the caller's check (the
demo: the reachability gate, and the torch's tip off the part by the gate's margin).

The seam is found when TIPM sees a corner on ``confirm_frames`` consecutive frames, each
within ``confirm_px`` of the previous one. The search gives up (``failed``, with ``reason``)
when the pattern is exhausted or ``time_limit_s`` has passed. (The demo then triangulates the
corner and approaches it: :func:`torchseam.live.demo._search_seam`.)

Settings: ``configs/search.yaml`` (:class:`SearchConfig`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from torchseam.core.config import config_field as _f
from torchseam.core.config import config_path, load_config
from torchseam.core.transforms import rotvec


@dataclass(frozen=True)
class SearchConfig:
    """The seam search's settings (``configs/search.yaml``)."""

    standoff_mm: float = _f(lo=0.0)                    # lowest search stand-off tried
    lateral_step_mm: float = _f(lo=0.0, lo_open=True)  # zig-zag: widening per leg
    max_extent_mm: float = _f(lo=0.0, lo_open=True)    # lateral bound, either side of the start
    angle_step_deg: float = _f(lo=0.0, lo_open=True)   # torch turn between two sweeps
    max_angle_deg: float = _f(lo=0.0, hi=90.0)         # angular bound, either side of the start
    speed_mm_s: float = _f(lo=0.0, lo_open=True)       # search speed (lateral)
    turn_deg_s: float = _f(lo=0.0, lo_open=True)       # search speed (about the torch axis)
    time_limit_s: float = _f(lo=0.0, lo_open=True)     # give up after this long
    confirm_frames: int = _f(lo=1)                     # corner seen on this many frames in a row
    confirm_px: float = _f(lo=0.0, lo_open=True)       # ... each this close to the previous one
    # the stand-off is chosen per start: the lowest of standoff_mm, + standoff_step_mm, ... up
    # to max_standoff_mm at which the whole search region passes the gate (choose_standoff)
    max_standoff_mm: float = _f(lo=0.0, default=25.0)
    standoff_step_mm: float = _f(lo=0.0, lo_open=True, default=5.0)
    region_step_mm: float = _f(lo=0.0, lo_open=True, default=2.5)  # its lateral sampling
    # the seam the search found may lie at most this far from the programmed one (the approach
    # aims at the found one; farther: another edge, or the wrong part, and the search fails)
    max_seam_offset_mm: float = _f(lo=0.0, lo_open=True, default=8.0)

    def _check(self) -> None:
        if self.max_standoff_mm < self.standoff_mm:
            raise ValueError(f"max_standoff_mm: {self.max_standoff_mm} is below standoff_mm "
                             f"{self.standoff_mm}")

    def standoffs(self) -> list[float]:
        """The stand-offs :func:`choose_standoff` tries, lowest first."""
        n = int(np.floor((self.max_standoff_mm - self.standoff_mm) / self.standoff_step_mm
                         + 1e-9))
        return [self.standoff_mm + k * self.standoff_step_mm for k in range(n + 1)]


def load_search_config(path=None) -> SearchConfig:
    return load_config(SearchConfig, path or config_path("search.yaml"))


def offset_pose(T: np.ndarray, lateral_mm: float = 0.0, angle_deg: float = 0.0,
                lift_mm: float = 0.0, along_mm: float = 0.0) -> np.ndarray:
    """``T`` (4, 4) displaced in its own frame: ``along_mm`` along x (travel), ``lateral_mm``
    along y, ``lift_mm`` back along the torch axis (-z), then turned by ``angle_deg`` about
    its own z (the torch axis)."""
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    M = np.eye(4)
    M[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    M[:3, 3] = [along_mm, lateral_mm, -lift_mm]
    return T @ M


def across_seam(plus: np.ndarray | None, minus: np.ndarray | None
                ) -> Callable[[float], np.ndarray]:
    """The move ``u`` mm across the seam, (3,) in the base: ``u * plus`` for ``u >= 0``,
    ``-u * minus`` below (``plus``/``minus``: the directions along the part's surfaces on the
    torch's +y and -y side, :meth:`torchseam.plan.weld.WeldPlan.search_arms`), so that the
    torch keeps its height over the surface it passes over."""
    p, m = (np.asarray(v, float) for v in (plus, minus))
    return lambda u: u * p if u >= 0 else -u * m


def search_start(T0: np.ndarray, standoff_mm: float, offset_mm: float, angle_deg: float,
                 across: Callable[[float], np.ndarray] | None = None) -> np.ndarray:
    """The pose ``offset_mm`` across the seam from the programmed start ``T0`` (along
    ``across``; default the torch's own y), lifted ``standoff_mm`` back along its axis and
    turned ``angle_deg`` about it."""
    if across is None:
        return offset_pose(T0, lateral_mm=offset_mm, angle_deg=angle_deg, lift_mm=standoff_mm)
    T = offset_pose(T0, angle_deg=angle_deg, lift_mm=standoff_mm)
    T[:3, 3] += across(offset_mm)
    return T


def choose_standoff(T0: np.ndarray, cfg: SearchConfig, offset_mm: float, angle_deg: float,
                    clear: Callable[[np.ndarray], np.ndarray],
                    across: Callable[[float], np.ndarray] | None = None
                    ) -> tuple[float, int, int]:
    """The search stand-off for a start ``offset_mm`` / ``angle_deg`` off the programmed start
    ``T0``: the lowest of ``cfg.standoffs()`` at which every pose of the search's region (the
    lateral bound around the start every ``region_step_mm``, at each of the pattern's torch
    turns) passes ``clear`` ((N, 4, 4) poses -> (N,) bool: the gate and the tip's clearance).
    None passing everywhere: the one that passes most (the search's legs are cut where the
    gate refuses). Returns (stand-off mm, poses passed, poses checked)."""
    n = int(np.ceil(cfg.max_extent_mm / cfg.region_step_mm))
    ys = offset_mm + np.linspace(-cfg.max_extent_mm, cfg.max_extent_mm, 2 * n + 1)
    angles = sorted({a for _, a in pattern(cfg)})
    best: tuple[int, float] | None = None
    for lift in cfg.standoffs():
        T = np.array([search_start(T0, lift, y, angle_deg + a, across)
                      for a in angles for y in ys])
        ok = int(np.asarray(clear(T), bool).sum())
        if ok == len(T):
            return lift, ok, len(T)
        if best is None or ok > best[0]:
            best = (ok, lift)
    assert best is not None
    return best[1], best[0], len(ys) * len(angles)


def steps_between(Ta: np.ndarray, Tb: np.ndarray, max_mm: float, max_deg: float
                  ) -> list[np.ndarray]:
    """Poses from ``Ta`` (excluded) to ``Tb`` (included) in a straight line and a constant
    turn (slerp), each at most ``max_mm`` and ``max_deg`` from the previous one."""
    from scipy.spatial.transform import Rotation, Slerp

    dp = float(np.linalg.norm(Tb[:3, 3] - Ta[:3, 3]))
    da = float(np.degrees(np.linalg.norm(rotvec(Ta[:3, :3].T @ Tb[:3, :3]))))
    n = max(1, int(np.ceil(max(dp / max_mm, da / max_deg) - 1e-9)))
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([Ta[:3, :3], Tb[:3, :3]])))
    out = []
    for f in np.arange(1, n + 1) / n:
        T = np.eye(4)
        T[:3, :3] = slerp([f]).as_matrix()[0]
        T[:3, 3] = Ta[:3, 3] + f * (Tb[:3, 3] - Ta[:3, 3])
        out.append(T)
    return out


def pattern(cfg: SearchConfig) -> list[tuple[float, float]]:
    """The search's vertices, (lateral mm, angle deg) from the start pose, in order."""
    ys = [0.0]
    k = 1
    while k * cfg.lateral_step_mm < cfg.max_extent_mm + cfg.lateral_step_mm:
        y = min(k * cfg.lateral_step_mm, cfg.max_extent_mm)
        ys += [y, -y]
        if y >= cfg.max_extent_mm:
            break
        k += 1
    angles = [0.0]
    k = 1
    while True:
        a = min(k * cfg.angle_step_deg, cfg.max_angle_deg)
        if a <= angles[-1] or a == 0.0:
            break
        angles += [a, -a]
        if a >= cfg.max_angle_deg:
            break
        k += 1
    out: list[tuple[float, float]] = []
    for i, a in enumerate(angles):
        sweep = ys if i % 2 == 0 else ys[::-1]  # the next sweep starts where this one ended
        out += [(y, a) for y in sweep]
    return out


class SeamSearch:
    """A bounded search for the stripe's corner around a start pose (see the module doc).

    Args:
        T_start: (4, 4) torch TCP pose the search starts from and is bounded around.
        lateral: ``lateral(y) -> (3,)``, the move ``y`` mm across the seam from the start in
            the base (the demo: along the part's surfaces, :func:`across_seam`); default along
            the start pose's y axis.
        cfg: settings.
        frame_rate_hz: camera frames per second (one :meth:`step` per frame).
        reachable: ``reachable(T) -> bool``, the reachability gate; default: all poses.
        t0_s: the time the search starts (the caller's clock).

    Per frame: :meth:`observe` with TIPM's result on it (``ok``, ``uv``), then, while
    neither ``found`` nor ``failed``, :meth:`step` for the next pose to command.
    """

    def __init__(self, T_start: np.ndarray, cfg: SearchConfig, frame_rate_hz: float,
                 reachable: Callable[[np.ndarray], bool] | None = None, t0_s: float = 0.0,
                 lateral: Callable[[float], np.ndarray] | None = None) -> None:
        self.T_start = np.asarray(T_start, float)
        # y mm across the seam from the start -> (3,) move in the base (default its own y)
        self.lateral = lateral or (lambda y: y * self.T_start[:3, 1])
        self.cfg = cfg
        self.dt = 1.0 / frame_rate_hz
        self.reachable = reachable or (lambda T: True)
        self.t0 = t0_s
        self.vertices = pattern(cfg)
        self.i = 1                         # the vertex being moved to
        self.y, self.a = 0.0, 0.0          # where the last pose commanded is
        self.seen: list[np.ndarray] = []   # consecutive corners
        self.found = False
        self.failed = False
        self.reason = ""
        self.found_at: np.ndarray | None = None    # the pose from which it was confirmed
        self.found_uv: np.ndarray | None = None
        self.elapsed_s = 0.0
        self.extent = (0.0, 0.0)           # largest |lateral| mm, |angle| deg commanded
        self.refused = 0                   # poses the gate refused (legs cut short)

    def pose(self, y: float, a: float) -> np.ndarray:
        """The pattern's pose ``y`` mm across the seam from the start, turned ``a`` deg."""
        T = offset_pose(self.T_start, angle_deg=a)
        T[:3, 3] += self.lateral(y)
        return T

    def observe(self, ok: bool, uv, t_s: float, T_now: np.ndarray | None = None) -> bool:
        """One frame's TIPM result; True when the seam is now confirmed."""
        if self.found or self.failed:
            return self.found
        self.elapsed_s = t_s - self.t0
        uv = np.asarray(uv, float)
        if ok and np.all(np.isfinite(uv)):
            if self.seen and np.linalg.norm(uv - self.seen[-1]) > self.cfg.confirm_px:
                self.seen = []
            self.seen.append(uv)
        else:
            self.seen = []
        if len(self.seen) >= self.cfg.confirm_frames:
            self.found = True
            self.found_uv = self.seen[-1]
            self.found_at = None if T_now is None else np.asarray(T_now, float)
            return True
        if self.elapsed_s >= self.cfg.time_limit_s:
            self._fail(f"time limit {self.cfg.time_limit_s:g} s reached")
        return False

    def _fail(self, why: str) -> None:
        c = self.cfg
        self.failed = True
        self.reason = (f"seam not found: {why}; the search covered up to "
                       f"{self.extent[0]:.1f} mm and {self.extent[1]:.1f} deg of the "
                       f"{c.max_extent_mm:g} mm / {c.max_angle_deg:g} deg bound around the "
                       f"start in {self.elapsed_s:.1f} s (the seam not seen on "
                       f"{c.confirm_frames} consecutive frames)")

    def step(self) -> np.ndarray | None:
        """The next pose to command (one frame of motion along the pattern), or None when the
        search has ended (found, or failed: see ``reason``)."""
        if self.found or self.failed:
            return None
        c = self.cfg
        while self.i < len(self.vertices):
            ty, ta = self.vertices[self.i]
            dy, da = ty - self.y, ta - self.a
            f = max(abs(dy) / (c.speed_mm_s * self.dt), abs(da) / (c.turn_deg_s * self.dt))
            if f <= 1e-12:
                self.i += 1
                continue
            g = min(1.0, 1.0 / f)
            y, a = self.y + g * dy, self.a + g * da
            # inside the bound by construction; clipped all the same (rounding)
            y = float(np.clip(y, -c.max_extent_mm, c.max_extent_mm))
            a = float(np.clip(a, -c.max_angle_deg, c.max_angle_deg))
            T = self.pose(y, a)
            if not self.reachable(T):
                self.refused += 1
                self.i += 1          # this leg ends here; on to the next vertex
                continue
            self.y, self.a = y, a
            self.extent = (max(self.extent[0], abs(y)), max(self.extent[1], abs(a)))
            if g >= 1.0:
                self.i += 1
            return T
        self._fail("the search pattern ended")
        return None
