"""Six segments, the look-ahead buffer and IPI step control."""

import numpy as np
import pytest

from torchseam.plan.path import LookAheadBuffer, ipi_step, six_segments


def test_six_segments_cover_the_ring():
    assert six_segments()[0].phi_start == pytest.approx(np.radians(90.0))  # configs/plan.yaml
    segs = six_segments(0.3)
    assert [s.name for s in segs] == list("abcdef")
    assert segs[0].phi_start == pytest.approx(0.3)
    assert segs[-1].phi_end == pytest.approx(0.3 + 2 * np.pi)
    for a, b in zip(segs, segs[1:], strict=False):
        assert a.phi_end == pytest.approx(b.phi_start)
        assert b.rotation_deg - a.rotation_deg == pytest.approx(-60.0)


def test_ipi_step_eq30():
    cp, np_ = np.array([0.0, 0, 0]), np.array([3.0, 4.0, 0])
    np.testing.assert_allclose(ipi_step(cp, np_, 2.0), [1.2, 1.6, 0])
    np.testing.assert_allclose(ipi_step(cp, np_, 7.0), np_)  # never past a located point


def test_buffer_walks_a_curved_path_in_equal_steps():
    phi = np.linspace(0, np.pi / 2, 400)
    pts = np.stack([76 * np.cos(phi), 76 * np.sin(phi), np.zeros_like(phi)], axis=1)
    buf = LookAheadBuffer(maxlen=1000)
    for k, p in enumerate(pts):
        buf.push(p, np.full((2, 3), np.nan), k / 25)
    cp, steps = pts[0], []
    while (nxt := buf.next_command(cp, 2.0)) is not None:
        ip, tangent, _ = nxt
        # the tangent is the circle's, centred on the point (no trailing lag)
        phi = np.arctan2(ip[1], ip[0])
        assert np.degrees(np.arccos(tangent @ [-np.sin(phi), np.cos(phi), 0])) < 0.5
        steps.append(np.linalg.norm(ip - cp))
        # each commanded point stays on the located arc (chords of 2 mm on r = 76 mm)
        assert abs(np.hypot(ip[0], ip[1]) - 76) < 0.01
        cp = ip
    assert len(steps) > 50
    np.testing.assert_allclose(steps[:-1], 2.0, atol=1e-9)
    assert buf.dropped == 0


def test_buffer_is_bounded_and_counts_what_it_drops():
    buf = LookAheadBuffer(maxlen=10)
    for k in range(25):
        buf.push(np.array([k * 0.3, 0, 0]), np.zeros((2, 3)), k)
    assert len(buf) == 10 and buf.dropped == 15


def test_buffer_smooths_noisy_points_without_lag():
    rng = np.random.default_rng(0)
    phi = np.linspace(0, 1.0, 240)
    true = np.stack([76 * np.cos(phi), 76 * np.sin(phi), 5 * np.sin(3 * phi)], axis=1)
    buf = LookAheadBuffer(maxlen=1000, smooth_mm=3.0)
    for k, p in enumerate(true + rng.normal(0, 0.08, true.shape)):
        buf.push(p, np.full((2, 3), np.nan), k / 25)
    raw = np.array([np.linalg.norm(buf.points[k].p - true[k]) for k in range(20, 200)])
    fit = np.array([np.linalg.norm(buf.fit(k)[0] - true[k]) for k in range(20, 200)])
    assert np.sqrt(np.mean(fit**2)) < 0.5 * np.sqrt(np.mean(raw**2))
    assert LookAheadBuffer().next_command(np.zeros(3), 2.0) is None
