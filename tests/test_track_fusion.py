"""EAKF-STC (METHOD.md section 4) on synthetic laser-stripe sequences with known ground truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchseam.core.errors import TorchseamError
from torchseam.sim.vstripe import VStripeSequence, v_stripe_sequence
from torchseam.track import EAKFSTC, STC, DriftGuard, TrackerConfig, TrackStatus

# heavy clutter near the corner (a quarter of the frames with bright blobs, a quarter with
# spatter streaks) and two stretches where the stripe vanishes
HEAVY = dict(noise_sigma=8.0, blob_prob=0.25, streak_prob=0.25, vanish=((40, 45), (85, 89)))


@pytest.fixture(scope="module")
def heavy() -> VStripeSequence:
    return v_stripe_sequence(6, 120, seed=0, **HEAVY)


@pytest.fixture(scope="module")
def heavy_runs(heavy: VStripeSequence) -> tuple:
    with torch.inference_mode():
        fused = EAKFSTC().run_sequence(heavy.frames, heavy.uv[:, 0])
        plain, _ = STC()(heavy.frames, heavy.uv[:, 0])
    return fused, plain


def _err(uv: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    return (uv - truth).norm(dim=-1)


def test_stays_on_the_stripe_under_clutter_where_plain_stc_drifts(heavy, heavy_runs) -> None:
    fused, plain = heavy_runs
    e, e_stc = _err(fused.uv, heavy.uv), _err(plain, heavy.uv)
    rmse = float(e.pow(2).mean().sqrt())
    assert rmse < 1.5
    assert float(e.flatten().quantile(0.95)) < 3.0
    assert float(e.max()) < 8.0
    # plain STC learns the clutter and the empty frames and walks off the stripe
    assert float(e_stc.pow(2).mean().sqrt()) > 10 * rmse
    assert int((e_stc.amax(dim=1) > 15.0).sum()) >= 4
    # the raw STC measurement inside the fusion is often far off: the guard is doing the work
    assert float((_err(fused.z, heavy.uv) > 5.0).float().mean()) > 0.1


def test_coasts_through_a_vanished_stripe_and_returns_to_tracked(heavy, heavy_runs) -> None:
    fused, _ = heavy_runs
    status, vanished = fused.status, ~heavy.visible
    assert float((status[vanished] != TrackStatus.TRACKED).float().mean()) > 0.9
    e = _err(fused.uv, heavy.uv)
    for end in (45, 89):
        back = status[:, end:end + 5] == TrackStatus.TRACKED
        assert bool(back.any(dim=1).all()), f"not tracked again within 5 frames of {end}"
        assert float(e[:, end + 8:end + 12].max()) < 5.0
    assert float((status[heavy.visible] == TrackStatus.TRACKED).float().mean()) > 0.6


def test_clean_sequence_is_tracked_to_subpixel_accuracy() -> None:
    seq = v_stripe_sequence(4, 100, seed=1, noise_sigma=6.0)
    with torch.inference_mode():
        res = EAKFSTC().run_sequence(seq.frames, seq.uv[:, 0])
    e = _err(res.uv, seq.uv)
    assert float(e.pow(2).mean().sqrt()) < 0.8 and float(e.max()) < 2.0
    assert float((res.status == TrackStatus.TRACKED).float().mean()) > 0.98


def test_long_dropout_goes_lost_then_reacquires() -> None:
    seq = v_stripe_sequence(4, 100, seed=2, noise_sigma=6.0, vanish=((30, 55),), amplitude=6.0)
    with torch.inference_mode():
        res = EAKFSTC(max_coast=5).run_sequence(seq.frames, seq.uv[:, 0])
    assert bool((res.status[:, 30:55] == TrackStatus.LOST).any(dim=1).all())
    assert bool((res.status[:, :30] == TrackStatus.TRACKED).all())
    assert float((res.status[:, -20:] == TrackStatus.TRACKED).float().mean()) > 0.9
    assert float(_err(res.uv[:, -20:], seq.uv[:, -20:]).max()) < 2.0


def test_step_api_equals_run_sequence_and_records_timings() -> None:
    seq = v_stripe_sequence(2, 15, seed=3, noise_sigma=8.0, blob_prob=0.3)
    trk = EAKFSTC()
    with torch.inference_mode():
        res = trk.run_sequence(seq.frames, seq.uv[:, 0])
        trk.init(seq.frames[:, 0].round().to(torch.uint8), seq.uv[:, 0])  # uint8 frames too
        trk.init(seq.frames[:, 0], seq.uv[:, 0])
        outs = [trk.step(seq.frames[:, t]) for t in range(1, 15)]
    uv = torch.stack([o[0] for o in outs], dim=1)
    torch.testing.assert_close(uv, res.uv[:, 1:])
    torch.testing.assert_close(torch.stack([o[1] for o in outs], 1), res.status[:, 1:])
    q = outs[-1][2]
    assert {"z", "trust", "psr", "second_ratio", "n_peaks", "d2", "r_scale", "std"} <= set(q)
    assert q["z"].shape == (2, 2) and q["trust"].shape == (2,)
    ms = trk.timings_ms()
    assert len(ms) == 14 and all(0.0 < t < 1000.0 for t in ms)


def test_reanchor_moves_onto_the_fix_and_keeps_the_velocity() -> None:
    """A drifted track moved onto the true point by reanchor() tracks from there (and its
    filter velocity is the one it had, not zero as after a restart)."""
    seq = v_stripe_sequence(2, 60, seed=4, noise_sigma=6.0)
    trk = EAKFSTC()
    with torch.inference_mode():
        trk.init(seq.frames[:, 0], seq.uv[:, 0] + torch.tensor([4.0, -3.0]))  # a bad start
        for t in range(1, 30):
            trk.step(seq.frames[:, t])
        vel = trk.state.kf.x[..., 1].clone()
        assert float(_err(trk.state.kf.uv, seq.uv[:, 29]).min()) > 2.0  # it kept the offset
        trk.reanchor(seq.frames[:, 29], seq.uv[:, 29])
        torch.testing.assert_close(trk.state.kf.uv, seq.uv[:, 29])
        torch.testing.assert_close(trk.state.kf.x[..., 1], vel)
        outs = [trk.step(seq.frames[:, t])[0] for t in range(30, 60)]
    e = _err(torch.stack(outs, 1), seq.uv[:, 30:])
    assert float(e.max()) < 2.0  # the clean-sequence bound of a fresh start (5 px before)
    with pytest.raises(TorchseamError, match="finite"):
        trk.reanchor(seq.frames[:, 59], torch.full((2, 2), float("nan")))


def test_guard_is_monotone_and_bounded() -> None:
    g = DriftGuard()
    n = 50
    base = dict(psr=torch.full((n,), 20.0), second_ratio=torch.full((n,), 0.2),
                d2=torch.full((n,), 1.0), spread=torch.full((n,), 0.8))
    sweeps = {"psr": (torch.linspace(2, 40, n), +1), "second_ratio": (torch.linspace(0, 1, n), -1),
              "d2": (torch.linspace(0, 100, n), -1), "spread": (torch.linspace(0.3, 10, n), -1)}
    with torch.no_grad():
        for name, (values, sign) in sweeps.items():
            kw = dict(base, **{name: values})
            trust, r_scale, rho_scale = g(**kw)
            d = sign * trust.diff()
            assert bool((d >= -1e-7).all()) and float(d.sum()) > 0.15, name
            assert bool(((trust > 0) & (trust < 1)).all())
            assert bool((r_scale >= 1).all() and (r_scale <= 1e3 * 1.0001).all())
            # learning follows trust, sharply: nothing is learnt from a rejected frame
            assert bool((rho_scale[trust < 0.3] < 0.01).all())
            assert bool((rho_scale[trust > 0.95] > 0.9).all())


def test_guard_can_be_fitted_by_gradient_descent() -> None:
    # labelled measurements: good ones sharp, single-peaked, inside the gate; bad ones not
    gen = torch.Generator().manual_seed(0)
    n = 400
    good = torch.rand(n, generator=gen) < 0.6

    def u(lo: float, hi: float) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=gen)

    psr = torch.where(good, u(8, 38), u(3, 7))
    sec = torch.where(good, u(0, 0.4), u(0.5, 1))
    d2 = torch.where(good, u(0, 4), u(4, 44))
    spread = torch.full((n,), 0.8)
    g = DriftGuard(psr0=30.0, second0=0.1, gate=1.0)  # a deliberately bad start
    opt = torch.optim.Adam(g.parameters(), lr=0.05)

    def loss_fn() -> torch.Tensor:
        trust, _, _ = g(psr, sec, d2, spread)
        return torch.nn.functional.binary_cross_entropy(trust.clamp(1e-6, 1 - 1e-6), good.float())

    start = float(loss_fn().detach())
    for _ in range(150):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
    with torch.no_grad():
        trust, _, _ = g(psr, sec, d2, spread)
    assert float(loss_fn().detach()) < 0.3 * start
    assert float(((trust > 0.5) == good).float().mean()) > 0.95


def test_gradients_reach_all_parameters_through_truncated_bptt() -> None:
    seq = v_stripe_sequence(2, 13, size=(72, 96), seed=4, noise_sigma=8.0, blob_prob=0.5,
                            amplitude=8.0)
    trk = EAKFSTC(window=(32, 32), target=(16, 16)).double()
    res = trk.run_sequence(seq.frames.double(), seq.uv[:, 0].double(), detach_every=4)
    loss = (res.uv - seq.uv.double()).pow(2).sum(dim=-1).mean()
    loss.backward()
    grads = {n: p.grad for n, p in trk.named_parameters()
             if n != "stc.log_temperature"}  # the soft-argmax's, unused by the subpixel peak
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads.values()), [
        n for n, g in grads.items() if g is None or not bool(torch.isfinite(g).all())]
    moved = {n for n, g in grads.items() if float(g.abs().sum()) > 0}
    for name in ("stc.log_alpha", "stc.log_sigma", "eakf.lam_raw", "eakf.a_raw", "eakf.log_q",
                 "eakf.log_r", "guard.log_psr0", "guard.log_gate", "guard.logit_second0"):
        assert name in moved, name
    with pytest.raises(TorchseamError, match="detach_every"):
        trk.run_sequence(seq.frames.double(), seq.uv[:, 0].double(), detach_every=0)


def test_config_defaults_round_trip_and_overrides() -> None:
    cfg = TrackerConfig()
    assert (cfg.alpha, cfg.beta, cfg.rho) == (2.25, 1.0, 0.075)  # the paper's
    assert cfg.window == (64, 64) and cfg.target == (32, 32)
    assert TrackerConfig.from_dict(cfg.to_dict()) == cfg
    assert TrackerConfig.from_dict({"window": [48, 40]}).window == (48, 40)
    with pytest.raises(TorchseamError, match="tracker config: gatee: unknown field"):
        TrackerConfig.from_dict({"gatee": 3.0})
    trk = EAKFSTC({"rho": 0.05, "frame_rate": 50.0}, gate=3.0).requires_grad_(False)
    assert float(trk.stc.rho) == pytest.approx(0.05, rel=1e-5)
    assert float(trk.eakf.dt) == pytest.approx(0.02)
    assert float(trk.guard.log_gate.exp()) == pytest.approx(3.0, rel=1e-5)
    assert float(trk.stc.sigma) == pytest.approx(32.0, rel=1e-5)  # mean target side
    assert trk.stc.window_size == (64, 64)
    with torch.no_grad():  # every guard default reaches the module, in natural units
        for name, value in DriftGuard().natural().items():
            assert float(value) == pytest.approx(getattr(cfg, name), rel=1e-5), name


def test_bad_inputs_raise_clear_errors() -> None:
    trk = EAKFSTC(window=(32, 32), target=(16, 16))
    frames = torch.zeros(2, 60, 80)
    with pytest.raises(TorchseamError, match="outside the 80 x 60 frame"):
        trk.init(frames, torch.tensor([[10.0, 10.0], [85.0, 10.0]]))
    with pytest.raises(TorchseamError, match="outside"):
        trk.init(frames, torch.tensor([[10.0, 10.0], [math.nan, 10.0]]))
    with pytest.raises(TorchseamError, match=r"uv0: expected shape \(2, 2\)"):
        trk.init(frames, torch.zeros(3, 2))
    with pytest.raises(TorchseamError, match="init"):
        EAKFSTC().step(frames)
    trk.init(frames, torch.full((2, 2), 20.0))
    with pytest.raises(TorchseamError, match=r"frames: expected shape \(B, Himg, Wimg\)"):
        trk.step(torch.zeros(60, 80))
    with pytest.raises(TorchseamError, match="batch size 2"):
        trk.step(torch.zeros(3, 60, 80))
    with pytest.raises(TorchseamError, match="unknown field"):
        EAKFSTC(windoww=(32, 32))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_runs_on_cuda_like_on_cpu() -> None:
    seq = v_stripe_sequence(3, 20, seed=5, noise_sigma=8.0, blob_prob=0.3)
    with torch.inference_mode():
        cpu = EAKFSTC().double().run_sequence(seq.frames.double(), seq.uv[:, 0].double())
        gpu = EAKFSTC().double().cuda().run_sequence(seq.frames.double().cuda(),
                                                     seq.uv[:, 0].double().cuda())
    torch.testing.assert_close(gpu.uv.cpu(), cpu.uv, atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------------------------
# AnchoredTracker: when a TIPM corner replaces the track (configs/anchor.yaml)

class _StubInner:
    """Stands in for the EAKF-STC stream: reports a fixed point, records re-anchoring."""

    def __init__(self, uv):
        self.uv, self.reanchored = np.asarray(uv, float), []

    def update(self, frame):
        return self.uv.copy(), int(TrackStatus.TRACKED)

    def reanchor(self, frame, uv):
        self.reanchored.append(np.asarray(uv, float))


def _corner(uv, rms, slopes=(-0.3, 0.3), gap_px=0.0):
    """A TipmResult of straight arms with ``slopes`` meeting at ``uv`` (ROI px), with a
    centre-line point in every column out to 130 px, but none within ``gap_px`` of the corner
    on the left arm."""
    from torchseam.vision.tipm import TipmResult

    arms = tuple(np.array([uv[1], s, 0.0]) for s in slopes)
    x = np.arange(-130.0, 131.0)
    x = x[(x >= 0) | (x <= -gap_px)]
    v = uv[1] + np.where(x < 0, slopes[0], slopes[1]) * x
    return TipmResult(True, np.asarray(uv, float), arms=arms, u0=float(uv[0]), rms_px=rms,
                      inlier_rms_px=rms,
                      centre=np.stack([uv[0] + x, v], axis=1))


def _anchored_with_tipm(offsets, rms, shapes=None):
    """AnchoredTracker on a stub EAKF-STC fixed at (200, 150) and a stub TIPM returning the
    corner at ``offsets[k]`` from the true point (200, 150) on call k (None: no corner;
    ``shapes[k]``: its ``_corner`` keyword arguments, slopes and gap)."""
    from torchseam.track.anchored import AnchoredTracker, load_anchored_model
    from torchseam.vision.tipm import TipmResult, load_tipm, load_tipm_config

    trk = AnchoredTracker(load_anchored_model(), load_tipm())
    trk.inner = _StubInner((200.0, 150.0))
    trk.x = None
    calls = iter(offsets)
    kinds = iter(shapes if shapes is not None else [{}] * len(offsets))

    class StubTipm:
        """TIPM as the tracker calls it on its window."""

        cfg = load_tipm_config()

        def find(self, roi, prior=None):
            trk.priors.append(prior)
            z = np.zeros(roi.shape[:2], np.uint8)
            offset, kind = next(calls), next(kinds)
            if offset is None:
                return TipmResult(False, np.full(2, np.nan), "no stripe found"), z, z
            # the ROI starts window_px up-left of the filtered point
            return _corner(np.array([200.0, 150.0]) + offset - trk.roi_origin(), rms,
                           **kind), z, z

    trk.priors = []
    trk.roi_origin = lambda: np.floor(trk.x) - trk.cfg.window_px
    trk.tipm = StubTipm()
    return trk


def test_anchored_fix_pulls_the_point_and_reanchors_eakf_stc():
    trk = _anchored_with_tipm([np.array([3.0, 0.0])] * 6, rms=0.15)
    frame = np.zeros((480, 640, 3), np.uint8)
    out = [trk.update(frame)[0] for _ in range(6)]
    # a tight fix 3 px beside EAKF-STC wins (EAKF-STC is a weak measurement) and EAKF-STC is
    # moved onto the filtered point
    assert abs(out[-1][0] - 203.0) < 0.3 and abs(out[-1][1] - 150.0) < 0.1
    assert len(trk.inner.reanchored) >= 1
    # once a fix was taken, TIPM fits the arms with that fix's shape as a prior
    assert trk.priors[0] is None and trk.priors[-1] is not None
    np.testing.assert_allclose(trk.priors[-1][:, :2], [[-0.3, 0.0], [0.3, 0.0]])


def test_the_arm_prior_learns_only_from_corners_the_image_shows():
    """Glare over the corner: TIPM's arms stop short of it and the corner is extrapolated,
    pulled toward the arm prior. Such a fix is still a measurement, but its shape is the
    prior's own: were it the next prior, a prior bent by the glare would hold itself for as
    long as the corner stays hidden and bias the fixes after it. So the prior keeps the shape
    of the last corner seen (both arms reach it) and weakens with the frames since."""
    frame = np.zeros((480, 640, 3), np.uint8)
    on = np.zeros(2)
    seen, hidden, new = ({"slopes": (-0.3, 0.3)}, {"slopes": (-0.2, 0.2), "gap_px": 40.0},
                         {"slopes": (-0.25, 0.25)})
    trk = _anchored_with_tipm([on] * 8, rms=0.15, shapes=[seen] * 2 + [hidden] * 4 + [new] * 2)
    for _ in range(8):
        trk.update(frame)
    assert trk.priors[0] is None
    for k in range(2, 7):  # after the seen corners, through the hidden ones
        np.testing.assert_allclose(trk.priors[k][:, :2], [[-0.3, 0.0], [0.3, 0.0]])
    w = [trk.priors[k][0, 2] for k in range(2, 7)]
    assert all(a > b for a, b in zip(w, w[1:], strict=False))  # weaker every frame
    assert trk.fix is not None and trk.fix.taken and trk.fix.seen
    np.testing.assert_allclose(trk.priors[7][:, :2], [[-0.25, 0.0], [0.25, 0.0]])  # seen again


def test_anchored_takes_a_far_clean_fix_at_once_and_refuses_far_loose_ones():
    frame = np.zeros((480, 640, 3), np.uint8)
    on, far = np.zeros(2), np.array([6.0, 0.0])
    # a clean corner 6 px from the prediction (closed loop: the image jumps when the torch
    # turns): taken in that frame, the filter starts again there
    trk = _anchored_with_tipm([on] * 5 + [far, far], rms=0.15)
    res, fused = [], []
    for _ in range(7):
        res.append(trk.update(frame))
        fused.append(np.array(trk.filter.x, float))
    out = [r[0] for r in res]
    assert abs(out[4][0] - 200.0) < 0.3
    assert abs(fused[5][0] - 206.0) < 0.3 and abs(out[6][0] - 206.0) < 0.3
    # ... but no evidence on the jump's own frame (offline, off the track's own prediction:
    # glare makes such corners, 54-60 px off on the bench's `beyond` seeds 1002-1003), and
    # that frame reports the prediction the jump left, not the corner; the next frame's
    # corner there confirms it
    assert res[4][1] == TrackStatus.TRACKED and res[5][1] == TrackStatus.COASTING
    assert abs(out[5][0] - 200.0) < 0.3
    assert res[6][1] == TrackStatus.TRACKED
    # a loop that predicts the point (expect() every frame, None where it has no prediction:
    # a segment's first frames) takes the fused point as it is: the jump's corner
    trk = _anchored_with_tipm([on] * 5 + [far], rms=0.15)
    for _ in range(6):
        trk.expect(None)
        uv, status = trk.update(frame)
    assert abs(uv[0] - 206.0) < 0.3 and status == TrackStatus.COASTING
    # the live loop (the robot's prediction every frame) as before: tracked at once
    trk = _anchored_with_tipm([on] * 5 + [far], rms=0.15)
    for _ in range(5):
        trk.update(frame)
    trk.expect(np.array([200.0, 150.0]))
    uv, status = trk.update(frame)
    assert abs(uv[0] - 206.0) < 0.3 and status == TrackStatus.TRACKED
    # a loose corner outside the fix gate (spatter on an arm; the gate's width is a fitted
    # value, 8 sigma in the shipped model: 15 px here): refused, however often it comes
    loose = np.array([15.0, 0.0])
    trk = _anchored_with_tipm([on] * 5 + [loose] * 3, rms=0.5)
    out = [trk.update(frame)[0] for _ in range(8)]
    assert all(abs(o[0] - 200.0) < 1.5 for o in out[5:])
    # ... where a clean one is taken at once (reported once the next frame confirms it)
    trk = _anchored_with_tipm([on] * 5 + [loose, loose], rms=0.15)
    out = [trk.update(frame)[0] for _ in range(7)]
    assert abs(out[5][0] - 200.0) < 1.5 and abs(out[6][0] - 215.0) < 0.3


def test_anchored_goes_back_to_its_track_when_the_next_frame_does_not_confirm_a_jump():
    """Offline, glare makes a clean corner elsewhere on the stripe for a frame while the
    corner is hidden: the filter jumps there, but the next frame finds no corner at it, so
    the filter goes back to the track it left and fuses that frame from there (the point
    follows the old track instead of coasting where the jump put it). A jump the next frame
    confirms is taken, as is one that shows again once the corner is seen."""
    frame = np.zeros((480, 640, 3), np.uint8)
    on, far = np.zeros(2), np.array([30.0, 0.0])
    # the frame after the jump: no corner at the jump (first call) nor on the old track
    # (the second, from where it went back); then the corner on the track
    trk = _anchored_with_tipm([on] * 5 + [far] + [None, None] + [on], rms=0.15)
    res = [trk.update(frame) for _ in range(8)]
    # the jump's own frame: the filter at the jump, the frame's point the prediction it left
    assert abs(res[5][0][0] - 200.0) < 0.3 and res[5][1] == TrackStatus.COASTING
    assert abs(res[6][0][0] - 200.0) < 1.5 and res[6][1] == TrackStatus.COASTING
    assert trk.inner.reanchored and abs(trk.inner.reanchored[-1][0] - 200.0) < 1.5
    assert abs(res[7][0][0] - 200.0) < 0.3 and res[7][1] == TrackStatus.TRACKED
    # a genuine jump whose corner is hidden on the next frame: taken again when it shows,
    # tracked once the frame after finds it there
    trk = _anchored_with_tipm([on] * 5 + [far] + [None, None] + [far, far], rms=0.15)
    res = [trk.update(frame) for _ in range(9)]
    assert abs(res[6][0][0] - 200.0) < 1.5
    assert abs(res[7][0][0] - 200.0) < 1.5 and res[7][1] == TrackStatus.COASTING
    assert abs(res[8][0][0] - 230.0) < 0.3 and res[8][1] == TrackStatus.TRACKED


def test_anchored_takes_the_robots_motion_as_its_prediction():
    frame = np.zeros((480, 640, 3), np.uint8)
    on, moved = np.zeros(2), np.array([6.0, 0.0])
    # the image jumps 6 px (the torch turned) and TIPM's fit there is loose (arc light)
    trk = _anchored_with_tipm([on] * 5 + [moved], rms=0.5)
    out = [trk.update(frame)[0] for _ in range(5)]
    trk.expect(np.array([205.5, 150.0]))           # the robot's motion says where to look
    out.append(trk.update(frame)[0])
    assert abs(out[5][0] - 206.0) < 1.0            # taken: it is where it was expected
    trk = _anchored_with_tipm([on] * 5 + [moved], rms=0.5)
    out = [trk.update(frame)[0] for _ in range(6)]
    assert abs(out[5][0] - 200.0) < 1.5            # no expectation: refused, as before
    trk.expect(None)                               # no idea: nothing changes
    assert trk._expected is None


def test_anchored_leans_on_its_prediction_under_red_glare():
    """A glare band over the corner: TIPM's fits stay tight while the corner slides along the
    stripe, and EAKF-STC follows. Under red haze around the point the filter trusts both less
    (the fitted glare_start, glare_scale) and moves onto them slowly."""
    from types import SimpleNamespace

    from torchseam.track.anchored import glare_level, load_anchored_model

    # the fitted glare weights (models/live_tracker.safetensors), as AnchoredTracker runs them
    cfg = SimpleNamespace(**load_anchored_model().fusion.values())
    dark = np.zeros((480, 640, 3), np.uint8)
    haze = dark.copy()
    # a red haze as strong as a frame holds (250 grey levels at most): the covariances grow by
    # the fitted glare term there, at least tenfold
    k = min(np.sqrt(99.0), (250.0 - cfg.glare_start) / cfg.glare_scale)
    level = round(cfg.glare_start + k * cfg.glare_scale)
    inflate = 1.0 + ((level - cfg.glare_start) / cfg.glare_scale) ** 2
    assert inflate >= 10.0
    haze[..., 2] = level
    assert glare_level(haze, np.array([200.0, 150.0]), 30) == level
    assert glare_level(dark, np.array([200.0, 150.0]), 30) == 0.0
    assert glare_level(haze, np.array([-100.0, 150.0]), 30) == 0.0  # the box off the frame
    moved = {}
    for name, frame in (("dark", dark), ("haze", haze)):
        # the filter at the true point (200, 150); TIPM's tight fixes and EAKF-STC both 3 px
        # beside it (a glare band biases both the same way)
        trk = _anchored_with_tipm([np.array([3.0, 0.0])] * 3, rms=0.15)
        trk.inner = _StubInner((203.0, 150.0))
        trk.x = np.array([200.0, 150.0])
        trk.P = trk.Q.copy()
        moved[name] = [trk.update(frame)[0][0] - 200.0 for _ in range(3)]
        assert trk.glare == (level if name == "haze" else 0.0)
        # the frame's fix is recorded with the glare factor on its covariance
        assert trk.fix is not None and trk.fix.taken
        np.testing.assert_allclose(trk.fix.uv, [203.0, 150.0], atol=1e-9)
        assert trk.fix.inflate == pytest.approx(inflate if name == "haze" else 1.0, rel=1e-6)
    assert moved["dark"][0] > 2.8                      # dark: taken at once (3 px)
    assert moved["haze"][0] < 0.9 * moved["dark"][0]   # haze: a part of the way per frame ...
    assert moved["haze"][2] > moved["haze"][0]         # ... still moving toward them


def test_corner_covariance_is_weak_along_a_shallow_stripe():
    from torchseam.track.anchored import corner_cov

    C = corner_cov(_corner((100.0, 100.0), 0.2, slopes=(-0.3, 0.3)), 0.5, 0.1)
    assert C[0, 0] > 10 * C[1, 1]                 # 147 deg corner: weak along u
    C2 = corner_cov(_corner((100.0, 100.0), 0.2, slopes=(-1.0, 1.0)), 0.5, 0.1)
    assert C2[0, 0] < C[0, 0] / 5                 # a sharper corner pins u down


def test_corner_covariance_grows_when_an_arm_stops_short_of_the_corner():
    """An arm whose centre line ends 40 px before the corner (spatter across it) is
    extrapolated there: its line is uncertain at the corner, so the fix is weak across that
    arm; complete arms keep the plain covariance, and a ridge prior steadies the extrapolation."""
    from torchseam.track.anchored import corner_cov

    def cov(res, prior=None):
        return corner_cov(res, 0.5, 0.1, prior, (5.0, 120.0))
    full = _corner((100.0, 100.0), 0.2)
    # complete arms: the leverage ratio is 1, as without the centre-line test
    sig2 = (0.5 * 0.2) ** 2
    n = np.array([[0.3, 1.0], [-0.3, 1.0]]) / np.hypot(0.3, 1.0)
    np.testing.assert_allclose(cov(full), sig2 * np.linalg.inv(n.T @ n), rtol=1e-9, atol=1e-15)
    # the uncertain direction (along the shallow stripe) grows with the gap, fast
    var_u = [cov(_corner((100.0, 100.0), 0.2, gap_px=g))[0, 0] for g in (0, 20, 40, 60)]
    assert var_u[0] == pytest.approx(cov(full)[0, 0])
    assert var_u[1] > 1.5 * var_u[0] and var_u[2] > 3 * var_u[1] and var_u[3] > 3 * var_u[2]
    short = _corner((100.0, 100.0), 0.2, gap_px=40.0)
    prior = np.array([[-0.3, 0.0, 1e5, 1e9], [0.3, 0.0, 1e5, 1e9]])
    assert np.trace(cov(short, prior)) < np.trace(cov(short))  # a firm prior: less extrapolated


def test_tipm_arm_prior_keeps_the_corner_where_an_arm_has_a_gap():
    """A left arm with a gap next to the corner and a short bent stretch beyond it: the free
    quadratic slides the corner along the stripe, the prior of the previous shape does not."""
    from torchseam.vision.tipm import load_tipm

    u = np.arange(0.0, 241.0)
    v = 100.0 + 0.3 * np.abs(u - 120.0)            # a 147 deg corner at (120, 100)
    rng = np.random.default_rng(0)
    v = v + rng.normal(0, 0.15, len(u))
    left = (u >= 60) & (u < 85)                    # left arm only 35-60 px from the corner
    v[left] -= 0.002 * (u[left] - 60) ** 2        # bent by spatter touching the stripe
    keep = left | (u > 120)
    pts = np.stack([u[keep], v[keep]], axis=1)
    tipm = load_tipm()
    free = tipm.corner(pts)
    prior = np.array([[-0.3, 0.0, 1e4, 1e9], [0.3, 0.0, 1e4, 1e9]])
    held = tipm.corner(pts, prior=prior)
    assert free.ok and held.ok
    assert np.linalg.norm(free.uv - (120, 100)) > 1.0
    assert np.linalg.norm(held.uv - (120, 100)) < 0.5 * np.linalg.norm(free.uv - (120, 100))


def test_anchor_config_names_a_bad_field(tmp_path):
    from torchseam.core.config import ConfigError
    from torchseam.track.anchored import load_anchor_config

    text = (Path(__file__).parents[1] / "configs" / "anchor.yaml").read_text()
    bad = tmp_path / "anchor.yaml"
    bad.write_text(text.replace("max_rms_px: 0.3", "max_rms_px: -1"))
    with pytest.raises(ConfigError, match="max_rms_px"):
        load_anchor_config(bad)


def test_glare_level_counts_the_median_np_partition_selects():
    """The glare level counted in one compiled pass (a histogram of the box's red response) is
    the element ``np.partition`` of the response selects: colour and mono boxes, clipped at
    the frame's border, even and odd pixel counts."""
    from torchseam.track.anchored import glare_level
    from torchseam.vision.tipm import red_response

    rng = np.random.default_rng(8)
    for k in range(400):
        h, w = (int(x) for x in rng.integers(3, 90, 2))
        shape = (h, w, 3) if k % 2 else (h, w)
        frame = rng.integers(0, int(rng.choice([8, 60, 256])), shape).astype(np.uint8)
        uv = rng.uniform(-20.0, 110.0, 2)
        half = int(rng.integers(1, 35))
        u, v = int(round(float(uv[0]))), int(round(float(uv[1])))
        box = frame[max(v - half, 0):max(v + half + 1, 0), max(u - half, 0):max(u + half + 1, 0)]
        if box.size == 0:
            ref = 0.0
        else:
            red = red_response(np.ascontiguousarray(box)).ravel()
            ref = float(np.partition(red, len(red) // 2)[len(red) // 2])
        assert glare_level(frame, uv, half) == ref
