"""Simulated laser-stripe sensor: the laser fan cut through the part, seen by the camera.

Physics kept: the fan leaves the projector and lights the first surface it meets; a lit point is
seen only if nothing of the part lies between it and the camera; points are projected with the
pinhole + OpenCV distortion model (``cv2.projectPoints`` is the reference); the stripe has a
Gaussian (or flat-top super-Gaussian) cross-section, brightness falling with incidence angle, and
speckle along it, as set by a :class:`~torchseam.core.config.StripeLook` (optionally split
into two parallel lobes, a laser diode lasing in two modes). :meth:`LaserSensor.arc_glint` is
the specular reflection of the arc on the main body (pipe, plate or sphere). Everything
geometric is done in the part frame {T}, through the :class:`~torchseam.core.part.Joint`
interface (every kind of part alike).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from torchseam.core.config import CellConfig, StripeLook
from torchseam.core.kernels import load_kernels
from torchseam.core.part import Joint
from torchseam.core.transforms import apply, invert

ARM_DISTANCE_MM = 5.0  # truth points on each stripe arm lie this far (3D) from the seam point
#: a groove's lit pieces (:meth:`LaserSensor._edges`): neighbouring hits farther apart than this
#: are on two pieces, and each piece's end is bisected this many times on the fan angle
EDGE_JUMP_MM = 1.0
EDGE_BISECT_STEPS = 20
SPLAT_STEP_PX = 0.25   # spacing of splatted samples along the imaged stripe
BLUR_MARGIN_PX = 16    # stripe box margin for the blur: > the Gaussian kernel's radius (7 px)
#: The stripe of the ``sim`` appearance family (``configs/noise.yaml``): a Gaussian
#: cross-section of sigma 1.8 px (about 0.35 mm on the part). The look of a stripe rendered
#: without a family, e.g. on the calibration board.
DEFAULT_STRIPE = StripeLook(sigma_px=1.8, order=1.0, peak=235.0, bgr=(0.18, 0.24, 1.0),
                            speckle=0.25, speckle_px=2.0, grain=0.12)
#: A split stripe (``StripeLook.split_px`` > 0): the second lobe's share of the light relative
#: to the first (the weaker mode of the diode).
SPLIT_SECOND_LOBE = 0.6
# Specular glint of the arc on the main pipe (:meth:`LaserSensor.arc_glint`), an anisotropic
# (Ward) lobe of steel ground round the pipe before welding: its slope spread along the pipe
# axis and across it (the grinding marks run round the pipe, so the glint spreads along the
# axis), distance (mm) from the arc at which the glint has half its brightness, evaluation grid
# step (px; bilinear in between), depth and spacing (mm) of the grinding marks that break it up.
GLINT_ROUGH_ALONG = 0.35
GLINT_ROUGH_ACROSS = 0.05
GLINT_HALF_MM = 60.0
GLINT_STEP_PX = 4
GLINT_MARK_DEPTH = 0.4
GLINT_MARK_MM = 2.0


@dataclass
class StripeView:
    """The stripe as the camera sees it in one frame.

    Attributes:
        uv: (N, 2) distorted pixel coordinates of the visible stripe samples, in fan order.
        brightness: (N,) relative brightness (incidence falloff) of each sample.
        surface: (N,) 1 main body (pipe, plate, sphere), 2 branch, 3 the exact seam point.
        seam_uv: (2,) pixel of the seam point (the weld feature point).
        seam_T: (3,) seam point in {T}.
        arm_T: (2, 3) points on the branch arm and the main arm, ``ARM_DISTANCE_MM`` from the
            seam.
        arm_uv: (2, 2) their pixels.
        visible: whether the seam point is lit, unoccluded and inside the image.
    """

    uv: np.ndarray
    brightness: np.ndarray
    surface: np.ndarray
    seam_uv: np.ndarray
    seam_T: np.ndarray
    arm_T: np.ndarray
    arm_uv: np.ndarray
    visible: bool


class LaserSensor:
    """Camera + line laser of ``cell``, looking at a :class:`~torchseam.core.part.Joint`.

    Example:
        >>> from torchseam.core.config import load_cell, load_part
        >>> sensor = LaserSensor(load_cell())
        >>> sensor.fan_rays
        1600
    """

    def __init__(self, cell: CellConfig, fan_rays: int = 1600, fan_half_angle_deg: float = 32.0):
        self.cell = cell
        self.K = cell.camera.K
        self.dist = np.asarray(cell.camera.dist, dtype=float)
        self.size = (cell.camera.width, cell.camera.height)
        self.fan_rays = fan_rays
        lp = cell.laser_plane
        self.n_C = np.asarray(lp.normal)
        self.d_C = float(lp.distance_mm)
        self.src_C = np.asarray(lp.source_mm)
        # Fan directions in {C}: centred on the direction from the source to the point of the
        # plane on the optical axis (what the sensor is aimed at).
        aim = np.array([0.0, 0.0, self.d_C / self.n_C[2]]) - self.src_C
        a = aim / np.linalg.norm(aim)
        b = np.cross(self.n_C, a)
        self._fan_ab = (a, b)
        self.psi = np.deg2rad(np.linspace(-fan_half_angle_deg, fan_half_angle_deg, fan_rays))
        self.fan_C = np.cos(self.psi)[:, None] * a + np.sin(self.psi)[:, None] * b
        w, h = self.size
        grain = np.random.default_rng(7).standard_normal(((h + 32) // 2, (w + 32) // 2))
        self._grain_field = cv2.resize(grain.astype(np.float32), (w + 32, h + 32))
        self._grains: dict[float, np.ndarray] = {}
        # the stripe's blurred box (reused: a fresh plane costs its page faults every frame)
        self._blur_plane = np.empty((h, w), np.float32)
        # the plane stripe_layer last drew into and the box of it that holds what it drew
        self._stripe_drawn: tuple[np.ndarray, slice, slice] | None = None
        self._glint_rays: np.ndarray | None = None
        k = load_kernels(__package__)  # compiled (or loaded) now, not on the first frame
        # the projection compiled where a probe finds it OpenCV's to the bit (else OpenCV)
        self._K = np.ascontiguousarray(self.K, dtype=np.float64)
        self._k14 = np.zeros(14)
        self._k14[:len(self.dist)] = self.dist
        self._project = k.project_points if _projection_agrees(
            k.project_points, self._K, self.dist, self._k14) else None

    # ---------------------------------------------------------------- projection
    def project(self, X_C: np.ndarray) -> np.ndarray:
        """(N, 3) points in {C} (mm) -> (N, 2) distorted pixels (OpenCV reference model)."""
        X = np.ascontiguousarray(X_C, dtype=np.float64).reshape(-1, 3)
        if not len(X):  # (OpenCV answers None to no points: a camera that sees no part)
            return np.zeros((0, 2))
        if self._project is not None:
            out = np.empty((len(X), 2))
            self._project(X, self._K, self._k14, out)
            return out
        uv, _ = cv2.projectPoints(X[:, None], np.zeros(3), np.zeros(3), self.K, self.dist)
        return uv.reshape(-1, 2)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        w, h = self.size
        return ((uv[..., 0] >= margin) & (uv[..., 0] <= w - 1 - margin)
                & (uv[..., 1] >= margin) & (uv[..., 1] <= h - 1 - margin))

    # ---------------------------------------------------------------- stripe geometry
    def view(self, joint: Joint, T_T_C: np.ndarray, phi_hint: float | None = None
             ) -> StripeView:
        """Stripe seen by a camera at pose ``T_T_C`` ({C} in {T}, 4x4 mm) on ``joint``."""
        R, c = T_T_C[:3, :3], T_T_C[:3, 3]
        src = apply(T_T_C, self.src_C)
        dirs = self.fan_C @ R.T
        t, surf_all = joint.raycast(src, dirs)
        hit = np.isfinite(t)
        psi = self.psi[hit]
        P = src + t[hit, None] * dirs[hit]
        surf = surf_all[hit]
        if not joint.seam_on_surface:  # a groove: its edges where they are, not at a ray
            psi, P, surf = self._edges(joint, src, R, t, surf_all, hit, psi, P)
            dirs, hit = self._fan_dirs(psi, R), np.ones(len(psi), bool)  # the kept rays
        n_T = R @ self.n_C
        d_T = self.d_C + n_T @ c

        try:
            seam_T = self._seam_in_plane(joint, n_T, d_T, c, phi_hint)
        except ValueError:  # the sensor looks off the seam altogether
            seam_T = np.full(3, np.nan)
        seam_ok = bool(np.all(np.isfinite(seam_T)))

        # Visibility from the camera: the first surface along the line of sight is the point.
        # The seam point's own line of sight goes in the same ray cast (one call instead of
        # two: the joint casts each ray on its own, so the numbers are those of two calls).
        los = P - c
        dist = np.linalg.norm(los, axis=1)
        rays = los / dist[:, None]
        if seam_ok:
            rays = np.concatenate([rays, ((seam_T - c) / np.linalg.norm(seam_T - c))[None]])
        t_cam, _ = joint.raycast(c, rays)
        seen = t_cam[:len(P)] >= dist - 1e-3
        X_C = (P - c) @ R  # {T} -> {C}
        seen &= X_C[:, 2] > 1.0

        # Brightness: Lambertian falloff with the laser's incidence angle.
        normals = np.where((surf == 1)[:, None], joint.normal_main(P), joint.normal_branch(P))
        inc = np.abs(np.einsum("ij,ij->i", normals, dirs[hit]))
        bright = 0.35 + 0.65 * inc

        seam_C = (seam_T - c) @ R
        # Insert the exact seam point where the fan passes from one surface to the other, so
        # the imaged corner is sharp (not where the seam is the middle of a root gap: no
        # surface holds it, the stripe breaks there).
        order_P, order_s, order_b, order_seen = P, surf, bright, seen
        jump = np.nonzero(surf[1:] != surf[:-1])[0]
        k_seam = None
        if len(jump) and joint.seam_on_surface:
            k = jump[np.argmin(np.linalg.norm(P[jump] - seam_T, axis=1))] + 1
            if np.linalg.norm(P[k] - seam_T) < 2.0:
                k_seam = k
                # (np.insert's values, without its overhead)
                order_P = np.concatenate([P[:k], seam_T[None], P[k:]])
                order_s = np.concatenate([surf[:k], np.array([3], surf.dtype), surf[k:]])
                order_b = np.concatenate([bright[:k], [0.5 * (bright[k - 1] + bright[k])],
                                          bright[k:]])
        a_T, b_T = R @ self._fan_ab[0], R @ self._fan_ab[1]

        def lit(angle: np.ndarray) -> np.ndarray:
            """(N,) fan angles -> (N, 3) lit points."""
            d = np.cos(angle)[:, None] * a_T + np.sin(angle)[:, None] * b_T
            return src + joint.raycast(src, d)[0][:, None] * d

        arm_T = self._arm_points(P, surf, psi, seam_T, lit)
        # the stripe, the seam point and the arm points projected in one call (each point on
        # its own)
        X_order = (order_P - c) @ R
        n = len(X_order)
        extra = [seam_C[None], (arm_T - c) @ R] if seam_ok else [(arm_T - c) @ R]
        projected = self.project(np.concatenate([X_order, *extra]))
        uv, arm_uv = projected[:n], projected[-2:]
        if seam_ok:
            seam_uv = projected[n]
            t_seam = t_cam[len(P):]
            # The seam lies on both surfaces: its line of sight may graze one of them.
            visible = bool(t_seam[0] >= np.linalg.norm(seam_T - c) - 0.05
                           and self.in_image(seam_uv) and seam_C[2] > 1.0)
        else:
            seam_uv, visible = np.full(2, np.nan), False
        if k_seam is not None:
            order_seen = np.concatenate([seen[:k_seam], [visible], seen[k_seam:]])
        keep = order_seen & self.in_image(uv, margin=-20.0)
        return StripeView(uv[keep], order_b[keep], order_s[keep], seam_uv, seam_T, arm_T,
                          arm_uv, visible)

    def _fan_dirs(self, psi: np.ndarray, R: np.ndarray) -> np.ndarray:
        """(N, 3) fan directions in {T} at fan angles ``psi`` for a camera turned by ``R``."""
        a, b = self._fan_ab
        return (np.cos(psi)[:, None] * a + np.sin(psi)[:, None] * b) @ R.T

    def _edges(self, joint: Joint, src: np.ndarray, R: np.ndarray, t: np.ndarray,
               surf_all: np.ndarray, hit: np.ndarray, psi: np.ndarray, P: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The lit points with the exact ends of each lit piece added: where the fan passes
        from one ray to the next across an edge (a hit then a miss, as at a root gap whose
        light goes into the bore, or a jump of more than ``EDGE_JUMP_MM``), the fan angle of
        the edge is bisected (``EDGE_BISECT_STEPS``) from the ray on the lit side: the piece
        continues while a ray hits the same surface near the line of the last two hits. The
        rays are ~0.2 mm apart on a face lit at 22 degrees, so a piece drawn to its last ray
        ended ~1.4 px short of the edge on average. Returns (psi, P, surface), in fan order."""
        idx = np.flatnonzero(hit)
        n = len(self.psi)
        surf_hit = surf_all[idx]
        # anchors (lit ray j, its neighbour ray nb, the previous lit ray back), in the order
        # of j, the neighbour after it first: each lit ray whose neighbour on one side is lost
        # (a miss, another surface, or a jump) while the one on its other side is lit
        m = len(idx)
        js_all = np.arange(m)
        cand = []
        for rank, step in ((0, 1), (1, -1)):
            nb = idx + step
            back = js_all - step
            ok = (nb >= 0) & (nb < n) & (back >= 0) & (back < m)
            bk = np.clip(back, 0, max(m - 1, 0))
            ok &= np.abs(idx[bk] - idx) == 1   # a lit neighbour on the other side
            nbc = np.clip(nb, 0, n - 1)
            gone = ~hit[nbc] | (surf_all[nbc] != surf_hit)
            k = np.clip(js_all + step, 0, max(m - 1, 0))   # nb's place among the lit rays
            jump = np.linalg.norm(P[k] - P, axis=1) > EDGE_JUMP_MM
            gone |= jump
            sel = np.flatnonzero(ok & gone)
            cand.append((2 * sel + rank, sel, nb[sel], back[sel]))
        key = np.concatenate([c[0] for c in cand])
        if not len(key):
            return psi, P, surf_hit
        order_ = np.argsort(key, kind="stable")
        js = np.concatenate([c[1] for c in cand])[order_]
        lo = self.psi[idx[js]]
        hi = self.psi[np.concatenate([c[2] for c in cand])[order_]]
        p0, p_back = P[js], P[np.concatenate([c[3] for c in cand])[order_]]
        sid = surf_hit[js]
        step = np.linalg.norm(p0 - p_back, axis=1)
        line = (p0 - p_back) / np.maximum(step, 1e-12)[:, None]
        for _ in range(EDGE_BISECT_STEPS):
            mid = 0.5 * (lo + hi)
            d = self._fan_dirs(mid, R)
            tm, sm = joint.raycast(src, d)
            q = src + np.where(np.isfinite(tm), tm, 0.0)[:, None] * d
            off = q - p0
            along = np.einsum("ij,ij->i", off, line)
            across = np.linalg.norm(off - along[:, None] * line, axis=1)
            same = (np.isfinite(tm) & (sm == sid) & (along > 0) & (along < 2.0 * step + 0.05)
                    & (across < 0.25 * step + 1e-3))
            lo, hi = np.where(same, mid, lo), np.where(same, hi, mid)
        d = self._fan_dirs(lo, R)
        te, se = joint.raycast(src, d)
        ok = np.isfinite(te) & (se == sid)
        e_psi = lo[ok]
        e_P = src + te[ok, None] * d[ok]
        psi_all = np.concatenate([psi, e_psi])
        order = np.argsort(psi_all, kind="stable")
        return (psi_all[order], np.concatenate([P, e_P])[order],
                np.concatenate([surf_hit, se[ok]])[order])

    @staticmethod
    def _seam_in_plane(joint: Joint, n: np.ndarray, d: float, c: np.ndarray,
                       phi_hint: float | None) -> np.ndarray:
        """Where the seam crosses the laser plane: the crossing nearest ``phi_hint`` (or, with
        no hint, the camera)."""
        phi, grid = _seam_grid(joint)
        f = grid @ n - d
        idx = np.nonzero(np.sign(f[1:]) != np.sign(f[:-1]))[0]
        if len(idx) == 0:
            raise ValueError("the laser plane does not cross the seam")
        mid = 0.5 * (phi[idx] + phi[idx + 1])
        if phi_hint is not None:
            off = mid - phi_hint
            i = idx[np.argmin(np.abs(np.angle(np.exp(1j * off)) if joint.closed else off))]
        else:
            i = idx[np.argmin(np.linalg.norm(joint.seam_point(mid) - c, axis=1))]
        root = _refine_root(lambda x: joint.seam_point(x) @ n - d, phi[i], phi[i + 1])
        return joint.seam_point(np.array([root]))[0]

    @staticmethod
    def _arm_points(P: np.ndarray, surf: np.ndarray, psi: np.ndarray, seam: np.ndarray,
                    lit) -> np.ndarray:
        """Lit points on the branch arm and the main arm exactly ``ARM_DISTANCE_MM`` from the
        seam: bracketed between fan samples, then solved for the fan angle."""
        out = np.full((2, 3), np.nan)
        dist = np.linalg.norm(P - seam, axis=1) - ARM_DISTANCE_MM
        arms, brackets = [], []
        for j, sid in enumerate((2, 1)):
            k = np.nonzero((surf[:-1] == sid) & (surf[1:] == sid)
                           & (np.sign(dist[:-1]) != np.sign(dist[1:])))[0]
            if len(k) == 0:
                continue
            k = k[np.argmin(np.abs(P[k] - seam).sum(axis=1))]
            arms.append(j)
            brackets.append((psi[k], psi[k + 1]))
        if arms:
            # both arms' roots in lockstep: one ray cast per round for the two (each ray is
            # cast on its own, so each root is the one a search of its own finds)
            ang = _refine_roots(
                lambda a: np.linalg.norm(lit(a) - seam, axis=1) - ARM_DISTANCE_MM, brackets)
            out[arms] = lit(np.array(ang))
        return out

    # ---------------------------------------------------------------- rendering
    def grain(self, depth: float) -> np.ndarray:
        """Float32 (H + 32, W + 32) fixed surface grain ``1 + depth * field`` (kept per depth)."""
        g = self._grains.get(depth)
        if g is None:
            g = self._grains[depth] = 1.0 + depth * self._grain_field
        return g

    def stripe_layer(self, view: StripeView, rng: np.random.Generator,
                     gaps: list[tuple[float, float]] | None = None,
                     look: StripeLook | None = None, out: np.ndarray | None = None
                     ) -> np.ndarray:
        """Float32 (H, W) red-channel stripe intensity, speckled, with optional dropouts.

        ``gaps`` are (start, end) arc-length ranges in pixels along the imaged stripe, measured
        from the feature point (negative: towards the first arm) where the stripe is missing.
        ``look`` sets the cross-section, peak and speckle (default :data:`DEFAULT_STRIPE`).
        A cross-section of order p > 1 is the super-Gaussian ``exp(-(x^2 / 2 sigma^2)^p)``:
        flat-topped, with steeper flanks than the Gaussian of the same sigma. A ``split_px`` > 0
        draws that cross-section twice, ``split_px`` apart across the stripe on either side of
        the fan's mid-plane (where the labels are), the second lobe weaker
        (:data:`SPLIT_SECOND_LOBE`); the light of the stripe is shared between them.
        ``out``: a C-contiguous float32 (H, W) plane to draw into (zeroed first) and return,
        instead of a new one. The same plane again: only the box this drew into last time is
        zeroed (the caller keeps the rest of it zero; scaling it keeps it so).
        """
        look = DEFAULT_STRIPE if look is None else look
        w, h = self.size
        uv = view.uv
        if out is not None:
            last = self._stripe_drawn
            if last is not None and _same_plane(last[0], out):
                out[last[1], last[2]] = 0.0
            else:
                out.fill(0.0)
            # (the whole plane until this call has drawn, should it fail half way)
            self._stripe_drawn = (out, slice(None), slice(None))
        if len(uv) < 2:
            if out is None:
                return np.zeros((h, w), np.float32)
            self._stripe_drawn = (out, slice(0, 0), slice(0, 0))   # nothing drawn
            return out
        # Samples every SPLAT_STEP_PX along the polyline, weighted by the brightness and the
        # arc length per sample. Do not bridge real gaps (occlusion, fan ends): consecutive
        # samples must be close (compiled: torchseam.sim._kernels.stripe_samples)
        pts, step, weight, starts = load_kernels(__package__).stripe_samples(
            np.ascontiguousarray(uv, dtype=np.float64),
            np.ascontiguousarray(view.brightness, dtype=np.float64), SPLAT_STEP_PX, 6.0)
        # speckle: smooth log-normal modulation along the stripe (mean about 1)
        stride = look.speckle_px / SPLAT_STEP_PX
        sp = rng.standard_normal(int(len(pts) // stride) + 2)
        sp = np.interp(np.arange(len(pts)) / stride, np.arange(len(sp)), sp)
        weight = weight * np.exp(look.speckle * sp - 0.48 * look.speckle**2)
        if gaps:
            arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
            k0 = int(np.argmin(np.linalg.norm(pts - view.seam_uv, axis=1)))
            arc = arc - arc[k0]
            for a0, a1 in gaps:
                weight[(arc >= a0) & (arc <= a1)] *= 0.04
        unit = step
        if look.split_px > 0:
            seg = np.diff(uv, axis=0)
            seg_len = np.linalg.norm(seg, axis=1)
            pts, weight, unit = _split(pts, weight, step, seg[starts], seg_len[starts],
                                       look.split_px)
        img, box = _splat(pts, weight, w, h, out)
        # grainy laser speckle on the surface: a random crop of a fixed speckle field
        dy, dx = rng.integers(0, 32, 2)
        if box is None:   # no point in the image: nothing drawn
            if out is not None:
                self._stripe_drawn = (out, slice(0, 0), slice(0, 0))
            return img
        # Blur, scale and speckle only where the stripe is (its bounding box plus more than
        # the kernel's reach): everything outside is zero before and after, and inside the
        # box the filter sees the same pixels, so the result is the full-frame one.
        sigma = look.sigma_px
        m = max(BLUR_MARGIN_PX, int(4 * sigma) + 2)
        x0, y0, x1, y1 = box
        ys, xs = slice(max(0, y0 - m), min(h, y1 + m)), slice(max(0, x0 - m), min(w, x1 + m))
        sub = cv2.GaussianBlur(img[ys, xs], (0, 0), sigma,
                               dst=self._blur_plane[:ys.stop - ys.start, :xs.stop - xs.start])
        if look.order != 1.0:
            sub = _super_gaussian(sub, _splat(pts, unit, w, h)[0][ys, xs], sigma, look.order)
        sub *= look.peak * np.sqrt(2 * np.pi) * sigma
        sub *= self.grain(look.grain)[dy:dy + h, dx:dx + w][ys, xs]
        img[ys, xs] = sub
        if out is not None:
            self._stripe_drawn = (out, ys, xs)
        return img

    def arc_glint(self, joint: Joint, T_T_C: np.ndarray, light_T: np.ndarray) -> np.ndarray:
        """Float32 (H, W) specular glint of a point light (the arc) at ``light_T`` ({T}, mm)
        on the main body, about [0, 1]: an anisotropic lobe, sharp across the pipe and spread
        along it (along x of {T} on a plate or sphere: the direction of the grinding marks),
        on the pixels that see the main body where the light reaches it, fading with
        the distance from the light and broken by the grinding marks. On the cylinder it is a
        band along the pipe from the arc outwards. Evaluated every ``GLINT_STEP_PX`` pixels
        and interpolated."""
        w, h = self.size
        rays = self._glint_grid()
        R, c = T_T_C[:3, :3], T_T_C[:3, 3]
        d = rays @ R.T
        t, surf = joint.raycast(c, d)
        out = np.zeros(len(d))
        idx = np.nonzero(surf == 1)[0]
        if len(idx):
            P = c + t[idx, None] * d[idx]
            n = joint.normal_main(P)
            to_l = light_T - P
            dist = np.linalg.norm(to_l, axis=1)
            to_l /= np.maximum(dist, 1e-9)[:, None]
            half = to_l - d[idx]
            half /= np.maximum(np.linalg.norm(half, axis=1), 1e-12)[:, None]
            # half vector in the surface frame: along the axis (x of {T}), round the pipe, normal
            hn = np.maximum(np.einsum("ij,ij->i", n, half), 1e-3)
            ha = half[:, 0]
            hr = n[:, 1] * half[:, 2] - n[:, 2] * half[:, 1]
            if np.any(n[:, 0]):  # a surface not parallel to x (a sphere): x along the surface
                across = np.sqrt(np.maximum(1.0 - n[:, 0] ** 2, 1e-6))
                ha = (ha - n[:, 0] * np.einsum("ij,ij->i", n, half)) / across
                hr = hr / across
            lobe = np.exp(-((ha / GLINT_ROUGH_ALONG) ** 2 + (hr / GLINT_ROUGH_ACROSS) ** 2)
                          / hn**2)
            lit = np.einsum("ij,ij->i", n, to_l) > 0.0
            # the light must reach the point (the branch shadows the far side)
            k = np.nonzero(lit & (lobe > 1e-4))[0]
            t_l, _ = joint.raycast(P[k] + 0.5 * n[k], to_l[k])
            reach = np.zeros(len(idx), bool)
            reach[k] = t_l >= dist[k] - 1.0
            val = lobe / (1.0 + (dist / GLINT_HALF_MM) ** 2) * _grinding_marks(P[:, 0])
            out[idx] = np.where(reach, val, 0.0)
        s = GLINT_STEP_PX
        gw, gh = -(-w // s), -(-h // s)
        img = cv2.resize(out.reshape(gh, gw).astype(np.float32), (gw * s, gh * s),
                         interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(img[:h, :w])

    def _glint_grid(self) -> np.ndarray:
        """(N, 3) unit rays in {C} through the centres of ``GLINT_STEP_PX`` pixel cells (the
        points ``cv2.resize`` interpolates between), row by row; computed once."""
        if self._glint_rays is None:
            w, h = self.size
            s = GLINT_STEP_PX
            u = np.arange(-(-w // s)) * s + (s - 1) / 2
            v = np.arange(-(-h // s)) * s + (s - 1) / 2
            uv = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 1, 2)
            xy = cv2.undistortPoints(uv, self.K, self.dist).reshape(-1, 2)
            r = np.c_[xy, np.ones(len(xy))]
            self._glint_rays = r / np.linalg.norm(r, axis=1, keepdims=True)
        return self._glint_rays


_MARKS = np.random.default_rng(11).standard_normal(4096)


def _grinding_marks(x_mm: np.ndarray) -> np.ndarray:
    """(N,) reflectance of the grinding marks round the main pipe at axial positions ``x_mm``:
    a fixed smooth random profile along the axis (mean about 1)."""
    prof = np.interp(x_mm / GLINT_MARK_MM, np.arange(len(_MARKS)), _MARKS, period=len(_MARKS))
    return np.clip(1.0 + GLINT_MARK_DEPTH * prof, 0.0, None)


def _split(pts: np.ndarray, weight: np.ndarray, step: np.ndarray, seg: np.ndarray,
           seg_len: np.ndarray, split_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The splat samples of a stripe split into two parallel lobes ``split_px`` apart across
    it (along each sample's segment normal), the second :data:`SPLIT_SECOND_LOBE` as bright
    as the first. Returns the points, their weights and their unit weights (``step`` per
    lobe, for the super-Gaussian profile)."""
    along = seg / np.maximum(seg_len, 1e-9)[:, None]
    off = 0.5 * split_px * np.stack([-along[:, 1], along[:, 0]], axis=1)
    a = 1.0 / (1.0 + SPLIT_SECOND_LOBE)
    return (np.concatenate([pts + off, pts - off]),
            np.concatenate([a * weight, (1.0 - a) * weight]), np.concatenate([step, step]))


def _super_gaussian(blurred: np.ndarray, unit: np.ndarray, sigma: float, order: float
                    ) -> np.ndarray:
    """Reshape a Gaussian-blurred stripe into a super-Gaussian cross-section of ``order``.

    ``unit`` is the same stripe splatted with unit brightness: blurred and normalised it is
    the Gaussian cross-section g in (0, 1] (1 on the line), so the stripe is
    ``blurred / g * exp(-(-ln g)^order)``: the brightness along the stripe times the new profile.
    Where two arms overlap (g > 1) the profile is 1.
    """
    g = cv2.GaussianBlur(unit, (0, 0), sigma)
    g *= np.sqrt(2 * np.pi) * sigma
    q = -np.log(np.maximum(g, 1e-30))
    np.maximum(q, 0.0, out=q)
    prof = np.exp(-(q**order))
    out = np.divide(blurred, g, out=np.zeros_like(blurred), where=g > 1e-12)
    out *= prof
    return out


_GRID_PHI = np.linspace(0.0, 2 * np.pi, 721)


def _seam_grid(joint: Joint) -> tuple[np.ndarray, np.ndarray]:
    """The seam sampled every half degree of its parameter over its span (a ring: (721,)
    angles and (721, 3) points; an open seam: its tabs included), computed once per joint (a
    joint does not change) and kept on it."""
    got = _SEAM_GRIDS.get(joint)
    if got is None:
        lo, hi = joint.phi_span()
        phi = _GRID_PHI if (lo, hi) == (0.0, 2 * np.pi) else np.linspace(
            lo, hi, int(np.ceil((hi - lo) / (_GRID_PHI[1] - _GRID_PHI[0]))) + 1)
        grid = joint.seam(phi).point
        grid.setflags(write=False)
        got = _SEAM_GRIDS[joint] = (phi, grid)
    return got


#: :func:`_seam_grid`'s cache: joint -> its seam grid, kept while the joint lives
_SEAM_GRIDS: weakref.WeakKeyDictionary[Joint, tuple[np.ndarray, np.ndarray]] = \
    weakref.WeakKeyDictionary()


def _same_plane(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether ``a`` and ``b`` are views of the same pixels (a caller's buffer indexed
    afresh each frame gives a new view object of it; ``a`` is kept alive, so its memory is
    not another array's)."""
    return a is b or (a.ctypes.data == b.ctypes.data and a.shape == b.shape
                      and a.strides == b.strides)


def _projection_agrees(project, K: np.ndarray, dist: np.ndarray, k14: np.ndarray) -> bool:
    """Whether the compiled ``project`` (``_kernels.project_points``) gives
    ``cv2.projectPoints``'s pixels to the bit for this camera, on probe points over its view
    (in front of it, behind it, at depth zero, far off the axis): checked once per sensor,
    so another OpenCV build's arithmetic falls back to OpenCV."""
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-300.0, 300.0, (4000, 2)), rng.uniform(-50.0, 400.0, 4000)]
    X[::50, 2] = 0.0
    ref = cv2.projectPoints(X[:, None], np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)
    got = np.empty_like(ref)
    project(X, K, k14, got)
    return bool(np.array_equal(ref, got, equal_nan=True))


def _refine_root(f, lo: float, hi: float, n: int = 33, rounds: int = 4) -> float:
    """Root of a vectorised ``f`` bracketed in [lo, hi]: ``rounds`` of n-way subdivision, then
    linear interpolation (about 1e-12 of the bracket; one vector call per round)."""
    return _refine_roots(f, [(lo, hi)], n, rounds)[0]


def _refine_roots(f, brackets: list[tuple[float, float]], n: int = 33, rounds: int = 4
                  ) -> list[float]:
    """:func:`_refine_root` for several brackets at once, in lockstep: each round evaluates
    ``f`` once on the subdivisions of every bracket still being narrowed (an element-wise
    ``f``, so each root is the one its own search finds, to the bit), the final interpolation
    once on every bracket's ends."""
    br = [(lo, hi) for lo, hi in brackets]
    # f at each bracket's ends, once evaluated: a subdivision's first and last points are
    # its bracket's ends (np.linspace), and f is element-wise, so the final interpolation
    # takes the values the rounds computed instead of evaluating f there again
    f_ends: list[tuple[float, float] | None] = [None] * len(br)
    active = list(range(len(br)))
    for _ in range(rounds):
        if not active:
            break
        xs = [np.linspace(*br[i], n) for i in active]
        y = f(np.concatenate(xs))
        still = []
        for m, i in enumerate(active):
            ym, x = y[m * n:(m + 1) * n], xs[m]
            k = np.nonzero(np.sign(ym[1:]) != np.sign(ym[:-1]))[0]
            if len(k):
                br[i] = (x[k[0]], x[k[0] + 1])
                f_ends[i] = (ym[k[0]], ym[k[0] + 1])
                still.append(i)
            elif x[0] == br[i][0] and x[-1] == br[i][1]:
                f_ends[i] = (ym[0], ym[-1])
        active = still
    todo = [i for i, e in enumerate(f_ends) if e is None]
    if todo:
        ends = f(np.array([v for i in todo for v in br[i]]))
        for j, i in enumerate(todo):
            f_ends[i] = (ends[2 * j], ends[2 * j + 1])
    out = []
    for (lo, hi), e in zip(br, f_ends, strict=True):
        assert e is not None
        ylo, yhi = e
        out.append(float(lo - ylo * (hi - lo) / (yhi - ylo)) if yhi != ylo else float(lo))
    return out


def _splat(pts: np.ndarray, weight: np.ndarray, w: int, h: int, out: np.ndarray | None = None
           ) -> tuple[np.ndarray, tuple[int, int, int, int] | None]:
    """Bilinear splat of weighted points into a float32 (h, w) image (keeps the centroid):
    ``out`` (all zeros, C-contiguous) or a new one.

    Returns the image and the box ``(x0, y0, x1, y1)`` (end-exclusive, inside the image)
    that holds every non-zero pixel, or None when nothing landed in the image.
    """
    img = np.zeros((h, w), np.float32) if out is None else out
    # compiled (torchseam.sim._kernels.splat): the four corners' np.bincount sums of the
    # points in the image, in a box around them, cast into the image: the same numbers
    box = load_kernels(__package__).splat(np.ascontiguousarray(pts, dtype=np.float64),
                                          np.ascontiguousarray(weight, dtype=np.float64), img)
    if box[0] < 0:
        return img, None
    return img, (int(box[0]), int(box[1]), int(box[2]), int(box[3]))


def camera_pose(cell: CellConfig, T_B_W: np.ndarray) -> np.ndarray:
    """Camera pose in {B} for a torch TCP pose ``T_B_W``: T_B_C = T_B_W inv(tool) hand_eye."""
    return T_B_W @ invert(cell.tool.matrix()) @ cell.hand_eye.matrix()
