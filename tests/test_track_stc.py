"""STC (METHOD.md section 2) against a direct per-sequence numpy implementation of the equations."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from torchseam.core.errors import TorchseamError
from torchseam.track.stc import (
    STC,
    confidence_map,
    extract_windows,
    hamming_window_2d,
    locate_peak,
    peak_quality,
    weight_window,
)

# --------------------------------------------------------------------------- numpy reference


def np_stc(frames: np.ndarray, uv0: np.ndarray, size: tuple[int, int], alpha: float,
           beta: float, rho: float, sigma: float, eps: float, scale_update: bool,
           lam: float = 0.25, num: int = 5) -> tuple[list, list, list]:
    """One sequence, written from METHOD.md eq. 1-11 and the reference MATLAB loop with full
    complex ``numpy.fft.fft2``; integer argmax (eq. 11)."""
    h, w = size
    H_img, W_img = frames.shape[1:]
    rs = np.arange(h) - h // 2
    cs = np.arange(w) - w // 2
    dist = rs[:, None] ** 2 + cs[None, :] ** 2
    conf = np.exp(-((np.sqrt(dist) / alpha) ** beta))          # eq. 1
    conf /= conf.sum()
    conff = np.fft.fft2(conf)
    ham = np.outer(np.hamming(h), np.hamming(w))

    def get_context(img: np.ndarray, pos: np.ndarray, window: np.ndarray) -> np.ndarray:
        u, v = int(np.floor(pos[0] + 0.5)), int(np.floor(pos[1] + 0.5))
        ys = np.clip(v - h // 2 + np.arange(h), 0, H_img - 1)
        xs = np.clip(u - w // 2 + np.arange(w), 0, W_img - 1)
        out = img[np.ix_(ys, xs)].astype(np.float64)
        return window * (out - out.mean())                       # eq. 4

    pos = np.asarray(uv0, dtype=np.float64).copy()
    scale, maxconf = 1.0, []
    positions, responses, models = [], [], []
    Hf = None
    for f, img in enumerate(frames, start=1):
        sigma = sigma * scale
        window = ham * np.exp(-dist / sigma**2)                   # eq. 5
        window /= window.sum()
        cp = get_context(img, pos, window)
        if f > 1:
            confmap = np.real(np.fft.ifft2(Hf * np.fft.fft2(cp)))  # eq. 10
            row, col = np.unravel_index(np.argmax(confmap), confmap.shape)  # eq. 11
            pos = pos + np.array([col - w // 2, row - h // 2], dtype=np.float64)
            responses.append(confmap)
            cp = get_context(img, pos, window)
            if scale_update:
                maxconf.append(np.real(np.fft.ifft2(Hf * np.fft.fft2(cp))).max())
                if f % (num + 2) == 0:
                    s = np.mean([np.sqrt(maxconf[-k] / maxconf[-k - 1]) for k in range(1, num + 1)])
                    scale = (1 - lam) * scale + lam * s
        hscf = conff / (np.fft.fft2(cp) + eps)                    # eq. 8
        Hf = hscf if f == 1 else (1 - rho) * Hf + rho * hscf      # eq. 9
        positions.append(pos.copy())
        models.append(Hf)
    return positions, responses, models


def textured_sequence(rng: np.random.Generator, T: int, size: tuple[int, int],
                      start: tuple[int, int], noise: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random texture translated by integer steps (+ a little noise)."""
    H, W = size
    big = ndimage.gaussian_filter(rng.standard_normal((H + 80, W + 80)), 2.0)
    big[40 + H // 2 - 3:40 + H // 2 + 3, 40 + W // 2 - 3:40 + W // 2 + 3] += 1.0
    steps = rng.integers(-2, 3, size=(T, 2))
    steps[0] = 0
    off = np.cumsum(steps, axis=0)
    frames = np.stack([np.roll(big, (o[1], o[0]), axis=(0, 1))[40:40 + H, 40:40 + W]
                       for o in off])
    frames = frames + noise * rng.standard_normal(frames.shape)
    uv = np.array(start, dtype=np.float64) + off
    return frames, uv


@pytest.mark.parametrize("scale_update", [False, True])
def test_batched_stc_equals_per_sequence_numpy(scale_update: bool) -> None:
    rng = np.random.default_rng(0)
    size, T = (30, 41), 16  # odd width, non-square: catches transposed or shifted centres
    starts = [(60, 40), (12, 8), (100, 70)]  # the second one sits on the border (replicate)
    seqs = [textured_sequence(rng, T, (90, 120), s) for s in starts]
    frames = torch.tensor(np.stack([s[0] for s in seqs]))
    uv0 = torch.tensor(np.stack([s[1][0] for s in seqs]))
    stc = STC(size, (12, 18), peak="argmax", scale_update=scale_update).double()
    stc.requires_grad_(False)
    with torch.no_grad():
        state = stc.init_state(frames[:, 0], uv0)
        pos, resp, models = [state.pos], [], [state.H_f]
        for t in range(1, T):
            det = stc.detect(state, frames[:, t])
            state = stc.learn(state, frames[:, t], det.uv)
            pos.append(det.uv)
            resp.append(det.response)
            models.append(state.H_f)
    for b, (fr, _) in enumerate(seqs):
        p_np, r_np, m_np = np_stc(fr, uv0[b].numpy(), size, float(stc.alpha), float(stc.beta),
                                  float(stc.rho), float(stc.sigma), stc.eps, scale_update)
        np.testing.assert_array_equal(np.stack([p[b].numpy() for p in pos]), np.stack(p_np))
        r_t = np.stack([r[b].numpy() for r in resp])
        r_n = np.stack(r_np)
        assert np.abs(r_t - r_n).max() <= 1e-5 * np.abs(r_n).max()
        m_t = np.stack([m[b].numpy() for m in models])
        m_n = np.stack(m_np)[..., : size[1] // 2 + 1]  # the rfft2 half spectrum
        assert np.abs(m_t - m_n).max() <= 1e-5 * np.abs(m_n).max()
    assert float(stc.sigma) == pytest.approx(15.0)  # mean target side
    moved = (state.sigma - stc.sigma).abs().max().item()
    assert (moved > 1e-3) if scale_update else (moved == 0.0)  # the scale update ran


def test_tracks_integer_translation_exactly() -> None:
    rng = np.random.default_rng(1)
    fr, uv = textured_sequence(rng, 30, (100, 120), (60, 50), noise=0.0)
    stc = STC((32, 32), (16, 16), peak="argmax").double()
    with torch.no_grad():
        out, q = stc(torch.tensor(fr)[None], torch.tensor(uv[:1]))
    np.testing.assert_array_equal(out[0].numpy(), uv)
    assert out.shape == (1, 30, 2) and q["psr"].shape == (1, 30)
    assert bool((q["psr"][0, 1:] > 10).all())


def test_subpixel_tracking_of_subpixel_motion() -> None:
    # a blob moving 0.3 px / frame: sub-pixel peaks follow it; integer argmax cannot
    H, W, T = 80, 100, 25
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    rng = np.random.default_rng(2)
    blobs = np.concatenate([[[0.0, 0.0, 1.0, 2.5]], np.column_stack([
        rng.uniform(-12, 12, (8, 2)), rng.uniform(0.3, 0.8, 8), rng.uniform(1.0, 2.5, 8)])])
    truth = np.stack([50 + 0.3 * np.arange(T), 40 + 0.2 * np.arange(T)], axis=1)
    frames = np.stack([sum(a * np.exp(-((xx - u - du) ** 2 + (yy - v - dv) ** 2) / (2 * s * s))
                           for du, dv, a, s in blobs) for u, v in truth])
    frames += 0.01 * rng.standard_normal(frames.shape)
    errs = {}
    for mode in ("subpixel", "argmax"):
        stc = STC((32, 32), (16, 16), peak=mode).double()
        with torch.no_grad():
            out, _ = stc(torch.tensor(frames)[None], torch.tensor(truth[:1]))
        errs[mode] = np.sqrt(((out[0].numpy() - truth) ** 2).sum(1).mean())
    assert errs["subpixel"] < 0.15  # 0.2 without centring the learnt map on the sub-pixel target
    assert errs["subpixel"] < errs["argmax"]


# --------------------------------------------------------------------------- windows / crops


def test_maps_are_normalised_and_centred() -> None:
    c = confidence_map((31, 40), 2.25, 1.0, dtype=torch.float64)
    assert abs(float(c.sum()) - 1.0) < 1e-12
    assert divmod(int(c.argmax()), 40) == (15, 20)
    # eq. 1 by hand at one offset (du, dv) = (3, -4): r = 5
    assert float(c[11, 23] / c[15, 20]) == pytest.approx(np.exp(-5 / 2.25), rel=1e-12)
    w = weight_window((31, 40), torch.tensor([4.0, 8.0], dtype=torch.float64))
    assert w.shape == (2, 31, 40)
    np.testing.assert_allclose(w.sum(dim=(1, 2)).numpy(), 1.0, rtol=1e-12)
    ham = hamming_window_2d((31, 40), dtype=torch.float64)
    np.testing.assert_allclose(ham.numpy(), np.outer(np.hamming(31), np.hamming(40)), atol=1e-12)
    ratio = (w[0, 15, 22] / w[0, 15, 20]) / (ham[15, 22] / ham[15, 20])
    assert float(ratio) == pytest.approx(np.exp(-4 / 16.0), rel=1e-10)  # exp(-r^2 / sigma^2)


def test_extract_windows_nearest_matches_numpy_with_replicated_border() -> None:
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, size=(2, 40, 50), dtype=np.uint8)
    centres = np.array([[20.4, 10.6], [1.2, 38.7]])  # second one hangs over two borders
    out = extract_windows(torch.tensor(img), torch.tensor(centres), (9, 12))
    assert out.dtype == torch.float64 and out.shape == (2, 9, 12)
    for b, (u, v) in enumerate(centres):
        ui, vi = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
        ys = np.clip(vi - 4 + np.arange(9), 0, 39)
        xs = np.clip(ui - 6 + np.arange(12), 0, 49)
        np.testing.assert_array_equal(out[b].numpy(), img[b][np.ix_(ys, xs)])


def test_extract_windows_bilinear_matches_map_coordinates_and_has_gradients() -> None:
    rng = np.random.default_rng(4)
    img = rng.random((2, 30, 40))
    centres = torch.tensor([[17.3, 11.8], [2.6, 27.45]], dtype=torch.float64, requires_grad=True)
    out = extract_windows(torch.tensor(img), centres, (7, 8), mode="bilinear")
    for b in range(2):
        u, v = centres[b].detach().numpy()
        rows = v - 3 + np.arange(7)
        cols = u - 4 + np.arange(8)
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        ref = ndimage.map_coordinates(img[b], [rr, cc], order=1, mode="nearest")
        np.testing.assert_allclose(out[b].detach().numpy(), ref, atol=1e-12)
    near = extract_windows(torch.tensor(img), torch.tensor([[17.0, 11.0]]).double().expand(2, 2),
                           (7, 8))
    at_int = extract_windows(torch.tensor(img), torch.tensor([[17.0, 11.0]]).double().expand(2, 2),
                             (7, 8), mode="bilinear")
    np.testing.assert_allclose(near.numpy(), at_int.numpy(), atol=1e-12)
    assert torch.autograd.gradcheck(
        lambda c: extract_windows(torch.tensor(img), c, (7, 8), mode="bilinear"),
        (torch.tensor([[17.3, 11.8], [12.6, 17.45]], dtype=torch.float64, requires_grad=True),))


# --------------------------------------------------------------------------- peaks and quality


def _gauss_map(size: tuple[int, int], peaks: list[tuple[float, float, float]], s: float = 1.5
               ) -> torch.Tensor:
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    m = sum(a * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * s * s)) for u, v, a in peaks)
    return torch.tensor(m)[None]


