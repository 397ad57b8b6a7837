"""Geometry of the pipe-to-pipe joint: two solid cylinders, their seam, ray casting.

Joint frame {T}: x along the main pipe axis, z up the branch (METHOD.md section 0). The main
pipe may be oval (semi-axes ``a`` along y and ``b`` along z); the branch axis may be offset and
tilted to the intersection angle ``beta`` in the x-z plane. Because the main pipe is a cylinder
along x, the seam has a closed form for all of these deviations: for a point on the branch
surface at angle ``phi`` the height along the branch axis follows from the ellipse equation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchseam.core.config import PartConfig

BRANCH_LENGTH_MM = 400.0  # how far the branch pipe extends above the main axis


@dataclass(frozen=True)
class SeamSample:
    """Seam points and local geometry at branch angles ``phi``; all arrays (N, 3) in {T}."""

    phi: np.ndarray
    point: np.ndarray
    tangent: np.ndarray        # unit, direction of increasing phi
    normal_main: np.ndarray    # outward unit normal of the main pipe
    normal_branch: np.ndarray  # outward unit normal of the branch


class PipeJoint:
    """Main pipe (oval, along x) and branch pipe (offset, tilted) as solids in {T}.

    Example:
        >>> from torchseam.core.config import load_part
        >>> joint = PipeJoint(load_part())
        >>> joint.seam(np.array([0.0])).point.shape
        (1, 3)
    """

    def __init__(self, part: PartConfig) -> None:
        R = part.main_od_mm / 2.0
        self.a = R * (1.0 + part.main_ovality)  # semi-axis along y
        self.b = R * (1.0 - part.main_ovality)  # semi-axis along z
        self.r = part.branch_od_mm / 2.0
        beta = np.deg2rad(part.intersection_angle_deg)
        self.d = np.array([np.cos(beta), 0.0, np.sin(beta)])      # branch axis
        self.e2 = np.array([0.0, 1.0, 0.0])
        self.e1 = np.cross(self.e2, self.d)                        # (sin b, 0, -cos b)
        self.o = np.array([part.branch_offset_mm[0], part.branch_offset_mm[1], 0.0])

    # ------------------------------------------------------------------ seam
    def seam(self, phi: np.ndarray) -> SeamSample:
        """Seam at branch angles ``phi`` (N,) rad, with tangent and both surface normals."""
        phi = np.asarray(phi, dtype=float).reshape(-1)
        c = self.o + self.r * (np.cos(phi)[:, None] * self.e1 + np.sin(phi)[:, None] * self.e2)
        dc = self.r * (-np.sin(phi)[:, None] * self.e1 + np.cos(phi)[:, None] * self.e2)
        s = np.sqrt(np.clip(1.0 - (c[:, 1] / self.a) ** 2, 1e-12, None))
        z = self.b * s
        h = (z - c[:, 2]) / self.d[2]
        dz = -self.b * c[:, 1] * dc[:, 1] / (self.a**2 * s)
        dh = (dz - dc[:, 2]) / self.d[2]
        p = c + h[:, None] * self.d
        t = dc + dh[:, None] * self.d
        t /= np.linalg.norm(t, axis=1, keepdims=True)
        return SeamSample(phi, p, t, self.normal_main(p), self.normal_branch(p))

    def normal_main(self, p: np.ndarray) -> np.ndarray:
        n = np.stack([np.zeros(len(p)), p[:, 1] / self.a**2, p[:, 2] / self.b**2], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def normal_branch(self, p: np.ndarray) -> np.ndarray:
        q = p - self.o
        n = q - (q @ self.d)[:, None] * self.d
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def arc_length_table(self, n: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """(phi, s): cumulative seam arc length (mm) over phi in [0, 2 pi], n + 1 samples."""
        phi = np.linspace(0.0, 2.0 * np.pi, n + 1)
        p = self.seam(phi).point
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        return phi, s

    # ------------------------------------------------------------------ ray casting
    def raycast(self, origin: np.ndarray, direction: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays with the solid union of both pipes.

        Args:
            origin: (N, 3) or (3,) ray origins in {T}, outside the solid.
            direction: (N, 3) unit directions.

        Returns:
            ``(t, surface)``: (N,) distance along each ray (``inf`` for a miss) and (N,) int8
            surface id (0 none, 1 main pipe, 2 branch).
        """
        direction = np.asarray(direction, dtype=float).reshape(-1, 3)
        o = np.broadcast_to(np.asarray(origin, dtype=float), direction.shape)
        t_main = self._hit_main(o, direction)
        t_branch = self._hit_branch(o, direction)
        t = np.minimum(t_main, t_branch)
        surface = np.where(np.isinf(t), 0, np.where(t_main <= t_branch, 1, 2)).astype(np.int8)
        return t, surface

    def _hit_main(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        # (y/a)^2 + (z/b)^2 = 1, entry root only.
        A = (d[:, 1] / self.a) ** 2 + (d[:, 2] / self.b) ** 2
        B = 2 * (o[:, 1] * d[:, 1] / self.a**2 + o[:, 2] * d[:, 2] / self.b**2)
        C = (o[:, 1] / self.a) ** 2 + (o[:, 2] / self.b) ** 2 - 1.0
        return _entry_root(A, B, C)

    def _hit_branch(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        q = o - self.o
        qa, da = q @ self.d, d @ self.d
        qp = q - qa[:, None] * self.d
        dp = d - da[:, None] * self.d
        A = np.einsum("ij,ij->i", dp, dp)
        B = 2 * np.einsum("ij,ij->i", qp, dp)
        C = np.einsum("ij,ij->i", qp, qp) - self.r**2
        t = _entry_root(A, B, C)
        h = qa + t * da  # height of the hit along the branch axis: the branch exists above 0
        return np.where((h > 0.0) & (h < BRANCH_LENGTH_MM), t, np.inf)


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
