"""The synthetic V-stripe frames (torchseam.sim.vstripe): the corner is where it says."""

from __future__ import annotations

import doctest
import math

import numpy as np

import torchseam.fit.synthetic
import torchseam.sim.vstripe
from torchseam.sim.vstripe import draw_v_stripes, v_stripe_sequence


def _ridge_error(img: np.ndarray, cu: float, cv: float, slope: float, cols: range) -> np.ndarray:
    """Ridge row (intensity centroid down each column) minus the arm's true row."""
    out = []
    for u in cols:
        v_true = cv + (u - cu) * slope
        rows = np.arange(int(round(v_true)) - 5, int(round(v_true)) + 6)
        col = img[rows, u].astype(np.float64)
        out.append((col * rows).sum() / col.sum() - v_true)
    return np.asarray(out)


def test_arms_run_through_the_sub_pixel_corner():
    # the old tracker fixture drew with cv2.LINE_AA on float images, i.e. pixel-quantised
    # lines: its arms sat up to ~0.6 px off the reported corner, depending on the fraction
    a = math.radians(35)
    for cu, cv in [(64.0, 64.0), (64.3, 64.7), (63.55, 64.2), (64.9, 63.05)]:
        img = draw_v_stripes([(cu, cv)], (128, 128), (math.pi + a, -a), peak=220.0,
                             width_px=1.2)[0]
        left = _ridge_error(img, cu, cv, math.tan(a), range(12, 50))
        right = _ridge_error(img, cu, cv, -math.tan(a), range(80, 116))
        assert np.abs(left).max() < 0.02 and np.abs(right).max() < 0.02, (cu, cv)
        assert abs(float(img.max()) - 220.0) < 1.0


def test_sequence_truth_vanish_and_clutter():
    seq = v_stripe_sequence(2, 12, (72, 96), seed=4, noise_sigma=0.0, blob_prob=1.0,
                            streak_prob=1.0, vanish=((5, 8),))
    assert seq.frames.shape == (2, 12, 72, 96) and seq.uv.shape == (2, 12, 2)
    assert seq.visible[:, 5:8].logical_not().all() and seq.visible[:, :5].all()
    # without noise the corner pixel of a visible frame is on the stripe (~200 + 15)
    u, v = seq.uv[0, 0].round().long().tolist()
    assert float(seq.frames[0, 0, v, u]) > 150.0
    # the same seed gives the same frames; clutter makes them brighter than a clean stripe
    again = v_stripe_sequence(2, 12, (72, 96), seed=4, noise_sigma=0.0, blob_prob=1.0,
                              streak_prob=1.0, vanish=((5, 8),))
    assert bool((again.frames == seq.frames).all())
    clean = v_stripe_sequence(2, 12, (72, 96), seed=4, noise_sigma=0.0, vanish=((5, 8),))
    assert float(seq.frames.sum()) > float(clean.frames.sum())


def test_docstring_examples():
    for mod in (torchseam.sim.vstripe, torchseam.fit.synthetic):
        result = doctest.testmod(mod)
        assert result.failed == 0 and result.attempted > 0, mod.__name__
