"""Geometry of the part: a branch pipe set on a main body, their seam, ray casting, torch frames.

The part's geometry is no simulator's: the simulated sensor and scene (:mod:`torchseam.sim`),
the planner and the reachability gate all build it from the part's config
(:class:`~torchseam.core.config.PartConfig`) with :func:`make_joint`, and the ideal torch frames
along its seam with :func:`torch_frames`. :mod:`torchseam.sim.joint` re-exports this module.

Every kind of part (``kind:`` in ``configs/parts/*.yaml``) is a branch pipe set on a main body:

* ``pipe``: the main pipe of METHOD.md section 0, a cylinder along x (:class:`PipeJoint`);
* ``offset``: the same with the branch axis ``design_offset_mm`` off the main axis by design
  (:class:`PipeJoint` with a design offset);
* ``plate``: a flat plate, its top face the plane z = 0 (:class:`PlateJoint`);
* ``sphere``: a sphere, a nozzle on a spherical head (:class:`SphereJoint`);
* ``inline``: a pipe of the branch's own size on the branch's axis, a girth joint: a butt with
  a root gap, or a lap under a sleeve (:class:`InlineJoint`).

One kind is no branch pipe: ``coupon``, two flat plates butted along a straight seam
(:class:`CouponJoint`). Its seam is **open** (:attr:`Joint.closed` False): it has two ends, the
plates run on past them (the run-on and run-off tabs), the positioner does not turn it, and
``phi`` is then its seam parameter, proportional to the length along the seam (0 and 2 pi at the
weld's two ends, beyond them on the tabs). :func:`seam_interp` maps between the seam parameter
and the arc length for both: round a closed ring, straight on past an open seam's ends.

Joint frame {T}: z up the branch (at the intersection angle ``beta`` from x in the x-z plane);
the origin is on the branch axis: on the main axis under the branch axis (pipe), at the foot of
the common perpendicular of the two axes (offset: the main axis runs along x at
``y = -design_offset_mm``), on the plate (plate), at the sphere's centre (sphere; a hillside
nozzle's ``design_offset_mm`` puts the centre at ``y = -design_offset_mm``). The branch may be
oval (``branch_ovality``: semi-axes ``r (1 + e)`` along ``e1`` and ``r (1 - e)`` along ``e2``),
and offset (``branch_offset_mm``) from the design. For a branch point at angle ``phi`` the
height along the branch axis where it meets the main body has a closed form for every kind
(:meth:`Joint.seam`): an ellipse equation (pipe), a plane (plate), a quadratic (sphere).

All kinds share one interface (:class:`Joint`): ``seam(phi)`` (points, tangents, both surface
normals), ``normal_main`` / ``normal_branch``, ``raycast`` (first hit of the solid union, surface
id 1 main body, 2 branch), ``arc_length_table``; the sensor, the scene, the planner and the
reachability gate use nothing else (the gate's clearance solids also read ``main_solid``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from types import ModuleType

import numpy as np

from torchseam.core.config import PartConfig
from torchseam.core.kernels import load_kernels
from torchseam.core.transforms import rotation_about

BRANCH_LENGTH_MM = 400.0  # how far the branch pipe extends above the main axis (pipe kinds)
#: Plate and sphere kinds: how far the branch extends above the highest point of its seam.
NOZZLE_ABOVE_SEAM_MM = 300.0
#: The plate kind: half the side of the square plate (centred under the branch) and its
#: thickness (below z = 0), mm.
PLATE_HALF_MM = 300.0
PLATE_THICKNESS_MM = 20.0


@dataclass(frozen=True)
class SeamSample:
    """Seam points and local geometry at branch angles ``phi``; all arrays (N, 3) in {T}."""

    phi: np.ndarray
    point: np.ndarray
    tangent: np.ndarray        # unit, direction of increasing phi
    normal_main: np.ndarray    # outward unit normal of the main body (pipe, plate or sphere)
    normal_branch: np.ndarray  # outward unit normal of the branch


class Joint:
    """A branch pipe (oval, offset, tilted) set on a main body, as solids in {T}.

    Subclasses give the main body: :meth:`_height` (where a branch generator meets it, with
    its derivative), :meth:`normal_main`, :meth:`main_solid` and :meth:`_main_body` (its kind
    and parameters for the compiled ray cast, :mod:`torchseam.core._kernels`).

    Attributes:
        kind: the part kind (``configs/parts/*.yaml`` ``kind:``).
        r: branch radius; ``k1``, ``k2`` its ovality factors along ``e1`` and ``e2``.
        d, e1, e2: branch axis and the two directions across it (e2 = y).
        o: a point of the branch axis (the true part's branch offset; the origin by design).
        branch_bottom, branch_top: where the branch solid starts and ends along its axis,
            measured from ``o`` (below the main body's surface and the branch's top end).
    """

    kind = "pipe"
    main_name = "main pipe"   # what the main body is called in messages
    #: the seam is a ring (phi wraps round); False for an open seam (:class:`CouponJoint`)
    closed = True
    #: the seam lies on both surfaces (a fillet's corner); False where the seam point is the
    #: middle of a root gap (:class:`BevelledJoint`), which no surface holds
    seam_on_surface = True
    _cast_geometry: np.ndarray | None = None   # the compiled casts' (made on the first cast)

    def __init__(self, part: PartConfig) -> None:
        self.kind = part.kind
        self.r = part.branch_od_mm / 2.0
        self.k1 = 1.0 + part.branch_ovality
        self.k2 = 1.0 - part.branch_ovality
        beta = np.deg2rad(part.intersection_angle_deg)
        self.d = np.array([np.cos(beta), 0.0, np.sin(beta)])      # branch axis
        self.e2 = np.array([0.0, 1.0, 0.0])
        self.e1 = np.cross(self.e2, self.d)                        # (sin b, 0, -cos b)
        self.o = np.array([part.branch_offset_mm[0], part.branch_offset_mm[1], 0.0])
        self.s = float(part.design_offset_mm)  # the main body's centre sits at y = -s
        # semi-axis directions scaled by the ovality (exactly e1, e2 for a round branch)
        self._f1, self._f2 = self.k1 * self.e1, self.k2 * self.e2
        # maps a vector across the branch to the round branch's (u / k1, v / k2) and the oval's
        # gradient (u / k1^2, v / k2^2); both exactly the identity for a round branch
        self._un = (1.0 / self.k1 - 1.0, 1.0 / self.k2 - 1.0)
        self._grad = (1.0 / self.k1**2 - 1.0, 1.0 / self.k2**2 - 1.0)
        self.branch_bottom = 0.0
        self.branch_top = BRANCH_LENGTH_MM

    # ------------------------------------------------------------------ seam
    def branch_point(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) points of the branch surface at angles ``phi`` in the plane through ``o``
        across the axis, and their derivatives in ``phi``."""
        c = self.o + self.r * (np.cos(phi)[:, None] * self._f1 + np.sin(phi)[:, None] * self._f2)
        dc = self.r * (-np.sin(phi)[:, None] * self._f1 + np.cos(phi)[:, None] * self._f2)
        return c, dc

    def seam(self, phi: np.ndarray) -> SeamSample:
        """Seam at branch angles ``phi`` (N,) rad, with tangent and both surface normals."""
        phi = np.asarray(phi, dtype=float).reshape(-1)
        c, dc = self.branch_point(phi)
        h, dh = self._height(c, dc)
        p = c + h[:, None] * self.d
        t = dc + dh[:, None] * self.d
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return SeamSample(phi, p, t, self.normal_main(p), self.normal_branch(p))

    def seam_point(self, phi: np.ndarray) -> np.ndarray:
        """(N, 3) seam points at branch angles ``phi`` (N,) rad: ``seam(phi).point`` (the
        same numbers) without the tangent and the normals, for root searches along the seam."""
        phi = np.asarray(phi, dtype=float).reshape(-1)
        c, dc = self.branch_point(phi)
        h, _ = self._height(c, dc)
        return c + h[:, None] * self.d

    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Height ``h`` along the branch axis where the generator through ``c`` meets the main
        body's surface, and ``dh / dphi`` (from ``dc = dc / dphi``)."""
        raise NotImplementedError

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) outward unit normals of the main body's surface at its points ``p``."""
        raise NotImplementedError

    def normal_branch(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) outward unit normals of the branch at its surface points ``p``."""
        q = p - self.o
        n = q - (q @ self.d)[:, None] * self.d
        n = self._across(n, self._grad)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def _polar(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(radius of the round branch, angle phi, height along the axis) of points (N, 3)."""
        q = p - self.o
        a = q @ self.d
        u = (q @ self.e1) / self.k1
        v = (q @ self.e2) / self.k2
        return np.hypot(u, v), np.arctan2(v, u), a

    def _across(self, v: np.ndarray, c: tuple[float, float]) -> np.ndarray:
        """``v`` (N, 3, across the axis) with its e1 and e2 parts scaled by 1 + c (``v`` itself
        for c = 0: a round branch)."""
        if c == (0.0, 0.0):
            return v
        return (v + c[0] * (v @ self.e1)[:, None] * self.e1
                + c[1] * (v @ self.e2)[:, None] * self.e2)

    def phi_span(self) -> tuple[float, float]:
        """The seam parameter's range over the part: the ring's [0, 2 pi] (an open seam: its
        tabs included)."""
        return 0.0, 2.0 * np.pi

    def dense_seam(self, n: int = 20001) -> SeamSample:
        """The seam sampled densely for distance look-ups: ``n`` points round a ring (an open
        seam: as densely, over its span, tabs included: the line runs on past its ends)."""
        lo, hi = self.phi_span()
        if self.closed:
            return self.seam(np.linspace(lo, hi, n))
        return self.seam(np.linspace(lo, hi, int((n - 1) * (hi - lo) / (2 * np.pi)) + 1))

    def phi_near(self, p: np.ndarray) -> float:
        """The seam parameter nearest a point ``p`` (3,) in {T} (roughly: a hint where to look
        for the seam): its angle about the branch axis."""
        return float(np.arctan2(p[1], p[0]))

    def arc_length_table(self, n: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """(phi, s): cumulative seam arc length (mm) over phi in [0, 2 pi], n + 1 samples."""
        phi = np.linspace(0.0, 2.0 * np.pi, n + 1)
        p = self.seam(phi).point
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        return phi, s

    def main_solid(self) -> dict:
        """The main body for clearance checks: ``{"kind": "pipe" | "plate" | "sphere",
        "origin": (3,) in {T}, "rotation": (3, 3) its own axes in {T}, ...}`` with its
        dimensions (see the subclasses)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ ray casting
    def raycast(self, origin: np.ndarray, direction: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays with the solid union of the main body and the branch.

        Args:
            origin: (N, 3) or (3,) ray origins in {T}, outside the solid.
            direction: (N, 3) unit directions.

        Returns:
            ``(t, surface)``: (N,) distance along each ray (``inf`` for a miss) and (N,) int8
            surface id (0 none, 1 main body, 2 branch).
        """
        d = np.ascontiguousarray(direction, dtype=float).reshape(-1, 3)
        o = np.ascontiguousarray(origin, dtype=float).reshape(-1, 3)
        if len(o) not in (1, len(d)):
            raise ValueError(f"raycast: {len(o)} origins for {len(d)} rays")
        return self._cast(o, d)

    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`raycast` of (N, 3) or (1, 3) origins ``o`` and (N, 3) directions ``d``, both
        C-contiguous: compiled (:func:`torchseam.core._kernels.raycast`), its kernels loaded
        on the first cast (commands that never cast need not load numba)."""
        k = load_kernels(__package__)
        return k.raycast(o, d, self._geometry(k), self._main_body(k)[0])

    def _geometry(self, k: ModuleType) -> np.ndarray:
        """The joint's geometry for the compiled ray casts (``k``: :mod:`torchseam.core._kernels`,
        whose docstring gives the layout), made on the first cast."""
        if self._cast_geometry is None:
            g = np.concatenate([self.o, self.d, self.e1, self.e2, self._f1, self._f2,
                                self._branch_shape(), self._main_body(k)[1]])
            assert g.shape == (k.GEOMETRY_SIZE,)
            self._cast_geometry = g
        return self._cast_geometry

    def _branch_shape(self) -> list[float]:
        """The branch for the compiled ray casts: ``k1, k2, r, r_in``, the root gap, tan of the
        bevel angle, its bottom and top (a plain branch: ``r_in = r``, no gap, no bevel)."""
        return [self.k1, self.k2, self.r, self.r, 0.0, 0.0, self.branch_bottom,
                self.branch_top]

    def _main_body(self, k: ModuleType) -> tuple[int, list[float]]:
        """The main body for the compiled ray casts: its kind (``k.PIPE``, ``k.PLATE``,
        ``k.SPHERE`` of :mod:`torchseam.core._kernels`) and its four parameters."""
        raise NotImplementedError

    def _branch_quadric(self, o: np.ndarray, d: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rays ``o + t d`` against the branch's axis: ``(qa, da, A, B, qq)``, the origin's and
        the direction's parts along the axis and the quadratic ``A t^2 + B t + qq`` of the
        squared distance from the axis (across it, in the branch's own cross-section)."""
        q = o - self.o
        qa, da = q @ self.d, d @ self.d
        qp = self._across(q - qa[:, None] * self.d, self._un)
        dp = self._across(d - da[:, None] * self.d, self._un)
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2 * np.einsum("ij,ij->i", qp, dp)
        return qa, da, A, B, np.einsum("ij,ij->i", qp, qp)


class PipeJoint(Joint):
    """Main pipe (oval, along x) and branch pipe (offset, tilted) as solids in {T}: the
    ``pipe`` kind, and the ``offset`` kind (the main axis at ``y = -design_offset_mm``).

    Example:
        >>> from torchseam.core.config import load_part
        >>> joint = PipeJoint(load_part())
        >>> joint.seam(np.array([0.0])).point.shape
        (1, 3)
    """

    def __init__(self, part: PartConfig) -> None:
        super().__init__(part)
        R = part.main_od_mm / 2.0
        self.a = R * (1.0 + part.main_ovality)  # semi-axis along y
        self.b = R * (1.0 - part.main_ovality)  # semi-axis along z

    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # (y + s)^2 / a^2 + z^2 / b^2 = 1 on the generator c + h d (the upper root)
        y = c[:, 1] + self.s
        s = np.sqrt(np.clip(1.0 - (y / self.a) ** 2, 1e-12, None))
        z = self.b * s
        h = (z - c[:, 2]) / self.d[2]
        dz = -self.b * y * dc[:, 1] / (self.a**2 * s)
        dh = (dz - dc[:, 2]) / self.d[2]
        return h, dh

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        n = np.stack([np.zeros(len(p)), (p[:, 1] + self.s) / self.a**2, p[:, 2] / self.b**2],
                     axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def _main_body(self, k: ModuleType) -> tuple[int, list[float]]:
        # ((y + s)/a)^2 + (z/b)^2 = 1
        return k.PIPE, [self.a, self.b, self.s, 0.0]

    def main_solid(self) -> dict:
        """``{"kind": "pipe", "origin": a point of the main axis, "a", "b"}`` (semi-axes along
        y and z)."""
        return {"kind": "pipe", "origin": np.array([0.0, -self.s, 0.0]), "a": self.a,
                "b": self.b, "rotation": np.eye(3)}


class PlateJoint(Joint):
    """A branch pipe set on a flat plate (the ``plate`` kind): the plate's top face is z = 0
    (a square of side ``2 PLATE_HALF_MM``, ``PLATE_THICKNESS_MM`` thick), the seam the
    branch's section by that plane (the branch's circle when it stands upright)."""

    main_name = "plate"

    def __init__(self, part: PartConfig) -> None:
        super().__init__(part)
        # the branch reaches below the plate all round (the plate hides that part)
        sb = self.d[2]
        reach = self.r * self.k1 * abs(self.d[0]) / sb
        self.branch_bottom = -reach - 1.0
        self.branch_top = reach + NOZZLE_ABOVE_SEAM_MM

    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return -c[:, 2] / self.d[2], -dc[:, 2] / self.d[2]

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        return np.broadcast_to(np.array([0.0, 0.0, 1.0]), (len(p), 3)).copy()

    def _main_body(self, k: ModuleType) -> tuple[int, list[float]]:
        # the top face only (rays come from above the plate), a square of half side
        return k.PLATE, [PLATE_HALF_MM, 0.0, 0.0, 0.0]

    def main_solid(self) -> dict:
        """``{"kind": "plate", "origin": the top face's centre, "half": half side,
        "thickness"}``."""
        return {"kind": "plate", "origin": np.zeros(3), "half": PLATE_HALF_MM,
                "thickness": PLATE_THICKNESS_MM, "rotation": np.eye(3)}


class SphereJoint(Joint):
    """A branch pipe set on a sphere (the ``sphere`` kind: a nozzle on a spherical head) of
    radius ``sphere_radius_mm`` centred at ``m = (0, -design_offset_mm, 0)``. The seam is where
    the branch generator c + h d reaches the sphere, the upper root of
    ``|c - m + h d|^2 = R^2``: ``h = -g + sqrt(g^2 + R^2 - |c - m|^2)``, ``g = (c - m) . d``
    (a circle of radius r at height sqrt(R^2 - r^2) for a round branch through the centre)."""

    main_name = "sphere"

    def __init__(self, part: PartConfig) -> None:
        super().__init__(part)
        self.R = float(part.sphere_radius_mm)
        self.m = np.array([0.0, -self.s, 0.0])
        h = self._height(*self.branch_point(np.linspace(0.0, 2 * np.pi, 72, endpoint=False)))[0]
        self.branch_top = float(h.max()) + NOZZLE_ABOVE_SEAM_MM

    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = c - self.m
        g = w @ self.d
        root = np.sqrt(np.clip(g * g + self.R**2 - np.einsum("ij,ij->i", w, w), 1e-12, None))
        dg = dc @ self.d
        dq = 2.0 * np.einsum("ij,ij->i", w, dc)
        return -g + root, -dg + (2.0 * g * dg - dq) / (2.0 * root)

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        n = p - self.m
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def _main_body(self, k: ModuleType) -> tuple[int, list[float]]:
        return k.SPHERE, [self.R, *self.m]

    def main_solid(self) -> dict:
        """``{"kind": "sphere", "origin": the centre, "radius"}``."""
        return {"kind": "sphere", "origin": self.m.copy(), "radius": self.R,
                "rotation": np.eye(3)}


#: :class:`BevelledJoint`: how many points along a ray's path through the branch wall are
#: tried for its first entry into the wall's material, then at most how many steps of regula
#: falsi narrow the bracket to how wide (mm along the ray)
BEVEL_MARCH_POINTS = 48
BEVEL_REFINE_STEPS = 30
BEVEL_REFINE_TOL_MM = 1e-10


class BevelledJoint(Joint):
    """A bevelled branch set on a main body with a root gap: the groove of a full-penetration
    set-on branch (``bevel_deg`` > 0 in the part file; issue 37's ``t_joint_bevel.yaml``).

    The branch is a pipe of wall ``w = branch_wall_mm`` (inner radius ``r_i = r - w``, oval
    like the outside). Its end is cut at the bevel angle ``b`` from the square end across the
    wall: in the half-plane of the branch axis at angle ``phi`` the end face runs from the
    *root edge* at radius ``r_i``, ``root_gap_mm`` (``g``) above where the inner generator meets
    the main body (height ``h_i(phi)`` along the axis), straight out and up to the *shoulder*
    at radius ``r``, ``w tan b`` higher. The groove is the wedge between that face and the main
    body's surface; the main body is cut to the branch's bore (a set-on branch), so light
    that passes through the root gap into the bore is lost (the ray counts as a miss).

    The seam is the **root centre**, the middle of the gap: ``c_i(phi) + (h_i + g / 2) d``,
    where the torch aims; it lies on no surface (:attr:`seam_on_surface` False). Its
    ``normal_main`` is the main body's normal at the main side's root edge and its
    ``normal_branch`` the bevel face's normal at the branch's root edge, so
    :func:`torch_frames` puts the torch on the bisector of the groove (on the T joint's crown
    22.5 degrees off the main pipe for a 45-degree bevel). The fillet's bisector would lie in
    the plane of a 45-degree bevel there: the laser, riding with the torch, would graze the
    bevel face and the camera would not see it.

    Surface ids of :meth:`raycast`: 1 the main body, 2 the branch (its outer wall above the
    shoulder and the bevel face alike); :meth:`normal_branch` tells them apart by the radius.
    The main body's own geometry (``_height``, ``normal_main``, ``main_solid``) is the plain
    joint's of the same kind (``base``); :meth:`raycast` casts it and the bevelled wall in one
    compiled pass (:mod:`torchseam.core._kernels`).
    """

    seam_on_surface = False

    def __init__(self, base: Joint, part: PartConfig) -> None:
        super().__init__(part)
        self.base = base
        self.kind, self.main_name = base.kind, base.main_name
        self.branch_bottom, self.branch_top = base.branch_bottom, base.branch_top
        self.wall = float(part.branch_wall_mm)
        self.r_in = self.r - self.wall
        self.gap = float(part.root_gap_mm)
        self.tan_b = float(np.tan(np.deg2rad(part.bevel_deg)))
        self._march = np.linspace(0.0, 1.0, BEVEL_MARCH_POINTS)

    # ------------------------------------------------------------------ the main body
    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.base._height(c, dc)

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        return self.base.normal_main(p)

    def main_solid(self) -> dict:
        return self.base.main_solid()

    def _main_body(self, k: ModuleType) -> tuple[int, list[float]]:
        return self.base._main_body(k)

    def _branch_shape(self) -> list[float]:
        return [self.k1, self.k2, self.r, self.r_in, self.gap, self.tan_b, self.branch_bottom,
                self.branch_top]

    # ------------------------------------------------------------------ the bevelled branch
    def _generator(self, rho: float | np.ndarray, phi: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Points across the branch axis at radius ``rho`` (of the round branch: scaled by the
        ovality like the outside) and angles ``phi``, (N, 3), and their derivatives in phi."""
        rho = np.asarray(rho, dtype=float).reshape(-1, 1)
        cos, sin = np.cos(phi)[:, None], np.sin(phi)[:, None]
        c = self.o + rho * (cos * self._f1 + sin * self._f2)
        dc = rho * (-sin * self._f1 + cos * self._f2)
        return c, dc

    def root_height(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Height along the branch axis of the branch's root edge at angles ``phi`` (the inner
        generator's meeting with the main body plus the gap), and its derivative in phi."""
        h, dh = self.base._height(*self._generator(self.r_in, phi))
        return h + self.gap, dh

    def _bevel_normal(self, rho: np.ndarray, phi: np.ndarray, dh: np.ndarray) -> np.ndarray:
        """(N, 3) outward unit normals of the bevel face at radius ``rho``, angle ``phi``
        (``dh``: the root edge's height's derivative in phi there, :meth:`root_height`)."""
        cos, sin = np.cos(phi)[:, None], np.sin(phi)[:, None]
        d_rho = cos * self._f1 + sin * self._f2 + self.tan_b * self.d
        d_phi = rho[:, None] * (-sin * self._f1 + cos * self._f2) + dh[:, None] * self.d
        n = np.cross(d_phi, d_rho)
        n *= -np.sign(n @ self.d)[:, None]  # the face looks down the axis, out of the wall
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def normal_branch(self, p: np.ndarray) -> np.ndarray:
        """Outward unit normals of the branch at its surface points: the outer wall's where a
        point lies on it, the bevel face's below the shoulder."""
        rho, phi, _ = self._polar(p)
        out = super().normal_branch(p)
        face = rho < self.r * (1.0 - 1e-9)
        if face.any():
            out[face] = self._bevel_normal(rho[face], phi[face], self.root_height(phi[face])[1])
        return out

    def seam_point(self, phi: np.ndarray) -> np.ndarray:
        """``seam(phi).point``."""
        return self.seam(phi).point

    def seam(self, phi: np.ndarray) -> SeamSample:
        """The root centre at branch angles ``phi`` (N,) rad: the middle of the root gap on
        the branch's inner generator; tangent, the main body's normal at its root edge and
        the bevel face's at the branch's root edge."""
        phi = np.asarray(phi, dtype=float).reshape(-1)
        c, dc = self._generator(self.r_in, phi)
        h, dh = self.base._height(c, dc)
        p = c + (h + 0.5 * self.gap)[:, None] * self.d
        t = dc + dh[:, None] * self.d
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        n_main = self.base.normal_main(c + h[:, None] * self.d)
        n_face = self._bevel_normal(np.full(len(phi), self.r_in), phi, dh)
        return SeamSample(phi, p, t, n_main, n_face)

    # ------------------------------------------------------------------ ray casting
    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The main body's surface except inside the branch's bore (cut out: set-on), and the
        branch's wall, first entered where a ray crosses the outer cylinder above the shoulder,
        else at the first point of its path through the wall's shell (outer cylinder to bore)
        that lies above the bevel face: tried at ``BEVEL_MARCH_POINTS`` points along that
        stretch in order (up to the first past the main body's hit, which hides the branch
        beyond it), then the crossing before the first point in the material refined to
        ``BEVEL_REFINE_TOL_MM`` (regula falsi, at most ``BEVEL_REFINE_STEPS`` steps).
        Compiled: :func:`torchseam.core._kernels.bevel_raycast`."""
        k = load_kernels(__package__)
        return k.bevel_raycast(o, d, self._geometry(k), self._main_body(k)[0], self._march,
                               BEVEL_REFINE_STEPS, BEVEL_REFINE_TOL_MM)


#: The ``inline`` kind: how far the lower pipe (a butt) or the sleeve (a lap) reaches below the
#: seam's plane, and the branch above it, mm
INLINE_BELOW_MM = 300.0


class InlineJoint(Joint):
    """A pipe continued along its own axis (the ``inline`` kind): a girth joint, whose stripe is
    straight across the seam (``joint: butt`` or ``lap`` in the part file).

    {T}: z up the pipe (``intersection_angle_deg`` is 90), the origin on the design axis in the
    seam's plane. The branch (the upper pipe) carries the part's offset and ovality as every
    kind's branch does.

    * ``butt``: two lengths of the branch's pipe (its diameter, wall ``branch_wall_mm``) end to
      end, their square-cut ends ``root_gap_mm`` apart; the main body is the lower pipe, round
      on the design axis, so the branch's offset is the joint's hi-lo. The seam is the **gap's
      centre**, midway between the two pipes' edges at each angle (on no surface:
      :attr:`seam_on_surface` False); the torch stands on the pipe's normal. Light that passes
      through the gap into the bore is lost; the ends' faces in the gap are lit where a ray
      reaches them.
    * ``lap``: a sleeve of wall ``sleeve_wall_mm`` slipped over the pipe (a sleeve or socket
      lap; the sleeve is the main body, coaxial with the pipe and oval like it), its end face in
      the seam's plane. The seam is the corner of that face and the pipe, where the fillet goes;
      the torch on its bisector, 45 degrees between the axis and the pipe's normal.

    Surface ids of :meth:`raycast`: 1 the main body (its outside and its end face), 2 the
    branch (the same).

    Example:
        >>> from torchseam.core.config import load_part
        >>> joint = make_joint(load_part("configs/parts/pipe_butt.yaml"))
        >>> bool(np.allclose(joint.seam(np.array([0.0])).point[0, 2], 0.0, atol=0.5))
        True
    """

    kind = "inline"

    def __init__(self, part: PartConfig) -> None:
        super().__init__(part)
        self.lap = part.joint == "lap"
        self.main_name = "sleeve" if self.lap else "lower pipe"
        self.seam_on_surface = self.lap
        self.gap = float(part.root_gap_mm)
        self.wall = float(part.branch_wall_mm)
        self.sleeve = float(part.sleeve_wall_mm)
        self.below = INLINE_BELOW_MM
        self.branch_bottom = 0.0 if self.lap else 0.5 * self.gap
        self.branch_top = INLINE_BELOW_MM

    # ------------------------------------------------------------------ seam
    def _height(self, c: np.ndarray, dc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(len(c)), np.zeros(len(c))   # the seam's plane through o

    def _lower_edge(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The butt's lower pipe: its outer edge at angles ``phi`` (N, 3) and d / dphi."""
        cos, sin = np.cos(phi)[:, None], np.sin(phi)[:, None]
        c = self.r * (cos * self.e1 + sin * self.e2) - 0.5 * self.gap * self.d
        return c, self.r * (-sin * self.e1 + cos * self.e2)

    def seam_point(self, phi: np.ndarray) -> np.ndarray:
        """``seam(phi).point``."""
        return super().seam_point(phi) if self.lap else self.seam(phi).point

    def seam(self, phi: np.ndarray) -> SeamSample:
        """A lap: the corner of the sleeve's end face and the pipe (:meth:`Joint.seam`). A
        butt: the gap's centre, midway between the two pipes' edges at angles ``phi``; tangent,
        and each pipe's normal at its edge."""
        if self.lap:
            return super().seam(phi)
        phi = np.asarray(phi, dtype=float).reshape(-1)
        cb, dcb = self.branch_point(phi)
        cb = cb + 0.5 * self.gap * self.d
        cm, dcm = self._lower_edge(phi)
        t = 0.5 * (dcb + dcm)
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return SeamSample(phi, 0.5 * (cb + cm), t, self.normal_main(cm), self.normal_branch(cb))

    # ------------------------------------------------------------------ normals
    def normal_main(self, p: np.ndarray) -> np.ndarray:
        """The sleeve's (lap) or the lower pipe's (butt) outward normals: the end face's (up
        the axis) at points in its plane inside the outer wall, else the outside's."""
        if self.lap:
            n = super().normal_branch(p)   # the sleeve is coaxial with the pipe, oval like it
            face = (p - self.o) @ self.d > -1e-6
        else:
            q = p - (p @ self.d)[:, None] * self.d
            n = q / np.linalg.norm(q, axis=1, keepdims=True)
            face = ((p @ self.d > -0.5 * self.gap - 1e-6)
                    & (np.linalg.norm(q, axis=1) < self.r * (1.0 - 1e-9)))
        return np.where(face[:, None], self.d, n)

    def normal_branch(self, p: np.ndarray) -> np.ndarray:
        """The upper pipe's outward normals: its end face's (down the axis, a butt) at points
        in that plane inside the outer wall, else the outside's."""
        n = super().normal_branch(p)
        if self.lap:
            return n
        rho, _, h = self._polar(p)
        face = (h < 0.5 * self.gap + 1e-6) & (rho < self.r * (1.0 - 1e-9))
        return np.where(face[:, None], -self.d, n)

    # ------------------------------------------------------------------ ray casting
    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """In numpy: the main body's hit and the branch's, the nearer kept."""
        o = np.broadcast_to(o, d.shape)
        t_main = self._hit_main(o, d)
        t_branch = self._hit_branch(o, d)
        t = np.minimum(t_main, t_branch)
        surface = np.where(np.isinf(t), 0, np.where(t_main <= t_branch, 1, 2)).astype(np.int8)
        return t, surface

    def _end_face(self, qa: np.ndarray, da: np.ndarray, A: np.ndarray, B: np.ndarray,
                  qq: np.ndarray, at: float, r0: float, r1: float) -> np.ndarray:
        """Rays (their parts along an axis, ``qa + t da``, and across it, squared distance
        ``A t^2 + B t + qq``) against the annulus ``r0 <= radius <= r1`` in the plane at
        height ``at`` (lit from the side the ray comes from)."""
        ok = np.abs(da) > 1e-12
        t = (at - qa) / np.where(ok, da, 1.0)
        rho2 = A * t * t + B * t + qq
        hit = ok & (t > 0) & (rho2 >= r0 * r0) & (rho2 <= r1 * r1)
        return np.where(hit, t, np.inf)

    def _hit_main(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        if self.lap:   # the sleeve: coaxial with the pipe, outer radius r + sleeve wall
            qa, da, A, B, qq = self._branch_quadric(o, d)
            r1 = self.r + self.sleeve
            t = _entry_root(A, B, qq - r1**2)
            h = qa + t * da
            t = np.where((h < 0.0) & (h > -self.below), t, np.inf)
            return np.minimum(t, self._end_face(qa, da, A, B, qq, 0.0, self.r, r1))
        # the lower pipe: round, on the design axis, its end at -gap / 2
        qa, da = o @ self.d, d @ self.d
        qp, dp = o - qa[:, None] * self.d, d - da[:, None] * self.d
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2 * np.einsum("ij,ij->i", qp, dp)
        qq = np.einsum("ij,ij->i", qp, qp)
        top = -0.5 * self.gap
        t = _entry_root(A, B, qq - self.r**2)
        h = qa + t * da
        t = np.where((h < top) & (h > top - self.below), t, np.inf)
        return np.minimum(t, self._end_face(qa, da, A, B, qq, top, self.r - self.wall, self.r))

    def _hit_branch(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        qa, da, A, B, qq = self._branch_quadric(o, d)
        t = _entry_root(A, B, qq - self.r**2)
        h = qa + t * da  # height of the hit along the branch axis: where the branch exists
        t = np.where((h > self.branch_bottom) & (h < self.branch_top), t, np.inf)
        if self.lap:   # its end is inside the sleeve
            return t
        face = self._end_face(qa, da, A, B, qq, self.branch_bottom, self.r - self.wall, self.r)
        return np.minimum(t, face)

    def main_solid(self) -> dict:
        """``{"kind": "pipe", "origin", "a", "b", "rotation", "half_length"}``: the lower pipe
        (butt) or the sleeve (lap) as a pipe whose own axes in {T} are ``rotation``'s columns
        (x: the branch's axis), its middle ``below / 2`` under the seam's plane."""
        if self.lap:
            r = self.r + self.sleeve
            a, b, centre = r * self.k2, r * self.k1, self.o - 0.5 * self.below * self.d
        else:
            a = b = self.r
            centre = -(0.5 * self.gap + 0.5 * self.below) * self.d
        rotation = np.stack([self.d, self.e2, np.cross(self.d, self.e2)], axis=1)
        return {"kind": "pipe", "origin": centre, "a": a, "b": b, "rotation": rotation,
                "half_length": 0.5 * self.below}


#: The coupon kind: how far its plates run on past each end of the welded seam (the run-on and
#: run-off tabs: the approach starts on one, the sensor looks ahead onto the other) and each
#: plate's width across the seam, mm.
COUPON_TAB_MM = 100.0
COUPON_PLATE_WIDTH_MM = 100.0


class CouponJoint(Joint):
    """Two flat plates butted along a straight seam (the ``coupon`` kind): an open seam.

    {T}: x along the seam, the weld from x = 0 to ``seam_length_mm``; z up, the first plate's
    top face z = 0; y across, the first plate (surface 1, the "main body") at y < 0, the second
    (surface 2) at y > 0. Their square edges stand ``root_gap_mm`` apart; the second plate is
    off its design place by ``branch_offset_mm`` (across the seam: a wider gap; up: the hi-lo).
    Each plate is ``plate_thickness_mm`` thick, ``COUPON_PLATE_WIDTH_MM`` wide, and runs
    ``COUPON_TAB_MM`` past both ends of the weld. Nothing is under them: light that passes
    through the gap is lost; the edges' faces in the gap are lit where a ray reaches them.

    The seam is the gap's centre, midway between the plates' top edges (on no surface: as a
    girth butt's, :attr:`seam_on_surface` False); the torch stands on the plates' normal. The
    seam parameter ``phi`` runs along x: ``x = seam_length_mm * phi / (2 pi)``.

    Example:
        >>> from torchseam.core.config import load_part
        >>> joint = make_joint(load_part("configs/parts/plate_butt.yaml"))
        >>> joint.closed, joint.seam(np.array([np.pi])).point[0, 0] == joint.length / 2
        (False, True)
    """

    kind = "coupon"
    main_name = "plates"
    closed = False
    seam_on_surface = False

    def __init__(self, part: PartConfig) -> None:
        super().__init__(part)
        self.length = float(part.seam_length_mm)
        self.gap = float(part.root_gap_mm)
        self.thickness = float(part.plate_thickness_mm)
        self.across, self.up = (float(v) for v in part.branch_offset_mm)
        x0, x1 = -COUPON_TAB_MM, self.length + COUPON_TAB_MM
        g, w, t = 0.5 * self.gap, COUPON_PLATE_WIDTH_MM, self.thickness
        self._boxes = (
            (np.array([x0, -g - w, -t]), np.array([x1, -g, 0.0])),
            (np.array([x0, g + self.across, self.up - t]),
             np.array([x1, g + self.across + w, self.up])))
        # no branch pipe (r 0: robot.reach checks the torch against the plates alone)
        self.r, self.k1, self.k2 = 0.0, 1.0, 1.0
        self.d = np.array([0.0, 0.0, 1.0])
        self.o = np.array([0.5 * (x0 + x1), 0.0, -0.5 * t])
        self.branch_bottom = self.branch_top = 0.0

    # ------------------------------------------------------------------ seam
    def phi_span(self) -> tuple[float, float]:
        k = 2.0 * np.pi / self.length
        return -COUPON_TAB_MM * k, (self.length + COUPON_TAB_MM) * k

    def phi_near(self, p: np.ndarray) -> float:
        return float(2.0 * np.pi * p[0] / self.length)

    def seam_point(self, phi: np.ndarray) -> np.ndarray:
        """``seam(phi).point``."""
        return self.seam(phi).point

    def seam(self, phi: np.ndarray) -> SeamSample:
        phi = np.asarray(phi, dtype=float).reshape(-1)
        n = len(phi)
        p = np.zeros((n, 3))
        p[:, 0] = self.length * phi / (2.0 * np.pi)
        p[:, 1], p[:, 2] = 0.5 * self.across, 0.5 * self.up
        x = np.broadcast_to(np.array([1.0, 0.0, 0.0]), (n, 3)).copy()
        z = np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, 3)).copy()
        return SeamSample(phi, p, x, z, z.copy())

    def _face_normal(self, p: np.ndarray, which: int) -> np.ndarray:
        """Outward normals of plate ``which`` (0 the first, 1 the second) at its surface points
        ``p``: its edge face's (towards the other plate) below its top, else its top's."""
        lo, hi = self._boxes[which]
        edge_y, sign = (hi[1], 1.0) if which == 0 else (lo[1], -1.0)
        on_edge = (np.abs(p[:, 1] - edge_y) < 1e-6) & (p[:, 2] < hi[2] - 1e-6)
        n = np.zeros((len(p), 3))
        n[:, 2] = 1.0
        n[on_edge] = (0.0, sign, 0.0)
        return n

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        return self._face_normal(np.asarray(p, float).reshape(-1, 3), 0)

    def normal_branch(self, p: np.ndarray) -> np.ndarray:
        return self._face_normal(np.asarray(p, float).reshape(-1, 3), 1)

    # ------------------------------------------------------------------ ray casting
    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """In numpy: each plate's box by slabs, the nearer hit kept."""
        o = np.broadcast_to(o, d.shape)
        t1, t2 = (_box_entry(o, d, lo, hi) for lo, hi in self._boxes)
        t = np.minimum(t1, t2)
        surface = np.where(np.isinf(t), 0, np.where(t1 <= t2, 1, 2)).astype(np.int8)
        return t, surface

    def main_solid(self) -> dict:
        """``{"kind": "plate", "origin", "half", "half_y", "thickness", "rotation"}``: one box
        round both plates (the gap is left out: the torch stands over it), its top face's
        centre the origin, at the higher plate's top."""
        (lo0, hi0), (lo1, hi1) = self._boxes
        lo, hi = np.minimum(lo0, lo1), np.maximum(hi0, hi1)
        return {"kind": "plate", "origin": np.array([0.5 * (lo[0] + hi[0]),
                                                     0.5 * (lo[1] + hi[1]), hi[2]]),
                "half": 0.5 * (hi[0] - lo[0]), "half_y": 0.5 * (hi[1] - lo[1]),
                "thickness": hi[2] - lo[2], "rotation": np.eye(3)}


def _box_entry(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Rays ``o + t d`` ((N, 3) each) against the axis-aligned box [lo, hi]: where they enter
    it (``inf``: a miss, or an origin inside)."""
    flat = d == 0.0
    safe = np.where(flat, 1.0, d)
    t1, t2 = (lo - o) / safe, (hi - o) / safe
    inside = (o >= lo) & (o <= hi)
    t_in = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(axis=1)
    t_out = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(axis=1)
    return np.where((t_in <= t_out) & (t_in > 0.0), t_in, np.inf)


def seam_interp(closed: bool, x: np.ndarray, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp`` of a seam table (``xp`` increasing, from the ring's start to its end: the
    arc length against the seam parameter, or back): round a closed seam (``x`` taken modulo
    the table's span), straight on past an open seam's ends (the end intervals' slopes)."""
    x = np.asarray(x, dtype=float)
    if closed:
        return np.interp(np.mod(x - xp[0], xp[-1] - xp[0]) + xp[0], xp, fp)
    y = np.interp(x, xp, fp)
    lo, hi = x < xp[0], x > xp[-1]
    y = np.where(lo, fp[0] + (x - xp[0]) * (fp[1] - fp[0]) / (xp[1] - xp[0]), y)
    return np.where(hi, fp[-1] + (x - xp[-1]) * (fp[-1] - fp[-2]) / (xp[-1] - xp[-2]), y)


def make_joint(part: PartConfig) -> Joint:
    """The joint of ``part``'s kind (``pipe`` and ``offset``: :class:`PipeJoint`; ``plate``:
    :class:`PlateJoint`; ``sphere``: :class:`SphereJoint`; ``inline``: :class:`InlineJoint`;
    ``coupon``: :class:`CouponJoint`); a bevelled branch (``bevel_deg`` > 0) is the
    :class:`BevelledJoint` on it."""
    if part.kind == "inline":
        return InlineJoint(part)
    if part.kind == "coupon":
        return CouponJoint(part)
    cls = {"pipe": PipeJoint, "offset": PipeJoint, "plate": PlateJoint,
           "sphere": SphereJoint}[part.kind]
    base = cls(part)
    return BevelledJoint(base, part) if part.bevel_deg > 0.0 else base


def _entry_root(A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Smallest positive root of A t^2 + B t + C = 0 for rays starting outside (C > 0)."""
    disc = B * B - 4 * A * C
    ok = (disc >= 0) & (A > 1e-12) & (C > 0)
    sq = np.sqrt(np.where(ok, disc, 0.0))
    t = (-B - sq) / np.where(ok, 2 * A, 1.0)
    return np.where(ok & (t > 0), t, np.inf)


def closed_form_orthogonal_seam(R: float, r: float, phi: np.ndarray) -> np.ndarray:
    """METHOD.md section 0: seam(phi) of the ideal orthogonal T, (N, 3)."""
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(R**2 - r**2 * np.sin(phi) ** 2)],
                    axis=1)


def torch_frames(sample: SeamSample) -> np.ndarray:
    """Ideal torch frames along a seam, (N, 4, 4) in the joint frame.

    x: travel direction (seam tangent); z: torch axis, pointing into the corner along the
    bisector of the two surface normals; y = z x x. The same convention as METHOD.md eq. 29
    (wx = px is the normal of the stripe plane, i.e. the travel direction).
    """
    x = sample.tangent
    z = -(sample.normal_main + sample.normal_branch)
    z = z - np.einsum("ij,ij->i", z, x)[:, None] * x
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, x)
    T = np.tile(np.eye(4), (len(x), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, z, sample.point
    return T


def nominal_part(part: PartConfig) -> PartConfig:
    """The design of ``part``: same kind, pipes, angle and designed offset, no deviations."""
    ident = dataclasses.replace(part.placement, position_mm=(0.0, 0.0, 0.0),
                                quaternion=(1.0, 0.0, 0.0, 0.0))
    return dataclasses.replace(part, branch_offset_mm=(0.0, 0.0), main_ovality=0.0,
                               branch_ovality=0.0, distortion_mm=0.0, placement_error=ident)


class SegmentGeometry:
    """The design part of one segment: the part's nominal geometry (:func:`nominal_part`: no
    unwanted offset, ovality or drift) at its placement, turned by the positioner by
    ``rotation_deg`` about the branch axis; its seam by angle and arc length, and the torch
    frames a robot programmed from the design follows. The planner works on it; the
    simulator's :class:`~torchseam.sim.scene.Scene` adds the true part to it.

    Example:
        >>> from torchseam.core.config import load_part
        >>> SegmentGeometry(load_part()).nominal_tcp(np.array([0.0, 10.0])).shape
        (2, 4, 4)
    """

    def __init__(self, part: PartConfig, rotation_deg: float = 0.0) -> None:
        self.part = part
        self.nominal_joint = make_joint(nominal_part(part))
        # positioner turn about the branch axis of the nominal part
        Rz = np.eye(4)
        Rz[:3, :3] = rotation_about(self.nominal_joint.d, np.deg2rad(rotation_deg))
        self.T_B_Tnom = part.placement.matrix() @ Rz
        self._phi_tab, self._s_tab = self.nominal_joint.arc_length_table()
        self.seam_length_mm = float(self._s_tab[-1])

    def phi_at(self, s_mm: np.ndarray) -> np.ndarray:
        """Nominal seam angle at arc length ``s_mm`` (wraps around a ring; an open seam's
        runs on past its ends)."""
        return seam_interp(self.nominal_joint.closed, s_mm, self._s_tab, self._phi_tab)

    def s_at(self, phi: np.ndarray) -> np.ndarray:
        """Nominal seam arc length at angle ``phi``."""
        return seam_interp(self.nominal_joint.closed, phi, self._phi_tab, self._s_tab)

    def nominal_tcp(self, s_mm: np.ndarray) -> np.ndarray:
        """Nominal torch poses in {B} at seam arc lengths ``s_mm`` (N,), (N, 4, 4)."""
        frames = torch_frames(self.nominal_joint.seam(self.phi_at(np.asarray(s_mm, float))))
        return self.T_B_Tnom @ frames