def test_locate_peak_modes_recover_subpixel_offsets() -> None:
    m = _gauss_map((32, 32), [(16 + 3.3, 16 - 2.6, 1.0)])
    np.testing.assert_allclose(locate_peak(m, "argmax")[0].numpy(), [3.0, -3.0])
    sub = locate_peak(m, "subpixel")[0].numpy()
    assert np.abs(sub - [3.3, -2.6]).max() < 0.12
    # soft-argmax: the expectation under softmax((m - mean) / (max - mean) / T)
    for T in (0.05, 0.2):
        soft = locate_peak(m, "soft", temperature=T)[0].numpy()
        z = (m[0] - m.mean()) / (m.max() - m.mean()) / T
        p = torch.softmax(z.flatten(), 0).reshape(32, 32).numpy()
        ii, jj = np.mgrid[0:32, 0:32] - 16
        np.testing.assert_allclose(soft, [(p * jj).sum(), (p * ii).sum()], atol=1e-9)
    assert np.abs(locate_peak(m, "soft", temperature=1e-3)[0].numpy() - [3, -3]).max() < 1e-6
    # differentiable w.r.t. the map for the training modes
    for mode in ("subpixel", "soft"):
        mm = m.clone().requires_grad_(True)
        locate_peak(mm, mode).sum().backward()
        assert float(mm.grad.abs().sum()) > 0


