"""Torch frame from three points (METHOD.md section 5, eq. 27-29), batched in torch.

``p``: the 3D weld point; ``q1``, ``q2``: a point on each stripe arm.
eq. 27: px = normal of the plane Omega through p, q1, q2 (oriented along the travel direction);
eq. 28: pz = bisector of the angle q1-p-q2 in Omega; py = pz x px;
eq. 29: wx = px, wy = -py, wz = -pz (wz points from the torch into the corner).
Work and travel angles then tilt the torch about wx and wy. Poses go to the robot as position +
quaternion in ABB order (w, x, y, z), with the sign kept continuous along the seam.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from pytorch_kinematics.transforms import matrix_to_quaternion
from torch import Tensor

from torchseam.core.checks import check_shape
from torchseam.core.transforms import axis_rotation, cross3

# |u1 x u2| / (|u1| |u2|) below this: the three points are (nearly) collinear
MIN_SIN = 0.02
MIN_ARM_MM = 0.2  # an arm point this close to the weld point is coincident with it


def torch_frame(p: Tensor, q1: Tensor, q2: Tensor, travel: Tensor | None = None,
                tangent: Tensor | None = None, facing: Tensor | None = None
                ) -> tuple[Tensor, Tensor]:
    """Torch orientation at weld points from the three-point principle.

    Args:
        p: (..., 3) weld points; q1, q2: (..., 3) points on each stripe arm.
        travel: (..., 3) travel direction; px is flipped to agree with it. Without it px
            follows the right-hand rule from q1 to q2.
        tangent: (..., 3) measured seam tangent (e.g. from the located path). When given, Omega
            is the plane through p perpendicular to it, instead of the stripe plane: the stripe
            plane leans on a curved seam (the saddle turns about 15 degrees over the 20 mm
            look-ahead), which tilts the arms' bisector off the joint's; across the seam, the
            bisector of the arms is the bisector of the joint.
        facing: (..., 3) where the torch points now (its wz, roughly), with ``tangent``: arms
            that run on in one line (a butt's straight stripe across its gap: no corner to
            bisect) give wz perpendicular to that line in Omega, on this side (the surface's
            normal, into it); without it they are degenerate.

    Returns:
        ``(R, valid)``: (..., 3, 3) rotation matrices with columns (wx, wy, wz), and (...,)
        bool. Degenerate inputs (coincident or collinear points, non-finite values) give
        ``valid = False`` and the identity, never NaN.

    Example:
        >>> p = torch.tensor([[0.0, 0.0, 0.0]])
        >>> q1, q2 = torch.tensor([[0.0, -5.0, 0.0]]), torch.tensor([[0.0, 0.0, -5.0]])
        >>> R, ok = torch_frame(p, q1, q2, travel=torch.tensor([[1.0, 0.0, 0.0]]))
        >>> ok.item(), [round(x, 4) for x in R[0, :, 2].tolist()]  # wz: into the corner
        (True, [-0.0, 0.7071, 0.7071])
    """
    for x, n in ((p, "p"), (q1, "q1"), (q2, "q2")):
        check_shape(x, "... 3", n)
    u1, u2 = q1 - p, q2 - p
    if tangent is not None:
        # Omega taken perpendicular to the seam: the arms' components across the seam
        check_shape(tangent, "... 3", "tangent")
        t = tangent / tangent.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        u1 = u1 - (u1 * t).sum(-1, keepdim=True) * t
        u2 = u2 - (u2 * t).sum(-1, keepdim=True) * t
        if travel is None:
            travel = t
    n1, n2 = u1.norm(dim=-1, keepdim=True), u2.norm(dim=-1, keepdim=True)
    cross = torch.cross(u1, u2, dim=-1)
    sin = cross.norm(dim=-1) / (n1 * n2).squeeze(-1).clamp_min(1e-12)
    valid = ((n1.squeeze(-1) > MIN_ARM_MM) & (n2.squeeze(-1) > MIN_ARM_MM) & (sin > MIN_SIN)
             & torch.isfinite(cross).all(-1))
    px = cross / cross.norm(dim=-1, keepdim=True).clamp_min(1e-12)             # eq. 27
    if travel is not None:
        check_shape(travel, "... 3", "travel")
        flip = (px * travel).sum(-1, keepdim=True) < 0
        px = torch.where(flip, -px, px)
    pz = u1 / n1.clamp_min(1e-12) + u2 / n2.clamp_min(1e-12)                    # eq. 28
    pz = pz / pz.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    if facing is not None and tangent is not None:
        # arms in one line (opposite): px the tangent, pz across the line in Omega, away
        # from where the torch points
        check_shape(facing, "... 3", "facing")
        line = u1 / n1.clamp_min(1e-12) - u2 / n2.clamp_min(1e-12)
        straight = ((sin <= MIN_SIN) & ((u1 * u2).sum(-1) < 0) & (n1.squeeze(-1) > MIN_ARM_MM)
                    & (n2.squeeze(-1) > MIN_ARM_MM) & torch.isfinite(line).all(-1))
        tx = torch.where((t * travel).sum(-1, keepdim=True) < 0, -t, t)
        across = torch.cross(tx, line, dim=-1)
        across = across / across.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        across = torch.where((across * facing).sum(-1, keepdim=True) > 0, -across, across)
        px = torch.where(straight[..., None], tx, px)
        pz = torch.where(straight[..., None], across, pz)
        valid = valid | straight
    py = torch.cross(pz, px, dim=-1)
    R = torch.stack([px, -py, -pz], dim=-1)                                    # eq. 29
    eye = torch.eye(3, dtype=R.dtype, device=R.device).expand_as(R)
    R = torch.where(valid[..., None, None], R, eye)
    return R, valid


def frame_from_arms(p: np.ndarray, q1: np.ndarray, q2: np.ndarray, tangent: np.ndarray,
                    facing: np.ndarray | None = None) -> tuple[np.ndarray, bool]:
    """The torch frame of :func:`torch_frame` with a seam tangent (Omega perpendicular to the
    seam, px along the tangent), for one point in numpy: the live loop's twin of the batched
    torch version (which pays ~1.5 ms of per-call tensor overhead on 3-vectors, this one
    ~30 us); ``tests/test_geometry.py`` holds the two to the same numbers (1e-12).

    Args:
        p: (3,) weld point; q1, q2: (3,) a point on each stripe arm; tangent: (3,) the seam's
            direction of travel (need not be unit). All mm, base frame.
        facing: (3,) where the torch points now: arms in one line (a butt) give the frame
            across that line (:func:`torch_frame`'s ``facing``).

    Returns:
        ``(R, ok)``: (3, 3) rotation with columns (wx, wy, wz) and whether the points define a
        frame (coincident or collinear arms without ``facing``: ``ok`` False and the
        identity).
    """
    t = tangent / max(float(np.linalg.norm(tangent)), 1e-12)
    u1, u2 = q1 - p, q2 - p
    u1 = u1 - (u1 @ t) * t
    u2 = u2 - (u2 @ t) * t
    n1, n2 = float(np.linalg.norm(u1)), float(np.linalg.norm(u2))
    cross = cross3(u1, u2)
    nc = float(np.linalg.norm(cross))
    sin = nc / max(n1 * n2, 1e-12)
    if (facing is not None and n1 > MIN_ARM_MM and n2 > MIN_ARM_MM and sin <= MIN_SIN
            and float(u1 @ u2) < 0 and math.isfinite(nc)):
        line = u1 / n1 - u2 / n2                      # arms in one line: across it in Omega
        across = cross3(t, line)
        across = across / max(float(np.linalg.norm(across)), 1e-12)
        if across @ facing > 0:
            across = -across
        py = cross3(across, t)
        return np.stack([t, -py, -across], axis=1), True
    if not (n1 > MIN_ARM_MM and n2 > MIN_ARM_MM and sin > MIN_SIN and math.isfinite(nc)):
        return np.eye(3), False
    px = cross / max(nc, 1e-12)                                        # eq. 27
    if px @ t < 0:
        px = -px
    pz = u1 / max(n1, 1e-12) + u2 / max(n2, 1e-12)                     # eq. 28
    pz = pz / max(float(np.linalg.norm(pz)), 1e-12)
    py = cross3(pz, px)
    return np.stack([px, -py, -pz], axis=1), True                      # eq. 29


def tilt(R: Tensor, work_deg: float = 0.0, travel_deg: float = 0.0) -> Tensor:
    """Apply the work angle (about wx) and the travel angle (about wy) in the torch frame:
    ``R`` (..., 3, 3) -> (..., 3, 3)."""
    M = axis_rotation(0, work_deg) @ axis_rotation(1, travel_deg)
    return R @ torch.as_tensor(M, dtype=R.dtype, device=R.device)


def quaternions(R: Tensor, previous: Tensor | None = None) -> Tensor:
    """(N, 3, 3) rotations -> (N, 4) quaternions (w, x, y, z), signs continuous along N.

    ``q`` and ``-q`` are the same rotation; a controller interpolating between them turns the
    long way round. Each quaternion takes the sign nearest its predecessor (the first one
    nearest ``previous`` (4,), when given).
    """
    q = matrix_to_quaternion(R)
    if len(q) == 0:
        return q
    # start with w >= 0 unless told where to continue from
    ref = previous if previous is not None else torch.tensor([1.0, 0, 0, 0]).to(q)
    out = []
    for k in range(len(q)):  # sequential by nature: each sign depends on the one before
        qk = q[k]
        if ref is not None and torch.dot(qk, ref) < 0:
            qk = -qk
        out.append(qk)
        ref = qk
    return torch.stack(out)
