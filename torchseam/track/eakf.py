"""EAKF: Kalman filter augmented for coloured process and measurement noise (METHOD.md section 3).

Per image axis (u shown, v identical; t is the frame interval):

- eq. 12  ``u(k+1) = u(k) + u'(k) t + 0.5 w(k) t^2``
- eq. 16  ``w(k) = lambda w(k-1) + n(k)``, n white with variance Q (coloured acceleration)
- eq. 18  ``X(k) = [u(k), u'(k), u(k-1), w(k)]``
- eq. 19  ``X(k+1) = Phi X(k) + Gamma n(k)``,
  ``Phi = [[1, t, 0, t^2/2], [0, 1, 0, t], [1, 0, 0, 0], [0, 0, 0, lambda]]``, ``Gamma = e_4``
- eq. 20  ``Z(k) = H X(k) + M(k)``, ``H = [[1, 0, 0, 0], [1, 0, -1, 0]]`` (position and the
  frame-to-frame displacement)
- eq. 17  ``M(k) = Psi M(k-1) + g(k-1)``, ``Psi = diag(a, b)``, g white with covariance R
- eq. 21-22 ``Z*(k) = Z(k+1) - Psi Z(k) = H* X(k) + g(k)``, ``H* = H Phi - Psi H``
  (``H Gamma = 0``, so the equivalent noise is white and independent of n(k))
- eq. 23-24 the u and v blocks stacked block-diagonally: state (8,) = [u block, v block],
  measurement (4,) = [u, du, v, dv]
- eq. 26 then eq. 25: the standard Kalman update with H*, R, then the prediction with Phi,
  Gamma Q Gamma^T (the paper's eq. 25 is the prediction, eq. 26 the update).

The one-frame delay: Z*(k) needs Z(k+1), so the update for step k runs when frame k+1 arrives,
then the state is propagated one step. After frame k+1 the filter holds X(k+1|k) = Phi X(k|k),
which is conditioned on all measurements Z(0..k+1) (Z*(0..k) carry Z(1..k+1)), so its position is
the best estimate at the newest frame; ``x_post`` keeps X(k|k) of the delayed update.

Internally the two blocks are batched as (B, 2, 4) states and (B, 2, 4, 4) covariances (the
cross-axis blocks of eq. 23-24 are zero and stay zero); :meth:`EAKF.stacked` gives the 8x8
block-diagonal matrices of the paper.

Measurement-noise scale: each frame's measurement may carry a factor ``s >= 1`` on R (the
fusion's distrust). If Z(j) carries extra independent noise of covariance ``(s_j - 1) R``, the
equivalent observation Z*(k) = Z(k+1) - Psi Z(k) carries ``(s_{k+1} - 1) R + Psi^2 (s_k - 1) R``,
so the update uses ``R_eff = R (s_{k+1} + Psi^2 (s_k - 1))`` per component; a displacement formed
from positions (``z(k) - z(k-1)``) takes the larger of the two frames' scales. With all s = 1
this is exactly R.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import Tensor, nn

from torchseam.core.checks import InputError, as_float, check_device, check_shape
from torchseam.track.config import TrackerConfig

__all__ = ["EAKF", "EAKFInnovation", "EAKFMatrices", "EAKFState", "eakf_filter",
           "eakf_init", "eakf_innovation", "eakf_matrices", "eakf_update"]

_D = TrackerConfig()  # the defaults

#: scale on the displacement noise of the synthetic Z(0) (its displacement is unknown)
UNKNOWN_SCALE = 1e6


@dataclass
class EAKFMatrices:
    """Per-axis model matrices (leading dim 2 = u, v axes).

    Attributes:
        Phi: (2, 4, 4) transition (eq. 19).
        GQG: (2, 4, 4) ``Gamma Q Gamma^T`` (eq. 19, 25).
        H: (2, 4) measurement matrix (eq. 20, same for both axes).
        Psi: (2, 2, 2) ``diag(a, b)`` per axis (eq. 17).
        H_star: (2, 2, 4) equivalent observation ``H Phi - Psi H`` (eq. 22).
        R: (2, 2) diagonal of R per axis: [position, displacement] (eq. 17).
        psi: (2, 2) ``[a, b]`` per axis (diagonal of Psi).
    """

    Phi: Tensor
    GQG: Tensor
    H: Tensor
    Psi: Tensor
    H_star: Tensor
    R: Tensor
    psi: Tensor


def eakf_matrices(dt: float | Tensor, lam: Tensor, a: Tensor, b: Tensor, q: Tensor,
                  r: Tensor) -> EAKFMatrices:
    """Build Phi, Gamma Q Gamma^T, H, Psi, H* and R for both axes.

    Args:
        dt: frame interval t (s).
        lam, a, b, q: (2,) per axis: acceleration colour, position / displacement noise colour,
            white acceleration variance Q.
        r: (2, 2) per axis [position, displacement] measurement noise variances (diag R).

    Returns:
        :class:`EAKFMatrices`.

    Example:
        >>> m = eakf_matrices(0.04, *(torch.zeros(2) for _ in range(3)), torch.ones(2),
        ...                   torch.ones(2, 2))
        >>> (m.H_star[0] * 1e4).round().tolist()
        [[10000.0, 400.0, 0.0, 8.0], [0.0, 400.0, 0.0, 8.0]]
    """
    for name, v in (("lam", lam), ("a", a), ("b", b), ("q", q)):
        check_shape(v, (2,), name)
    check_shape(r, (2, 2), "r")
    t = dt if isinstance(dt, Tensor) else torch.tensor(float(dt), dtype=lam.dtype)
    t = t.to(device=lam.device, dtype=lam.dtype)
    z, o = torch.zeros_like(t), torch.ones_like(t)
    phi0 = torch.stack([torch.stack([o, t, z, 0.5 * t * t]), torch.stack([z, o, z, t]),
                        torch.stack([o, z, z, z]), torch.stack([z, z, z, z])])  # eq. 19
    e44 = torch.zeros(4, 4, dtype=lam.dtype, device=lam.device)
    e44[3, 3] = 1.0
    Phi = phi0 + e44 * lam[:, None, None]
    GQG = e44 * q[:, None, None]  # Gamma = e_4 (eq. 19)
    H = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, -1.0, 0.0]], dtype=lam.dtype,
                     device=lam.device)  # eq. 20
    psi = torch.stack([a, b], dim=-1)  # (2, 2)
    Psi = torch.diag_embed(psi)  # eq. 17
    H_star = H @ Phi - Psi @ H  # eq. 22
    return EAKFMatrices(Phi=Phi, GQG=GQG, H=H, Psi=Psi, H_star=H_star, R=r, psi=psi)


@dataclass
class EAKFState:
    """Filter state after the newest frame k (B sequences, 2 axes).

    Attributes:
        x: (B, 2, 4) X(k|k-1) = Phi X(k-1|k-1): the estimate at the newest frame k, given
            Z(0..k) (see the module docstring on the delay).
        P: (B, 2, 4, 4) its covariance.
        Z: (B, 2, 2) Z(k) = [position, displacement] per axis, kept for Z*(k) at frame k+1.
        s: (B, 2, 2) noise scales of Z(k)'s components (for the Psi Z(k) term).
        s_ref: (B, 2) noise scale of the raw position measured at frame k (a displacement
            formed from it at frame k+1 is as bad as the worse of the two frames).
        k: index of the newest frame (0 after :func:`eakf_init`).
        x_post: (B, 2, 4) X(k-1|k-1), the delayed update done when frame k arrived (None at k=0).
        P_post: (B, 2, 4, 4) its covariance (None at k=0).
    """

    x: Tensor
    P: Tensor
    Z: Tensor
    s: Tensor
    s_ref: Tensor
    k: int = 0
    x_post: Tensor | None = None
    P_post: Tensor | None = None

    @property
    def uv(self) -> Tensor:
        """(B, 2) position estimate at the newest frame."""
        return self.x[..., 0]

    @property
    def uv_var(self) -> Tensor:
        """(B, 2) its variance per axis."""
        return self.P[..., 0, 0]

    def predict_uv(self, Phi: Tensor) -> Tensor:
        """(B, 2) predicted position at the next frame, the first row of Phi X(k|k-1)."""
        return (Phi[:, 0, :] * self.x).sum(dim=-1)

    def flat(self) -> tuple[Tensor, Tensor]:
        """The stacked (eq. 23-24) state (B, 8) and block-diagonal covariance (B, 8, 8)."""
        B = self.x.shape[0]
        P = self.P.new_zeros(B, 8, 8)
        P[:, :4, :4] = self.P[:, 0]
        P[:, 4:, 4:] = self.P[:, 1]
        return self.x.reshape(B, 8), P

    def detach(self) -> EAKFState:
        """A copy cut from the autograd graph (truncated BPTT)."""
        kw: dict[str, Any] = {f.name: (v.detach() if isinstance(v, Tensor) else v)
                              for f in fields(self) for v in [getattr(self, f.name)]}
        return EAKFState(**kw)


@dataclass
class EAKFInnovation:
    """Innovation of the delayed update, computed before the measurement is trusted or not.

    Attributes:
        Z_new: (B, 2, 2) Z(k+1) = [position, displacement] per axis.
        nu: (B, 2, 2) innovation ``Z*(k) - H* X(k|k-1)`` (eq. 26).
        PHt: (B, 2, 4, 2) ``P H*^T``.
        HPHt: (B, 2, 2, 2) ``H* P H*^T``.
        S: (B, 2, 2, 2) innovation covariance with the new frame's scale at 1 (the gate's).
        d2_pos: (B,) squared Mahalanobis distance of the position innovations,
            ``sum_axis nu_pos^2 / S_pos`` (chi-square, 2 dof, under the model).
        dz_given: whether the displacement was measured separately.
    """

    Z_new: Tensor
    nu: Tensor
    PHt: Tensor
    HPHt: Tensor
    S: Tensor
    d2_pos: Tensor
    dz_given: bool

    def d2(self) -> Tensor:
        """(B,) full squared Mahalanobis distance ``sum_axis nu^T S^-1 nu`` (4 dof)."""
        return (self.nu[..., None, :] @ _inv2(self.S) @ self.nu[..., :, None])[..., 0, 0].sum(-1)


_ADJ: dict[tuple, tuple[Tensor, Tensor]] = {}


def _inv2(S: Tensor) -> Tensor:
    """Inverse of (..., 2, 2) matrices in closed form (adjugate / determinant: a handful of
    element-wise ops, cheaper than a LAPACK call on tiny batches)."""
    key = (S.device, S.dtype)
    if key not in _ADJ:
        # made outside inference mode even when first called inside it: an inference tensor
        # in the cache would break every later call that needs gradients (training)
        with torch.inference_mode(False):
            _ADJ[key] = (torch.tensor([3, 1, 2, 0], device=S.device),
                         torch.tensor([1.0, -1.0, -1.0, 1.0], device=S.device, dtype=S.dtype))
    perm, sign = _ADJ[key]
    f = S.reshape(S.shape[:-2] + (4,))
    det = f[..., 0] * f[..., 3] - f[..., 1] * f[..., 2]
    return (f.index_select(-1, perm) * sign / det[..., None]).reshape(S.shape)


def eakf_init(z0: Tensor, p0: Tensor) -> EAKFState:
    """Initial state at frame 0: ``X(0|-1) = [z0, 0, z0, 0]`` per axis, ``P = diag(p0)``.

    Args:
        z0: (B, 2) first position measurement (u, v).
        p0: (2, 4) or (4,) initial variances of [position, velocity, previous position,
            acceleration].

    Returns:
        :class:`EAKFState` with k = 0; Z(0) = [z0, 0] (the displacement at frame 0 is unknown,
        so its scale is :data:`UNKNOWN_SCALE`).

    Example:
        >>> eakf_init(torch.tensor([[10.0, 20.0]]), torch.ones(4)).uv
        tensor([[10., 20.]])
    """
    check_shape(z0, ("B", 2), "z0")
    B = z0.shape[0]
    z = torch.zeros_like(z0)
    x = torch.stack([z0, z, z0, z], dim=-1)  # (B, 2, 4)
    p0 = p0.expand(2, 4).to(z0)
    P = torch.diag_embed(p0).expand(B, 2, 4, 4)
    Z = torch.stack([z0, z], dim=-1)
    s = torch.ones_like(Z)
    s = torch.stack([s[..., 0], s[..., 1] * UNKNOWN_SCALE], dim=-1)
    return EAKFState(x=x, P=P, Z=Z, s=s, s_ref=torch.ones_like(z0), k=0)


def eakf_innovation(state: EAKFState, m: EAKFMatrices, z: Tensor,
                    dz: Tensor | None = None) -> EAKFInnovation:
    """Innovation of the delayed update for step k when frame k+1's measurement arrives.

    Args:
        state: state after frame k.
        m: model matrices (:func:`eakf_matrices`).
        z: (B, 2) position measurement (u, v) at frame k+1.
        dz: optional (B, 2) separately measured displacement; default ``z - z(k)``.

    Returns:
        :class:`EAKFInnovation`.
    """
    B = state.x.shape[0]
    check_shape(z, (B, 2), "z")
    z = as_float(z, state.x)
    if dz is None:
        dzv = z - state.Z[..., 0]
    else:
        check_shape(dz, (B, 2), "dz")
        dzv = as_float(dz, state.x)
    Z_new = torch.stack([z, dzv], dim=-1)  # Z(k+1), (B, 2, 2)
    Zs = Z_new - m.psi * state.Z  # eq. 21: Z*(k) = Z(k+1) - Psi Z(k)
    nu = Zs - (m.H_star @ state.x[..., None])[..., 0]  # eq. 26
    PHt = state.P @ m.H_star.transpose(-1, -2)
    HPHt = m.H_star @ PHt
    if dz is None:  # the gate's S: this frame trusted (s = 1), the displacement as bad as z(k)
        s_new = torch.stack([torch.ones_like(z), state.s_ref.clamp_min(1.0)], -1)
    else:
        s_new = torch.ones_like(Z_new)
    S = HPHt + torch.diag_embed(m.R * (s_new + m.psi**2 * (state.s - 1.0)))
    d2_pos = (nu[..., 0] ** 2 / S[..., 0, 0]).sum(dim=-1)
    return EAKFInnovation(Z_new=Z_new, nu=nu, PHt=PHt, HPHt=HPHt, S=S, d2_pos=d2_pos,
                          dz_given=dz is not None)


def eakf_update(state: EAKFState, m: EAKFMatrices, inn: EAKFInnovation,
                r_scale: Tensor | None = None, keep: Tensor | None = None) -> EAKFState:
    """Delayed update of step k (eq. 26) with Z*(k), then prediction to frame k+1 (eq. 25).

    Args:
        state: state after frame k.
        m: model matrices.
        inn: :func:`eakf_innovation` of frame k+1's measurement.
        r_scale: optional measurement-noise scale of frame k+1, (B,) or (B, 2) per axis,
            values >= 1 (1 = trusted); see the module docstring for how it enters R.
        keep: optional (B,) weight in [0, 1] of the raw measurement in the Z(k+1) kept for the
            next equivalent observation ``Z(k+2) - Psi Z(k+1)``. 1 (default) keeps it: exact
            under the model. 0 replaces it by its prediction ``H* X(k|k-1) + Psi Z(k)`` (the
            conditional mean without it), so a rejected outlier neither enters the next
            update through Psi nor blinds the next innovation gate with an inflated R; its
            noise scale is then taken as 1. The fusion passes its trust here.

    Returns:
        State after frame k+1 (``x`` = X(k+1|k), ``x_post`` = X(k|k)).
    """
    B = state.x.shape[0]
    if r_scale is None:
        sc = torch.ones_like(inn.Z_new[..., 0])
    else:
        if r_scale.shape not in ((B,), (B, 2)):
            raise InputError(f"r_scale: expected shape ({B},) or ({B}, 2), "
                             f"got {tuple(r_scale.shape)}")
        r_scale = as_float(r_scale, state.x)
        sc = (r_scale[:, None] if r_scale.ndim == 1 else r_scale).expand(B, 2)
    if inn.dz_given:
        s_new = sc[..., None].expand(B, 2, 2)
    else:  # displacement z(k+1) - z(k) is as bad as the worse of the two
        s_new = torch.stack([sc, torch.maximum(sc, state.s_ref)], -1)
    R_eff = m.R * (s_new + m.psi**2 * (state.s - 1.0))  # (B, 2, 2) diagonal of R_eff
    S = inn.HPHt + torch.diag_embed(R_eff)  # eq. 26
    K = inn.PHt @ _inv2(S)  # (B, 2, 4, 2)
    x_post = state.x + (K @ inn.nu[..., None])[..., 0]  # eq. 26
    P_post = state.P - K @ inn.PHt.transpose(-1, -2)  # (I - K H*) P, K optimal
    x = (m.Phi @ x_post[..., None])[..., 0]  # eq. 25
    P = m.Phi @ P_post @ m.Phi.transpose(-1, -2) + m.GQG
    P = 0.5 * (P + P.transpose(-1, -2))
    Z_keep, s_keep = inn.Z_new, s_new
    if keep is not None:
        if keep.shape != (B,):
            raise InputError(f"keep: expected shape ({B},), got {tuple(keep.shape)}")
        drop = (1.0 - as_float(keep, state.x))[:, None, None]
        Z_keep = inn.Z_new - drop * inn.nu  # Z - nu is the predicted Z(k+1)
        s_keep = s_new - drop * (s_new - 1.0)
    return EAKFState(x=x, P=P, Z=Z_keep, s=s_keep, s_ref=sc, k=state.k + 1, x_post=x_post,
                     P_post=P_post)


def eakf_filter(z: Tensor, dt: float | Tensor, lam: Tensor, a: Tensor, b: Tensor, q: Tensor,
                r: Tensor, p0: Tensor, r_scale: Tensor | None = None,
                dz: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Run the EAKF over whole sequences (functional form, e.g. for ``gradcheck``).

    Args:
        z: (B, T, 2) position measurements.
        dt, lam, a, b, q, r: as :func:`eakf_matrices`.
        p0: (2, 4) or (4,) initial variances (:func:`eakf_init`).
        r_scale: optional (B, T) or (B, T, 2) measurement-noise scales (frame 0's unused).
        dz: optional (B, T, 2) separately measured displacements (frame 0's unused).

    Returns:
        uv (B, T, 2) position estimate at each frame (given measurements up to that frame) and
        its variance (B, T, 2).

    Example:
        >>> z = torch.cumsum(torch.ones(1, 10, 2), dim=1)
        >>> uv, var = eakf_filter(z, 0.04, *(torch.zeros(2) for _ in range(3)),
        ...                       torch.full((2,), 100.0), torch.ones(2, 2), torch.ones(4))
        >>> tuple(uv.shape)
        (1, 10, 2)
    """
    check_shape(z, ("B", "T", 2), "z")
    B, T = z.shape[:2]
    if r_scale is not None and r_scale.shape not in ((B, T), (B, T, 2)):
        raise InputError(f"r_scale: expected shape ({B}, {T}) or ({B}, {T}, 2), "
                         f"got {tuple(r_scale.shape)}")
    if dz is not None:
        check_shape(dz, (B, T, 2), "dz")
    m = eakf_matrices(dt, lam, a, b, q, r)
    state = eakf_init(as_float(z[:, 0], lam), p0)
    uvs, vs = [state.uv], [state.uv_var]
    for k in range(1, T):
        inn = eakf_innovation(state, m, z[:, k], None if dz is None else dz[:, k])
        state = eakf_update(state, m, inn, None if r_scale is None else r_scale[:, k])
        uvs.append(state.uv)
        vs.append(state.uv_var)
    return torch.stack(uvs, dim=1), torch.stack(vs, dim=1)


