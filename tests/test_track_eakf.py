"""EAKF (METHOD.md section 3) against Kalman filters written here from the equations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.linalg import block_diag

from torchseam.core.errors import TorchseamError
from torchseam.track.eakf import EAKF, UNKNOWN_SCALE, eakf_filter, eakf_matrices

# --------------------------------------------------------------------------- references


def np_eakf(z: np.ndarray, dt: float, lam: np.ndarray, a: np.ndarray, b: np.ndarray,
            q: np.ndarray, r: np.ndarray, p0: np.ndarray, r_scale: np.ndarray | None = None,
            dz: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The stacked 8-state filter of eq. 18-26, one sequence z (T, 2), plain numpy.

    H* is taken in the closed form printed in METHOD.md, the matrices are stacked
    block-diagonally by hand (eq. 23-24) and the covariance update is the textbook
    ``(I - K H*) P``. ``r_scale`` (T, 2) follows the module docstring's R_eff rule.
    """
    t = dt

    def phi(l: float) -> np.ndarray:
        return np.array([[1, t, 0, 0.5 * t * t], [0, 1, 0, t], [1, 0, 0, 0], [0, 0, 0, l]])

    def h_star(a_: float, b_: float) -> np.ndarray:
        return np.array([[1 - a_, t, 0, 0.5 * t * t], [-b_, t, b_, 0.5 * t * t]])

    Phi = block_diag(phi(lam[0]), phi(lam[1]))
    Gamma = block_diag([[0], [0], [0], [1]], [[0], [0], [0], [1]])
    Hs = block_diag(h_star(a[0], b[0]), h_star(a[1], b[1]))
    psi = np.array([a[0], b[0], a[1], b[1]])
    Q = np.diag(q)
    R = np.diag([r[0, 0], r[0, 1], r[1, 0], r[1, 1]])
    T = len(z)
    x = np.array([z[0, 0], 0, z[0, 0], 0, z[0, 1], 0, z[0, 1], 0], dtype=np.float64)
    P = np.diag(np.asarray(p0).reshape(-1) if np.size(p0) == 8 else np.tile(p0, 2))
    Zp = np.array([z[0, 0], 0.0, z[0, 1], 0.0])
    sp = np.array([1.0, UNKNOWN_SCALE, 1.0, UNKNOWN_SCALE])
    out = {"uv": [x[[0, 4]]], "var": [np.diag(P)[[0, 4]]], "x_post": [None], "P": [P]}
    for k in range(1, T):
        d = z[k] - Zp[[0, 2]] if dz is None else dz[k]
        Z = np.array([z[k, 0], d[0], z[k, 1], d[1]])
        s1 = np.ones(2) if r_scale is None else r_scale[k]
        s = np.array([s1[0], s1[0], s1[1], s1[1]])
        if dz is None:
            s[[1, 3]] = np.maximum(s[[1, 3]], sp[[0, 2]])
        R_eff = R * np.diag(s + psi**2 * (sp - 1.0))
        Zs = Z - psi * Zp                                     # eq. 21
        S = Hs @ P @ Hs.T + R_eff                             # eq. 25
        K = P @ Hs.T @ np.linalg.inv(S)
        x = x + K @ (Zs - Hs @ x)
        P = (np.eye(8) - K @ Hs) @ P
        out["x_post"].append(x.copy())
        x = Phi @ x                                           # eq. 26
        P = Phi @ P @ Phi.T + Gamma @ Q @ Gamma.T
        Zp, sp = Z, s
        out["uv"].append(x[[0, 4]])
        out["var"].append(np.diag(P)[[0, 4]])
        out["P"].append(P)
    return {k: (np.array(v) if k != "x_post" else v) for k, v in out.items()}


def np_ordinary_kf(z: np.ndarray, dt: float, q: float, r: np.ndarray, p0: np.ndarray,
                   dz_from_z: bool = True) -> np.ndarray:
    """Textbook predict-then-update KF on the 4-state of eq. 18 with white noise (lambda = 0)
    and the direct measurement Z(k) = H X(k) + v(k) of eq. 20; one axis, z (T,)."""
    Phi = np.array([[1, dt, 0, 0.5 * dt * dt], [0, 1, 0, dt], [1, 0, 0, 0], [0, 0, 0, 0.0]])
    G = np.array([[0.0], [0], [0], [1]])
    H = np.array([[1.0, 0, 0, 0], [1, 0, -1, 0]])
    x = np.array([z[0], 0, z[0], 0.0])
    P = np.diag(p0)
    out = [x[0]]
    for k in range(1, len(z)):
        x = Phi @ x
        P = Phi @ P @ Phi.T + G @ G.T * q
        Z = np.array([z[k], z[k] - z[k - 1]])
        S = H @ P @ H.T + np.diag(r)
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (Z - H @ x)
        P = (np.eye(4) - K @ H) @ P
        out.append(x[0])
    return np.array(out)