def test_peak_quality_separates_single_double_and_noise_maps() -> None:
    single = _gauss_map((48, 48), [(24, 24, 1.0)])
    double = _gauss_map((48, 48), [(14, 14, 1.0), (34, 30, 0.97)])
    noise = torch.tensor(np.random.default_rng(5).standard_normal((1, 48, 48)))
    qs, qd, qn = (peak_quality(m) for m in (single, double, noise))
    assert qs["n_peaks"].item() == 1 and qs["second_ratio"].item() < 0.05
    assert qs["psr"].item() > 20
    assert qd["n_peaks"].item() == 2 and qd["second_ratio"].item() > 0.9
    assert qn["psr"].item() < 6 and qn["second_ratio"].item() > 0.6
    assert qn["psr"].item() < qd["psr"].item() < qs["psr"].item()


# --------------------------------------------------------------------------- parameters, checks


def test_parameters_stay_positive_and_receive_gradients() -> None:
    rng = np.random.default_rng(6)
    fr, uv = textured_sequence(rng, 6, (80, 90), (45, 40))
    stc = STC((24, 24), (12, 12), peak="soft").double()
    out, _ = stc(torch.tensor(fr)[None] + 0.3 * torch.tensor(rng.random((1, 6, 80, 90))),
                 torch.tensor(uv[:1]))
    loss = ((out[0] - torch.tensor(uv)) ** 2).sum()
    loss.backward()
    for name in ("log_alpha", "log_beta", "logit_rho", "log_sigma", "log_temperature"):
        g = getattr(stc, name).grad
        assert g is not None and torch.isfinite(g) and float(g) != 0.0, name
    with torch.no_grad():
        stc.log_alpha.fill_(-50.0)
        stc.logit_rho.fill_(80.0)
        assert float(stc.alpha) > 0 and 0 < float(stc.rho) <= 1