def _pair(x: float | Sequence[float], name: str) -> tuple[float, float]:
    if isinstance(x, (int, float)):
        return float(x), float(x)
    v = tuple(float(e) for e in x)
    if len(v) != 2:
        raise InputError(f"{name}: expected a number or a (u, v) pair, got {x!r}")
    return v[0], v[1]


class EAKF(nn.Module):
    """Batched coloured-noise augmented Kalman filter (METHOD.md section 3).

    Learnable tensors (per axis u, v; ``nn.Parameter`` when ``learnable``, else buffers):
    ``lam_raw``, ``a_raw``, ``b_raw`` (2,) with ``lam = tanh(lam_raw)`` etc. in (-1, 1);
    ``log_q`` (2,) with ``Q = exp(log_q)``; ``log_r`` (2, 2) with ``R = exp(log_r)``, columns
    [position, displacement]. Read them through the properties ``lam``, ``a``, ``b``, ``Q``,
    ``R``. The frame interval ``dt`` (s) and the initial variances ``p0`` (2, 4) are buffers.

    Args:
        frame_rate: frames per second; t = 1 / frame_rate.
        lam, a, b: noise colours, a number or a (u, v) pair, each in (-1, 1).
        q: white-acceleration variance Q (px^2 / s^4), number or pair.
        r: (position, displacement) measurement variances (px^2): a pair used for both axes or
            a 2x2 nested sequence [[u_pos, u_disp], [v_pos, v_disp]].
        p0: initial variances of [position, velocity, previous position, acceleration]
            (px^2, px^2/s^2, px^2, px^2/s^4).
        learnable: register lam, a, b, Q, R as parameters.

    Example:
        >>> f = EAKF(frame_rate=25.0)
        >>> uv, var = f(torch.randn(3, 20, 2) + 100.0)
        >>> tuple(uv.shape), tuple(f.stacked()["Phi"].shape)
        ((3, 20, 2), (8, 8))
    """

    # registered as parameters or buffers in __init__
    lam_raw: Tensor
    a_raw: Tensor
    b_raw: Tensor
    log_q: Tensor
    log_r: Tensor
    dt: Tensor
    p0: Tensor

    def __init__(self, frame_rate: float = _D.frame_rate, lam: float | Sequence[float] = _D.lam,
                 a: float | Sequence[float] = _D.a, b: float | Sequence[float] = _D.b,
                 q: float | Sequence[float] = _D.q,
                 r: Sequence[float] | Sequence[Sequence[float]] = (_D.r_pos, _D.r_disp),
                 p0: Sequence[float] = _D.p0, learnable: bool = _D.learnable) -> None:
        super().__init__()
        if not frame_rate > 0:
            raise InputError(f"frame_rate: expected > 0, got {frame_rate}")
        lam2, a2, b2 = _pair(lam, "lam"), _pair(a, "a"), _pair(b, "b")
        for name, v in (("lam", lam2), ("a", a2), ("b", b2)):
            if not all(-1.0 < e < 1.0 for e in v):
                raise InputError(f"{name}: expected values in (-1, 1), got {v}")
        q2 = _pair(q, "q")
        rt = torch.tensor(r, dtype=torch.float64)
        if rt.shape == (2,):
            rt = rt.expand(2, 2)
        if rt.shape != (2, 2) or not bool((rt > 0).all()):
            raise InputError(f"r: expected positive (pos, disp) or [[u_pos, u_disp], "
                             f"[v_pos, v_disp]], got {r!r}")
        p0t = torch.tensor(p0, dtype=torch.float64)
        if p0t.shape == (4,):
            p0t = p0t.expand(2, 4)
        if p0t.shape != (2, 4) or not bool((p0t > 0).all()):
            raise InputError(f"p0: expected 4 positive variances, got {p0!r}")
        if not all(v > 0 for v in q2):
            raise InputError(f"q: expected > 0, got {q!r}")
        dtype = torch.get_default_dtype()
        raw = {"lam_raw": torch.atanh(torch.tensor(lam2)), "a_raw": torch.atanh(torch.tensor(a2)),
               "b_raw": torch.atanh(torch.tensor(b2)), "log_q": torch.tensor(q2).log(),
               "log_r": rt.log()}
        for name, value in raw.items():
            t = value.to(dtype).clone()
            if learnable:
                self.register_parameter(name, nn.Parameter(t))
            else:
                self.register_buffer(name, t)
        self.register_buffer("dt", torch.tensor(1.0 / frame_rate, dtype=dtype))
        self.register_buffer("p0", p0t.to(dtype).clone())

    @property
    def lam(self) -> Tensor:
        return torch.tanh(self.lam_raw)

    @property
    def a(self) -> Tensor:
        return torch.tanh(self.a_raw)

    @property
    def b(self) -> Tensor:
        return torch.tanh(self.b_raw)

    @property
    def Q(self) -> Tensor:  # noqa: N802 - the math's name
        return self.log_q.exp()

    @property
    def R(self) -> Tensor:  # noqa: N802
        return self.log_r.exp()

    @property
    def frame_rate(self) -> float:
        return 1.0 / float(self.dt)

    def matrices(self) -> EAKFMatrices:
        """Per-axis model matrices from the current parameters (build once per sequence)."""
        return eakf_matrices(self.dt, self.lam, self.a, self.b, self.Q, self.R)

    def stacked(self) -> dict[str, Tensor]:
        """The block-diagonal matrices of eq. 23-24: Phi (8, 8), Gamma (8, 2), H (4, 8),
        Psi (4, 4), H_star (4, 8), Q (2, 2), R (4, 4); state order [u, u', u_prev, w_u, v, ...],
        measurement order [u, du, v, dv]."""
        m = self.matrices()
        gamma = torch.zeros(4, 1, dtype=m.Phi.dtype, device=m.Phi.device)
        gamma[3, 0] = 1.0
        return {"Phi": torch.block_diag(m.Phi[0], m.Phi[1]),
                "Gamma": torch.block_diag(gamma, gamma),
                "H": torch.block_diag(m.H, m.H),
                "Psi": torch.block_diag(m.Psi[0], m.Psi[1]),
                "H_star": torch.block_diag(m.H_star[0], m.H_star[1]),
                "Q": torch.diag(self.Q),
                "R": torch.diag(m.R.reshape(4))}

    def init_state(self, z0: Tensor) -> EAKFState:
        """State at frame 0 from the first position (B, 2) (:func:`eakf_init`)."""
        check_shape(z0, ("B", 2), "z0")
        check_device(z0, "z0", self.dt)
        return eakf_init(as_float(z0, self.dt), self.p0)

    def innovation(self, state: EAKFState, z: Tensor, dz: Tensor | None = None,
                   m: EAKFMatrices | None = None) -> EAKFInnovation:
        """:func:`eakf_innovation` with this filter's matrices (pass ``m`` to reuse them)."""
        return eakf_innovation(state, m or self.matrices(), z, dz)

    def update(self, state: EAKFState, inn: EAKFInnovation, r_scale: Tensor | None = None,
               m: EAKFMatrices | None = None, keep: Tensor | None = None) -> EAKFState:
        """:func:`eakf_update` with this filter's matrices."""
        return eakf_update(state, m or self.matrices(), inn, r_scale, keep)

    def step(self, state: EAKFState, z: Tensor, r_scale: Tensor | None = None,
             dz: Tensor | None = None, m: EAKFMatrices | None = None) -> EAKFState:
        """Feed frame k+1's measurement z (B, 2): delayed update of step k, then prediction.
        ``state.uv`` of the result is the estimate at frame k+1."""
        m = m or self.matrices()
        return eakf_update(state, m, eakf_innovation(state, m, z, dz), r_scale)

    def forward(self, z: Tensor, r_scale: Tensor | None = None, dz: Tensor | None = None
                ) -> tuple[Tensor, Tensor]:
        """Filter whole sequences: z (B, T, 2) -> (uv (B, T, 2), variance (B, T, 2))."""
        check_device(z, "z", self.dt)
        return eakf_filter(z, self.dt, self.lam, self.a, self.b, self.Q, self.R, self.p0,
                           r_scale, dz)


def accel_variance_for(px_per_frame2: float, frame_rate: float) -> float:
    """Q (px^2/s^4) for a white acceleration of ``px_per_frame2`` px/frame^2 (std) at
    ``frame_rate``: helps choose Q in frame units. Example: 1 px/frame^2 at 25 Hz -> 390625."""
    return (px_per_frame2 * frame_rate**2) ** 2

