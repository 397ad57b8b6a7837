"""LiteEAKFSTC, the numpy B = 1 twin of the torch EAKFSTC, on simulated heavy-arc frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchseam.track import EAKFSTC, TrackInputError, TrackStatus
from torchseam.track.anchored import fitted_eakf_stc, load_anchor_config
from torchseam.track.base import Tracker
from torchseam.track.fusion import LiteEAKFSTC, LiteTracker
from torchseam.track.peers import (
    Confirmed,
    grey_tensor,
    make_tracker,
    run_tracker,
)
from torchseam.vision.tipm import red_response

F64 = torch.float64
REANCHOR_EVERY = 10
# quality scores compared between module and twin (z, peak, r_scale, rho_scale, std as well)
QUALITY = ("psr", "trust", "second_ratio", "n_peaks", "d2", "z", "peak", "r_scale",
           "rho_scale", "std")


@pytest.fixture(scope="module")
def heavy(cell, part, noise) -> tuple[list[np.ndarray], np.ndarray]:
    """80 simulated heavy-arc BGR frames and the true feature pixel (80, 2) of each."""
    from torchseam.sim.sequence import SequenceSpec, simulate

    spec = SequenceSpec(n_frames=80, level=noise.level("heavy"), seed=11)
    pairs = list(simulate(cell, part, noise, spec))
    return [f for f, _ in pairs], np.array([t.uv for _, t in pairs], float)


def _same_state(lite: LiteEAKFSTC, module: EAKFSTC, where: str) -> None:
    """The twin's filter state equals the module's (batch index 0)."""
    kf = module.state.kf
    for name in ("x", "P", "Z", "s", "s_ref", "x_post"):
        mine, theirs = getattr(lite, name), getattr(kf, name)
        assert (mine is None) == (theirs is None), f"{where}: {name}"
        if mine is not None:
            np.testing.assert_allclose(mine, theirs[0].numpy(), rtol=1e-9, atol=1e-9,
                                       err_msg=f"{where}: {name}")
    assert lite.coast == int(module.state.coast[0]), where


def _lockstep(module: EAKFSTC, frames: list[np.ndarray], uv0: np.ndarray,
              fixes: np.ndarray | None) -> list[int]:
    """Step ``module`` (float64) and its twin through ``frames`` side by side, re-anchoring
    both on ``fixes[k]`` every REANCHOR_EVERY frames, and assert they agree on every frame.
    Returns the statuses."""
    lite = LiteEAKFSTC.from_module(module)
    statuses = []
    with torch.inference_mode():
        module.init(grey_tensor(frames[0]).clone(), torch.tensor(uv0[None], dtype=F64))
        lite.init(frames[0], uv0)
        np.testing.assert_array_equal(lite.uv, uv0)
        _same_state(lite, module, "init")
        for k, frame in enumerate(frames[1:], start=1):
            grey = grey_tensor(frame).clone()
            uv_m, st_m, q_m = module.step(grey)
            uv_l, st_l, q_l = lite.step(frame)
            np.testing.assert_allclose(uv_l, uv_m[0].numpy(), rtol=0, atol=1e-6,
                                       err_msg=f"frame {k}")
            assert st_l == int(st_m[0]), f"frame {k}"
            for key in QUALITY:
                np.testing.assert_allclose(q_l[key], q_m[key][0].numpy(), rtol=1e-9,
                                           atol=1e-9, err_msg=f"frame {k}: {key}")
            _same_state(lite, module, f"frame {k}")
            statuses.append(st_l)
            if fixes is not None and k % REANCHOR_EVERY == 0:
                fix = fixes[k]
                module.reanchor(grey, torch.tensor(fix[None], dtype=F64))
                lite.reanchor(frame, fix)
                np.testing.assert_allclose(lite.uv, fix, rtol=0, atol=1e-12)
                np.testing.assert_allclose(module.state.kf.uv[0].numpy(), fix, rtol=0,
                                           atol=1e-12)
                assert lite.status == int(TrackStatus.TRACKED)
                _same_state(lite, module, f"reanchor at frame {k}")
    return statuses


@pytest.mark.parametrize("make, statuses_seen", [
    (lambda: fitted_eakf_stc(), {TrackStatus.TRACKED, TrackStatus.COASTING}),
    (lambda: EAKFSTC(), {TrackStatus.TRACKED, TrackStatus.COASTING}),
    # the regularised eq. 8 and the start model in detection (STC reg, anchor)
    (lambda: EAKFSTC(reg=20.0, anchor=0.3), {TrackStatus.TRACKED, TrackStatus.COASTING}),
    # a short coasting limit: the LOST branch too
    (lambda: EAKFSTC(max_coast=2),
     {TrackStatus.TRACKED, TrackStatus.COASTING, TrackStatus.LOST}),
], ids=["fitted", "default", "reg+anchor", "max_coast=2"])
def test_twin_equals_the_module_frame_by_frame_with_reanchoring(heavy, make,
                                                               statuses_seen) -> None:
    frames, truth = heavy
    statuses = _lockstep(make().double(), frames, truth[0], truth)
    # the comparison covers every status the sequence is meant to exercise
    assert {TrackStatus(s) for s in statuses} == statuses_seen


def test_twin_equals_the_module_near_the_frame_border(heavy) -> None:
    """Cropped so that the feature sits ~6 px from the top-left corner: every context window
    runs off the frame and replicates its border (the slow path of the twin's crop)."""
    frames, truth = heavy
    u0, v0 = np.floor(truth[0]).astype(int) - 6
    crops = [np.ascontiguousarray(f[v0:v0 + 100, u0:u0 + 140]) for f in frames]
    shifted = truth - [u0, v0]
    assert shifted[:, 0].min() < 32 and shifted[:, 1].min() < 32  # the window (64) crosses
    statuses = _lockstep(fitted_eakf_stc().double(), crops, shifted[0], shifted)
    assert TrackStatus.TRACKED in statuses


def test_grey_frames_give_the_same_track_as_colour_frames(heavy) -> None:
    """An (H, W) uint8 frame is taken as the red-stripe response of the colour frame."""
    frames, truth = heavy
    module = fitted_eakf_stc()
    colour, grey = LiteEAKFSTC.from_module(module), LiteEAKFSTC.from_module(module)
    greys = [red_response(f) for f in frames[:40]]
    assert greys[0].shape == frames[0].shape[:2] and greys[0].dtype == np.uint8
    colour.init(frames[0], truth[0])
    grey.init(greys[0], truth[0])
    for k in range(1, 40):
        uv_c, st_c, q_c = colour.step(frames[k])
        uv_g, st_g, q_g = grey.step(greys[k])
        np.testing.assert_array_equal(uv_g, uv_c)
        assert st_g == st_c
        for key in QUALITY:
            np.testing.assert_array_equal(q_g[key], q_c[key])
        if k % REANCHOR_EVERY == 0:
            colour.reanchor(frames[k], truth[k])
            grey.reanchor(greys[k], truth[k])
    # and they did track: not stuck where they started
    assert np.linalg.norm(colour.uv - truth[39]) < 5.0
    assert np.linalg.norm(truth[39] - truth[0]) > 5.0


def test_bad_inputs_are_refused_with_the_argument_named(heavy) -> None:
    frames, truth = heavy
    f0 = frames[0]
    h, w = f0.shape[:2]
    lite = LiteEAKFSTC.from_module(EAKFSTC())
    with pytest.raises(TrackInputError, match="init"):
        lite.step(f0)
    with pytest.raises(TrackInputError, match="init"):
        lite.reanchor(f0, truth[0])
    for uv0 in ([w + 5.0, 10.0], [-1.0, 10.0], [10.0, h + 0.0], [np.nan, 10.0],
                [10.0, np.inf], [1.0, 2.0, 3.0]):
        with pytest.raises(TrackInputError, match="uv0"):
            lite.init(f0, np.array(uv0))
    # the edges of the frame's pixels are inside
    lite.init(f0, np.array([-0.5, h - 0.5]))
    for bad in (np.zeros((h, w, 4), np.uint8), np.zeros((h, w, 1), np.uint8),
                np.zeros((2, h, w, 3), np.uint8), f0.tolist()):
        with pytest.raises(TrackInputError, match="frame"):
            lite.init(bad, truth[0])
        lite.init(f0, truth[0])
        with pytest.raises(TrackInputError, match="frame"):
            lite.step(bad)
    before = lite.uv
    with pytest.raises(TrackInputError, match="finite"):
        lite.reanchor(f0, np.array([np.nan, 1.0]))
    np.testing.assert_array_equal(lite.uv, before)  # refused before touching the state
    x, Z = lite.x.copy(), lite.Z.copy()
    with pytest.raises(TrackInputError, match="frame"):
        lite.reanchor(np.zeros((h, w, 4), np.uint8), truth[0] + 6.0)
    np.testing.assert_array_equal(lite.x, x)  # a bad frame is refused before the shift too
    np.testing.assert_array_equal(lite.Z, Z)


@pytest.mark.parametrize("setting", [{"crop": "bilinear"}, {"peak": "soft"},
                                     {"peak": "argmax"}, {"scale_update": True}])
def test_from_module_refuses_settings_it_does_not_run(setting) -> None:
    key = next(iter(setting))
    with pytest.raises(TrackInputError, match=key):
        LiteEAKFSTC.from_module(EAKFSTC(**setting))


def test_eakf_stc_tracker_is_the_twin_and_follows_a_heavy_arc_seam(cell, part, noise,
                                                                    tipm) -> None:
    from torchseam.sim.sequence import SequenceSpec, simulate

    pairs = list(simulate(cell, part, noise, SequenceSpec(n_frames=80,
                                                          level=noise.level("heavy"), seed=5)))
    frames, truth = [f for f, _ in pairs], np.array([t.uv for _, t in pairs], float)
    confirmed = make_tracker("eakf-stc", tipm)
    # its status held to TIPM's corner (Confirmed): the twin is the point's own tracker
    assert isinstance(confirmed, Confirmed) and isinstance(confirmed.inner, LiteTracker)
    trk = confirmed.inner
    uv, status, secs, idle_secs, note = run_tracker(trk, frames, truth[0], tipm)
    assert uv.shape == (80, 2) and status.shape == (80,) and note == "given"
    assert idle_secs.shape == (80,) and idle_secs[1:].min() > 0  # the learning, between frames
    err = np.linalg.norm(uv - truth, axis=1)
    rmse = float(np.sqrt(np.mean(err ** 2)))
    frozen = float(np.sqrt(np.mean(np.sum((truth - truth[0]) ** 2, axis=1))))
    # measured 1.0 px (max 2.4) against 14 px for a tracker that never moves
    assert rmse < 3.0 and frozen > 4 * rmse
    assert float(err.max()) < 8.0
    assert float(np.mean(status == TrackStatus.TRACKED)) > 0.6
    # the wrapper's reanchor moves the twin onto the fix
    trk.reanchor(frames[-1], truth[-1] + [1.0, -1.0])
    np.testing.assert_allclose(trk.lite.uv, truth[-1] + [1.0, -1.0])


def test_docstring_example_runs() -> None:
    import doctest

    import torchseam.track.fusion

    result = doctest.testmod(torchseam.track.fusion)
    assert result.failed == 0 and result.attempted > 0


def test_learning_between_frames_gives_the_same_track(heavy):
    """``idle()`` (the live loop's between-frames hook) applies the context learning that the
    next step would apply itself: the same numbers, bit for bit, whether it is called or not,
    with re-anchoring, and whatever the caller does to its frame buffer after a step."""
    frames, truth = heavy
    module = fitted_eakf_stc()
    runs = []
    for between in (False, True):
        lite = LiteEAKFSTC.from_module(module)
        buf = frames[0].copy()
        lite.init(buf, truth[0])
        out = []
        for k, f in enumerate(frames[1:], start=1):
            buf[...] = f  # one camera buffer, refilled every frame
            uv, status, q = lite.step(buf)
            if k % REANCHOR_EVERY == 0:
                lite.reanchor(buf, truth[k])
            buf[...] = 0  # the driver reuses the buffer before the learning is applied
            if between:
                assert lite._pending
                lite.idle()
                assert not lite._pending
            out.append((uv, status, q["psr"], q["trust"]))
        runs.append(out)
    for (uv_a, st_a, psr_a, tr_a), (uv_b, st_b, psr_b, tr_b) in zip(*runs, strict=True):
        np.testing.assert_array_equal(uv_a, uv_b)
        assert (st_a, psr_a, tr_a) == (st_b, psr_b, tr_b)
    # and the track is a real one: near the truth on this heavy sequence
    err = np.linalg.norm(np.array([r[0] for r in runs[1]]) - truth[1:], axis=1)
    assert np.median(err) < 2.0


def test_the_twins_transforms_are_scipy_ffts() -> None:
    """The twin calls pocketfft without scipy.fft's dispatch: the same spectra and responses
    as scipy.fft.rfft2 / irfft2, to the bit."""
    import scipy.fft

    from torchseam.track.fusion import _irfft2, _rfft2

    rng = np.random.default_rng(2)
    for scale in (1e-3, 1.0, 1e4):
        x = rng.normal(size=(64, 64)) * scale
        X = scipy.fft.rfft2(x)
        np.testing.assert_array_equal(_rfft2(x), X)
        Y = X * (rng.normal(size=X.shape) + 1j * rng.normal(size=X.shape))
        np.testing.assert_array_equal(_irfft2(Y, (64, 64)), scipy.fft.irfft2(Y, s=(64, 64)))


class _Offset(Tracker):
    """A tracker with no evidence of its own: its point is the truth moved by ``offset`` px,
    always said ``tracked`` (as STC, KCF, CSRT and MOSSE say it)."""

    name = "offset"

    def __init__(self, truth: np.ndarray, offset: tuple[float, float]) -> None:
        self.truth, self.offset, self.k = truth, np.asarray(offset, float), 0

    def init(self, frame: np.ndarray, uv: np.ndarray) -> None:
        self.k = 0

    def update(self, frame: np.ndarray) -> tuple[np.ndarray, int]:
        self.k += 1
        return self.truth[self.k] + self.offset, int(TrackStatus.TRACKED)


def test_a_tracker_without_evidence_is_tracked_only_where_tipm_sees_its_corner(clean_seq,
                                                                                 tipm):
    """The status rule of every tracker: a point on the true corner is `tracked` on clean
    frames; the same tracker 12 px along the stripe off it (its own status still `tracked`)
    is not, on any frame, and its point stays its own (Confirmed weighs, never corrects)."""
    frames = [f for f, _ in clean_seq]
    truth = np.array([t.uv for _, t in clean_seq], float)
    cfg = load_anchor_config()
    for offset, tracked in (((0.0, 0.0), True), ((12.0, 0.0), False)):
        trk = Confirmed(_Offset(truth, offset), tipm, cfg)
        trk.init(frames[0], truth[0])
        for k, frame in enumerate(frames[1:], start=1):
            res = trk.track(frame)
            np.testing.assert_allclose(res.uv, truth[k] + offset)
            assert res.tracked == tracked, (offset, k, res.status)
            assert res.fix is not None and np.linalg.norm(res.fix.uv - truth[k]) < 1.0
            if not tracked:
                assert res.status == TrackStatus.COASTING  # 11 frames: not lost yet
    # every tracker whose own status is no image evidence is held to it
    for name in ("eakf-stc", "stc", "kcf", "csrt", "mosse"):
        assert isinstance(make_tracker(name, tipm), Confirmed), name
    assert not isinstance(make_tracker("tipm", tipm), Confirmed)
    assert not isinstance(make_tracker("anchored", tipm), Confirmed)