def test_truncated_bptt_and_float32_default() -> None:
    rng = np.random.default_rng(7)
    fr, uv = textured_sequence(rng, 8, (70, 80), (40, 35))
    stc = STC((24, 24), (12, 12))
    out, _ = stc(torch.tensor(fr, dtype=torch.float32)[None], torch.tensor(uv[:1]).float(),
                 detach_every=3)
    assert out.dtype == torch.float32
    out.sum().backward()  # no "backward through the graph a second time" error
    assert np.abs(out[0].detach().numpy() - uv).max() <= 1.0


def test_bad_inputs_raise_clear_errors() -> None:
    stc = STC((16, 16), (8, 8))
    with pytest.raises(TorchseamError, match=r"frames0: expected shape \(B, Himg, Wimg\)"):
        stc.init_state(torch.zeros(30, 30), torch.zeros(1, 2))
    with pytest.raises(TorchseamError, match=r"uv0: expected shape \(2, 2\)"):
        stc.init_state(torch.zeros(2, 30, 30), torch.zeros(2, 3))
    with pytest.raises(TorchseamError, match="centres"):
        extract_windows(torch.zeros(2, 30, 30), torch.zeros(3, 2), (5, 5))
    with pytest.raises(TorchseamError, match="mode"):
        extract_windows(torch.zeros(2, 30, 30), torch.zeros(2, 2), (5, 5), mode="cubic")
    with pytest.raises(TorchseamError, match="rho"):
        STC(rho=1.5)
    state = stc.init_state(torch.zeros(2, 30, 30), torch.full((2, 2), 15.0))
    with pytest.raises(TorchseamError, match="batch size 2"):
        stc.detect(state, torch.zeros(3, 30, 30))
    with pytest.raises(TorchseamError, match="init"):
        STC().step(torch.zeros(1, 30, 30))