def np_cv_kf(z: np.ndarray, dt: float, q: float, r: float, p_pos: float, p_vel: float
             ) -> np.ndarray:
    """Plain constant-velocity KF, state [u, u'], white acceleration (variance q) entering
    through G = [t^2/2, t], position measurements; z (N, T) vectorised over N sequences."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    G = np.array([0.5 * dt * dt, dt])
    N, T = z.shape
    x = np.stack([z[:, 0], np.zeros(N)], axis=1)
    P = np.broadcast_to(np.diag([p_pos, p_vel]), (N, 2, 2)).copy()
    out = [x[:, 0].copy()]
    for k in range(1, T):
        x = x @ F.T
        P = F @ P @ F.T + q * np.outer(G, G)
        S = P[:, 0, 0] + r
        K = P[:, :, 0] / S[:, None]
        x = x + K * (z[:, k] - x[:, 0])[:, None]
        P = P - K[:, :, None] * P[:, None, 0, :]
        out.append(x[:, 0].copy())
    return np.stack(out, axis=1)


def _params(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"lam": rng.uniform(-0.5, 0.9, 2), "a": rng.uniform(-0.5, 0.8, 2),
            "b": rng.uniform(-0.5, 0.8, 2), "q": rng.uniform(1e3, 1e5, 2),
            "r": rng.uniform(0.2, 3.0, (2, 2)), "p0": np.array([2.0, 900.0, 3.0, 5e4])}


def _torch(p: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in p.items()}


# --------------------------------------------------------------------------- tests


def test_matrices_follow_the_equations() -> None:
    lam, a, b = torch.tensor([0.3, -0.2]), torch.tensor([0.4, 0.1]), torch.tensor([-0.3, 0.6])
    m = eakf_matrices(0.04, lam, a, b, torch.tensor([1.0, 2.0]), torch.ones(2, 2))
    t = 0.04
    for i in range(2):
        Phi = torch.tensor([[1, t, 0, 0.5 * t * t], [0, 1, 0, t], [1, 0, 0, 0],
                            [0, 0, 0, float(lam[i])]])
        torch.testing.assert_close(m.Phi[i], Phi)                                      # eq. 19
        Hs = torch.tensor([[1 - float(a[i]), t, 0, 0.5 * t * t],
                           [-float(b[i]), t, float(b[i]), 0.5 * t * t]])
        torch.testing.assert_close(m.H_star[i], Hs)                                    # eq. 22
        torch.testing.assert_close(m.H_star[i], m.H @ m.Phi[i] - m.Psi[i] @ m.H)
    gamma = torch.tensor([0.0, 0, 0, 1])
    assert torch.count_nonzero(m.H @ gamma) == 0   # H Gamma = 0: the equivalent noise is white
    torch.testing.assert_close(m.GQG[1], torch.outer(gamma, gamma) * 2.0)
    f = EAKF(25.0, lam=(0.3, -0.2), a=(0.4, 0.1), b=(-0.3, 0.6))
    st = f.stacked()                                                                # eq. 23-24
    assert st["Phi"].shape == (8, 8) and st["H_star"].shape == (4, 8)
    assert st["Gamma"].shape == (8, 2) and st["R"].shape == (4, 4) and st["Psi"].shape == (4, 4)
    torch.testing.assert_close(st["Phi"][4:, 4:], m.Phi[1], rtol=1e-5, atol=1e-6)
    assert torch.count_nonzero(st["Phi"][:4, 4:]) == 0
    assert torch.count_nonzero(st["H_star"][:2, 4:]) == 0
    torch.testing.assert_close(st["H_star"], st["H"] @ st["Phi"] - st["Psi"] @ st["H"])


@pytest.mark.parametrize("with_scale", [False, True])
def test_equals_numpy_kalman_filter_on_a_constructed_case(with_scale: bool) -> None:
    rng = np.random.default_rng(10)
    B, T, dt = 3, 40, 0.04
    z = np.cumsum(rng.normal(0, 1.0, (B, T, 2)), axis=1) + rng.normal(0, 0.5, (B, T, 2)) + 100
    scale = np.exp(rng.uniform(0, 4, (B, T, 2))) * (rng.random((B, T, 1)) < 0.3) + 1.0
    ps = [_params(s) for s in range(B)]
    for b in range(B):  # parameters differ per axis (and per case)
        p = ps[b]
        rs = scale[b] if with_scale else None
        ref = np_eakf(z[b], dt, p["lam"], p["a"], p["b"], p["q"], p["r"], p["p0"], rs)
        pt = _torch(p)
        uv, var = eakf_filter(torch.tensor(z[b:b + 1]), dt, pt["lam"], pt["a"], pt["b"],
                              pt["q"], pt["r"], pt["p0"],
                              torch.tensor(scale[b:b + 1]) if with_scale else None)
        np.testing.assert_allclose(uv[0].numpy(), ref["uv"], rtol=0, atol=1e-8)
        np.testing.assert_allclose(var[0].numpy(), ref["var"], rtol=1e-8, atol=1e-10)


def test_module_batches_sequences_and_exposes_the_stacked_state() -> None:
    rng = np.random.default_rng(11)
    z = np.cumsum(rng.normal(0, 1.0, (4, 25, 2)), axis=1)
    f = EAKF(25.0, lam=(0.6, 0.2), a=(0.3, -0.1), b=(0.2, 0.4), q=(3e4, 8e4),
             r=[[0.5, 1.5], [0.8, 2.0]]).double()
    p = {"lam": f.lam.detach().numpy(), "a": f.a.detach().numpy(), "b": f.b.detach().numpy(),
         "q": f.Q.detach().numpy(), "r": f.R.detach().numpy(), "p0": f.p0.numpy()}
    with torch.no_grad():
        uv, _ = f(torch.tensor(z))
        state = f.init_state(torch.tensor(z[:, 0]))
        for k in range(1, 25):
            state = f.step(state, torch.tensor(z[:, k]))
    x8, P8 = state.flat()
    for b in range(4):
        ref = np_eakf(z[b], float(f.dt), p["lam"], p["a"], p["b"], p["q"], p["r"],
                      p["p0"].reshape(-1))
        np.testing.assert_allclose(uv[b].numpy(), ref["uv"], atol=1e-8)
        np.testing.assert_allclose(P8[b].numpy(), ref["P"][-1], rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(x8[b].numpy()[[0, 4]], ref["uv"][-1], atol=1e-8)


def test_reduces_to_the_ordinary_filter_when_a_b_lambda_are_zero() -> None:
    rng = np.random.default_rng(12)
    T, dt, q = 60, 0.04, 2e4
    z = np.cumsum(np.cumsum(rng.normal(0, 0.1, (1, T, 2)), axis=1), axis=1) \
        + rng.normal(0, 0.7, (1, T, 2))
    zero = torch.zeros(2, dtype=torch.float64)
    p0 = np.array([1.5, 400.0, 1.5, q])  # w starts at its stationary variance Q (lambda = 0)
    r = np.array([0.5, 1.2])
    uv, _ = eakf_filter(torch.tensor(z), dt, zero, zero, zero, torch.full((2,), q),
                        torch.tensor(np.stack([r, r])), torch.tensor(p0))
    # (i) the textbook KF on the same 4-state with the direct measurement of eq. 20: with
    # Psi = 0, Z* = Z(k+1) and X(k+1|k) after the delayed update is exactly its X(k+1|k+1)
    for ax in range(2):
        np.testing.assert_allclose(uv[0, :, ax].numpy(), np_ordinary_kf(z[0, :, ax], dt, q, r, p0),
                                   atol=1e-9)
    # (ii) the plain constant-velocity KF when the displacement row carries no information
    uv_pos, _ = eakf_filter(torch.tensor(z), dt, zero, zero, zero, torch.full((2,), q),
                            torch.tensor([[0.5, 1e14]] * 2), torch.tensor(p0))
    cv = np_cv_kf(z[0].T, dt, q, 0.5, p0[0], p0[1])
    np.testing.assert_allclose(uv_pos[0].numpy(), cv.T, atol=1e-5)


def _coloured_trajectories(rng: np.random.Generator, N: int, T: int, dt: float, lam: float,
                           q: float, a: float, r: float) -> tuple[np.ndarray, np.ndarray]:
    """Truth with coloured acceleration (eq. 12, 16) and positions with AR(1) noise (eq. 17)."""
    u = np.zeros((N, T))
    vel = rng.normal(0, 10.0, N)
    w = rng.normal(0, np.sqrt(q / (1 - lam**2)), N)
    pos = np.zeros(N)
    m = rng.normal(0, np.sqrt(r / (1 - a * a)), N)
    z = np.zeros((N, T))
    for k in range(T):
        u[:, k], z[:, k] = pos, pos + m
        pos = pos + vel * dt + 0.5 * w * dt * dt
        vel = vel + w * dt
        w = lam * w + rng.normal(0, np.sqrt(q), N)
        m = a * m + rng.normal(0, np.sqrt(r), N)
    return u, z


def test_beats_a_constant_velocity_filter_on_coloured_noise() -> None:
    rng = np.random.default_rng(13)
    N, T, dt, lam, a = 48, 200, 0.04, 0.9, 0.8
    q = (0.02 * 625) ** 2 * (1 - lam**2)  # stationary acceleration 0.02 px/frame^2
    r = 1.0 * (1 - a * a)                 # stationary measurement noise 1 px, AR(1) a = 0.8
    u, z = _coloured_trajectories(rng, N, T, dt, lam, q, a, r)
    zz = torch.tensor(np.stack([z, z], axis=-1))
    f2 = torch.full((2,), 1.0, dtype=torch.float64)
    r_disp = 2 * (1 - a) * r / (1 - a * a)  # variance of z(k) - z(k-1) from the noise
    p0 = torch.tensor([1.0, 100.0, 1.0, q / (1 - lam**2)])
    uv, _ = eakf_filter(zz, dt, f2 * lam, f2 * a, f2 * 0.0, f2 * q,
                        torch.tensor([[r, r_disp]] * 2), p0)
    err = uv[..., 0].numpy() - u
    rmse_seq = np.sqrt((err[:, 10:] ** 2).mean(axis=1))
    rmse_eakf = np.sqrt((rmse_seq**2).mean())
    # the ordinary filter gets its best tuning in hindsight: only the ratio q / r matters once
    # started, so scan it over eight decades
    best, best_seq = np.inf, None
    for ratio in 10.0 ** np.arange(-1.0, 7.01, 0.25):
        est = np_cv_kf(z, dt, ratio, 1.0, 1.0, 100.0)
        s = np.sqrt(((est - u)[:, 10:] ** 2).mean(axis=1))
        if np.sqrt((s**2).mean()) < best:
            best, best_seq = np.sqrt((s**2).mean()), s
    raw = np.sqrt(((z - u)[:, 10:] ** 2).mean())
    assert rmse_eakf < 0.97 * best < raw
    assert (rmse_seq < best_seq).mean() > 0.75  # and on most seeds, not just on average


def test_one_frame_delay_is_explicit() -> None:
    f = EAKF(25.0, lam=0.0, a=0.5, b=0.2, q=1e3, r=(1e-6, 1e-6)).double()
    v = torch.tensor([[2.0, -1.0]], dtype=torch.float64)  # px / frame, exact straight line
    z = torch.tensor([[50.0, 40.0]], dtype=torch.float64) + v * torch.arange(12.0).double()[:, None]
    with torch.no_grad():
        s0 = f.init_state(z[0:1])
        assert s0.k == 0 and s0.x_post is None  # frame 0: nothing to update yet
        s1 = f.step(s0, z[1:2])
        assert s1.k == 1 and s1.x_post is not None
        # the update that ran at frame 1 is the one of step 0: X(0|0), conditioned on Z*(0)
        # = Z(1) - Psi Z(0); it estimates frame 0's position, and propagating it gives frame 1
        m = f.matrices()
        torch.testing.assert_close(s1.x, (m.Phi @ s1.x_post[..., None])[..., 0])
        assert abs(float(s1.x_post[0, 0, 0]) - 50.0) < 0.5  # frame 0 at 50, frame 1 at 52
        s = s1
        outs = [s0.uv, s1.uv]
        for k in range(2, 12):
            s = f.step(s, z[k:k + 1])
            outs.append(s.uv)
            # X(k-1|k-1): the position of the previous frame (not of the newest one)
            assert float((s.x_post[0, :, 0] - z[k - 1]).abs().max()) < 1e-3
    uv = torch.cat(outs)
    # the estimate at frame k already uses z(k): no lag on a noiseless line
    assert float((uv[3:] - z[3:]).abs().max()) < 1e-3
    # causality: changing z(k) changes the estimates from frame k on, never before
    z2 = z.clone()
    z2[6] += 3.0
    with torch.no_grad():
        uv2, _ = f(z2[None])
        uv1, _ = f(z[None])
    torch.testing.assert_close(uv2[0, :6], uv1[0, :6])
    assert float((uv2[0, 6] - uv1[0, 6]).abs().max()) > 0.5


def test_noise_scale_makes_the_filter_ignore_an_outlier() -> None:
    T = 30
    t = torch.arange(T, dtype=torch.float64)
    truth = torch.stack([100 + 1.5 * t, 80 - 0.5 * t], dim=1)
    g = torch.Generator().manual_seed(0)
    z = truth + 0.3 * torch.randn(T, 2, generator=g, dtype=torch.float64)
    z[15] += torch.tensor([25.0, -18.0], dtype=torch.float64)
    f = EAKF(25.0, q=2e3, r=(0.1, 0.2)).double()
    scale = torch.ones(1, T, dtype=torch.float64)
    scale[0, 15] = 1e6
    with torch.no_grad():
        trusting, _ = f(z[None])
        guarded, _ = f(z[None], r_scale=scale)
    assert float((trusting[0, 15] - truth[15]).norm()) > 5.0
    # the scaled frame also spoils the next equivalent observation (Z*(k) holds Psi Z(k)):
    # R_eff there is inflated too, so the frame after the outlier is not thrown either
    assert float((guarded[0, 15:] - truth[15:]).norm(dim=1).max()) < 1.0


def test_gradcheck_wrt_lambda_a_b_q_r() -> None:
    rng = np.random.default_rng(14)
    # frame units (dt = 1) keep the finite differences well conditioned
    z = torch.tensor(np.cumsum(rng.normal(0, 1, (2, 6, 2)), axis=1))
    scale = torch.tensor(1.0 + rng.random((2, 6, 2)) * 3)
    inputs = (torch.tensor([0.5, -0.3]), torch.tensor([0.3, 0.2]), torch.tensor([-0.2, 0.4]),
              torch.tensor([0.4, 0.9]), torch.tensor([[0.5, 1.0], [0.7, 1.3]]))
    inputs = tuple(x.double().requires_grad_(True) for x in inputs)
    p0 = torch.tensor([1.0, 2.0, 1.0, 0.5], dtype=torch.float64)

    def fn(lam, a, b, q, r):
        uv, var = eakf_filter(z, 1.0, lam, a, b, q, r, p0, scale)
        return uv, var

    assert torch.autograd.gradcheck(fn, inputs)
    # and through the module's raw parameters (tanh / exp parameterisation)
    f = EAKF(25.0).double()
    uv, _ = f(z * 5.0, r_scale=scale)
    uv.pow(2).sum().backward()
    for name in ("lam_raw", "a_raw", "b_raw", "log_q", "log_r"):
        g = getattr(f, name).grad
        assert g is not None and bool(torch.isfinite(g).all()) and float(g.abs().sum()) > 0, name


def test_gradients_still_flow_after_a_run_in_inference_mode() -> None:
    """The live loop runs the filter under inference_mode; a later training run in the same
    process must still get gradients (regression: a cache filled with inference tensors)."""
    from torchseam.track import eakf as eakf_mod

    eakf_mod._ADJ.clear()
    z = torch.cumsum(torch.randn(2, 8, 2, generator=torch.Generator().manual_seed(3)), 1)
    f = EAKF(25.0)
    with torch.inference_mode():
        f(z)
    uv, _ = f(z)
    uv.pow(2).sum().backward()
    assert f.lam_raw.grad is not None and bool(torch.isfinite(f.lam_raw.grad).all())


def test_parameters_stay_in_range() -> None:
    f = EAKF()
    with torch.no_grad():
        f.lam_raw.fill_(40.0)
        f.a_raw.fill_(-40.0)
        f.log_q.fill_(-200.0)
        assert float(f.lam.max()) <= 1.0 and float(f.a.min()) >= -1.0
        assert float(f.Q.min()) >= 0.0 and f.R.shape == (2, 2) and bool((f.R > 0).all())


def test_bad_inputs_raise_clear_errors() -> None:
    with pytest.raises(TorchseamError, match="lam"):
        EAKF(lam=1.2)
    with pytest.raises(TorchseamError, match="frame_rate"):
        EAKF(frame_rate=0.0)
    with pytest.raises(TorchseamError, match="r:"):
        EAKF(r=(1.0, -1.0))
    f = EAKF()
    with pytest.raises(TorchseamError, match=r"z: expected shape \(B, T, 2\)"):
        f(torch.zeros(5, 2))
    with pytest.raises(TorchseamError, match="r_scale"):
        f(torch.zeros(1, 5, 2), r_scale=torch.ones(1, 4))
    s = f.init_state(torch.zeros(2, 2))
    with pytest.raises(TorchseamError, match=r"z: expected shape \(2, 2\)"):
        f.step(s, torch.zeros(3, 2))