def test_regularised_and_anchored_stc_is_structural_and_fittable() -> None:
    """reg / anchor off: no parameter, the paper's numbers; on: the start model is the mean of
    the first ``anchor_frames`` models and stays put, and both parameters get gradients."""
    from torchseam.track.stc import learn_spatial_context, learn_spatial_context_reg

    paper = STC(window=(32, 32), target=(16, 16))
    assert "log_reg" not in paper.state_dict() and "logit_anchor" not in paper.state_dict()
    assert float(paper.reg) == 0.0 and float(paper.anchor) == 0.0
    # reg -> 0 is eq. 8
    g = torch.Generator().manual_seed(0)
    c_f = torch.fft.rfft2(confidence_map((16, 16), 2.25, 1.0, dtype=torch.float64))
    p_f = torch.fft.rfft2(torch.randn(3, 16, 16, generator=g, dtype=torch.float64))
    torch.testing.assert_close(learn_spatial_context_reg(c_f, p_f, 0.0, 0.0),
                               learn_spatial_context(c_f, p_f, 0.0))
    # a flat window (a saturated flash): no NaN
    flat = learn_spatial_context_reg(c_f, torch.zeros_like(p_f), 5.0)
    assert torch.isfinite(torch.view_as_real(flat)).all()
    with pytest.raises(TorchseamError, match="reg"):
        STC(reg=-1.0)
    with pytest.raises(TorchseamError, match="anchor"):
        STC(anchor=1.0)
    with pytest.raises(TorchseamError, match="anchor_frames"):
        STC(anchor=0.5, anchor_frames=0)

    stc = STC(window=(32, 32), target=(16, 16), reg=5.0, anchor=0.4, anchor_frames=3)
    assert {"log_reg", "logit_anchor"} <= set(dict(stc.named_parameters()))
    frames = torch.rand(2, 8, 64, 80, generator=g) * 50
    frames[:, :, 30:33, :] += 200.0
    uv0 = torch.tensor([[40.0, 31.0], [38.0, 31.5]])
    state = stc.init_state(frames[:, 0], uv0)
    refs = [state.H_ref]
    for t in range(1, 8):
        state, uv, _ = stc.track(state, frames[:, t])
        refs.append(state.H_ref)
    assert refs[3] is refs[2] and refs[7] is refs[2]  # frozen after anchor_frames
    assert torch.isfinite(uv).all()
    uv[:, 0].sum().backward()
    assert stc.log_reg.grad is not None and torch.isfinite(stc.log_reg.grad)
    assert stc.logit_anchor.grad is not None and torch.isfinite(stc.logit_anchor.grad)
    assert float(stc.log_reg.grad.abs()) > 0 and float(stc.logit_anchor.grad.abs()) > 0


def test_block_maxima_are_amaxs_with_and_without_a_gradient():
    """The 2x2-block maxima of the peak analysis: the values of the strided amax (ties
    included) in inference, amax itself (its gradient) when a gradient is carried."""
    from torchseam.track.stc import _block_max

    torch.manual_seed(3)
    for dtype in (torch.float32, torch.float64):
        r = torch.randn(6, 64, 64, dtype=dtype).clamp_max(1.2)  # ties at the clamp
        assert torch.equal(_block_max(r), r.reshape(6, 32, 2, 32, 2).amax(dim=(2, 4)))
    x = torch.tensor([[[1.0, 1.0], [1.0, 0.0]]], requires_grad=True)
    _block_max(x).sum().backward()
    assert x.grad is not None
    assert torch.allclose(x.grad, torch.tensor([[[1.0, 1.0], [1.0, 0.0]]]) / 3)
