"""Pixels -> 3D, ECAL arm points and the torch frame, against the simulator's truth."""

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from torchseam.core.transforms import apply, invert
from torchseam.geometry.ecal import load_ecal
from torchseam.geometry.torch_frame import quaternions, tilt, torch_frame
from torchseam.geometry.triangulate import FastTriangulator, Triangulator
from torchseam.sim.scene import Scene, torch_frames
from torchseam.sim.sequence import SequenceSpec, simulate


def _flange(cell, truth):
    return truth.T_B_C @ invert(cell.hand_eye.matrix())


def test_triangulation_recovers_the_true_3d_points(cell, clean_seq):
    tri = Triangulator(cell)
    uv = torch.tensor(np.stack([np.vstack([t.uv, t.arm_uv]) for _, t in clean_seq]))  # (N,3,2)
    T_B_F = torch.tensor(np.stack([_flange(cell, t) for _, t in clean_seq]))[:, None]
    X = tri(uv, T_B_F).numpy()
    truth = np.stack([np.vstack([t.seam_B, t.arm_B]) for _, t in clean_seq])
    np.testing.assert_allclose(X, truth, atol=1e-6)
    # the OpenCV path of the live loop gives the same points
    fast = FastTriangulator(cell)
    for i in range(len(clean_seq)):
        np.testing.assert_allclose(fast(uv[i].numpy(), T_B_F[i, 0].numpy()), truth[i],
                                   atol=1e-6)
    # float32 on the same inputs stays within a micrometre or so
    X32 = Triangulator(cell, torch.float32)(uv.float(), T_B_F.float())
    assert np.abs(X32.double().numpy() - truth).max() < 5e-3


def _true_frame(scene, truth):
    """Torch axis and seam tangent of the true part at the true seam point."""
    Tp = scene.part_pose(truth.t_s)
    P = apply(invert(Tp), truth.seam_B)
    j = scene.true_joint
    phis = np.linspace(0, 2 * np.pi, 40001)
    k = int(np.argmin(np.linalg.norm(j.seam(phis).point - P, axis=1)))
    s = j.seam(phis[k:k + 1])
    F = torch_frames(s)[0]
    return Tp[:3, :3] @ F[:3, 2], Tp[:3, :3] @ s.tangent[0]


@pytest.mark.parametrize("angle", [60.0, 90.0])
def test_ecal_torch_axis_within_a_degree_of_the_joint_bisector(cell, part, noise, angle, tipm):
    p = dataclasses.replace(part, intersection_angle_deg=angle)
    scene, ecal, tri = Scene(p), load_ecal(), Triangulator(cell)
    errs = []
    for seed in range(5):
        for img, t in simulate(cell, p, noise, SequenceSpec(n_frames=1, seed=seed)):
            found = tipm(img)
            red, mask, _ = tipm.stripe_mask(img)
            arms = ecal(mask, found.uv, red)
            assert arms.ok and not arms.fallback
            T_B_F = torch.tensor(_flange(cell, t))
            pq = tri(torch.tensor(np.vstack([found.uv, arms.p_tangent])), T_B_F)
            z_true, tangent = _true_frame(scene, t)
            R, ok = torch_frame(pq[:1], pq[1:2], pq[2:], tangent=torch.tensor(tangent)[None])
            assert ok.all()
            errs.append(np.degrees(np.arccos(np.clip(R[0, :, 2].numpy() @ z_true, -1, 1))))
    assert max(errs) < 1.0


def _v_mask(spatter: bool = False, occlude: bool = False, left_end=(20, 90)):
    mask = np.zeros((300, 300), np.uint8)
    c = (150, 150)
    cv2.line(mask, c, left_end, 255, 5)
    if not occlude:
        cv2.line(mask, c, (280, 80), 255, 5)
    if spatter:
        cv2.line(mask, (80, 170), (120, 240), 255, 3)   # streak crossing the circles, apart
        cv2.circle(mask, (150, 210), 14, 255, -1)         # blob below the corner
    return mask, np.array(c, float)


def test_ecal_rejects_spatter_crossings():
    ecal = load_ecal()
    clean = ecal(*_v_mask())
    noisy = ecal(*_v_mask(spatter=True))
    assert clean.ok and noisy.ok and noisy.rejected > 0
    np.testing.assert_allclose(noisy.angles, clean.angles, atol=0.02)
    # arms leave up-left and up-right
    assert noisy.p[0, 0] < 150 < noisy.p[1, 0] and (noisy.p[:, 1] < 150).all()


def test_ecal_occluded_arm_falls_back_to_previous_direction():
    ecal = load_ecal()
    prev = ecal(*_v_mask()).angles
    mask, uv = _v_mask(occlude=True)
    res = ecal(mask, uv, prev_angles=prev)
    assert res.ok and res.fallback
    np.testing.assert_allclose(res.angles, prev, atol=0.02)
    res = ecal(mask, uv)
    assert not res.ok and "occluded" in res.reason
    res = ecal(np.zeros_like(mask), uv)
    assert not res.ok and "no arm" in res.reason


def test_ecal_occluded_arm_mirrors_the_seen_arms_turn():
    """Along the saddle the V opens and closes about a steady bisector (image angles of the two
    arms over 20 frames of a heavy 60-degree ring: correlation -0.98, d1 = -0.94 d0), so the
    hidden arm is turned by minus the seen arm's turn since the previous frame, not held."""
    ecal = load_ecal()
    prev = ecal(*_v_mask()).angles
    mask, uv = _v_mask(occlude=True, left_end=(24, 112))  # the left arm turned down ~8 degrees
    res = ecal(mask, uv, prev_angles=prev)
    assert res.ok and res.fallback
    turn = res.angles[0] - prev[0]
    assert abs(np.degrees(turn)) > 5
    np.testing.assert_allclose(res.angles[1], prev[1] - turn, atol=1e-9)


def test_degenerate_three_points_give_flags_not_nan():
    p = torch.zeros(5, 3, dtype=torch.float64)
    q1 = torch.tensor([[1.0, 0, 0], [0, 0, 0], [1, 0, 0], [0, 5, 0], [float("nan"), 0, 0]],
                      dtype=torch.float64)
    q2 = torch.tensor([[2.0, 0, 0], [0, 0, 5], [-1, 0, 0], [0, 0, 5], [0, 0, 5]],
                      dtype=torch.float64)
    R, ok = torch_frame(p, q1, q2)
    assert ok.tolist() == [False, False, False, True, False]  # collinear, coincident, ...
    assert torch.isfinite(R).all()
    R3 = R[3]
    torch.testing.assert_close(R3 @ R3.T, torch.eye(3, dtype=torch.float64))
    assert torch.det(R3).item() == pytest.approx(1.0)


def test_quaternion_signs_are_continuous_and_tilt_is_applied():
    ang = torch.linspace(0, 3 * np.pi, 200, dtype=torch.float64)
    R = torch.zeros(200, 3, 3, dtype=torch.float64)
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1] = ang.cos(), -ang.sin(), ang.sin(), ang.cos()
    R[:, 2, 2] = 1
    q = quaternions(R)
    assert (q[1:] * q[:-1]).sum(-1).min() > 0.99  # no sign flips along the path
    Rt = tilt(torch.eye(3, dtype=torch.float64), work_deg=10.0)
    assert torch.rad2deg(torch.acos(Rt[2, 2])).item() == pytest.approx(10.0)


def test_ecal_two_crossings_of_one_arm_are_not_a_pair():
    # a dark streak along the left arm splits it in two on every circle and the right arm is
    # occluded: the two crossings are one arm, not the V (taken as a pair they gave a torch
    # axis 33 degrees off on a heavy-arc frame)
    mask, uv = _v_mask(occlude=True)
    cv2.line(mask, (150, 150), (20, 90), 255, 15)
    cv2.line(mask, (132, 142), (20, 90), 0, 1)  # from 20 px out: the corner stays joined
    ecal = load_ecal()
    res = ecal(mask, uv)
    assert not res.ok and np.all(np.isnan(res.p))
    prev = ecal(*_v_mask()).angles
    res = ecal(mask, uv, prev_angles=prev)
    assert not res.ok or abs(_wrap_deg(res.angles[0] - res.angles[1])) > 90


def _wrap_deg(a: float) -> float:
    return float(np.degrees((a + np.pi) % (2 * np.pi) - np.pi))


def test_ecal_arm_direction_from_few_circles_is_not_extrapolated():
    from torchseam.geometry.ecal import _tangent_points, load_ecal_config

    min_circles = load_ecal_config().min_extrapolation_circles

    uv = np.zeros(2)
    true = np.radians([160.0, 20.0])
    jitter = np.radians([[1.0, -1.0], [0.0, 0.0], [-1.0, 1.0], [1.0, -1.0], [0.0, 0.0]])
    assert min_circles > 3
    for n in (2, 3, 4, 5):
        radii = 25.0 + 10.0 * np.arange(n)
        pts = _tangent_points(uv, radii, true + jitter[:n], 50.0, min_circles)
        err = np.degrees(np.abs(np.arctan2(pts[:, 1], pts[:, 0]) - true))
        # a line through +-1 degree of noise on two or three close circles, extrapolated to
        # r = 0, lands 3.5-6 degrees off; the mean stays within the noise
        assert err.max() <= (1.0 if n <= 3 else 5.0)
    # with enough circles the chord's lean on a curved arm is extrapolated away
    radii = 25.0 + 10.0 * np.arange(7)
    lean = true + np.radians(0.05) * radii[:, None] * np.array([1, -1])
    pts = _tangent_points(uv, radii, lean, 50.0, min_circles)
    np.testing.assert_allclose(np.arctan2(pts[:, 1], pts[:, 0]), true, atol=1e-9)


def test_expected_pixel_follows_the_camera(cell, part, noise):
    """The stripe's crossing with the seam line through points seen before, projected from the
    camera's pose now, lands on the true feature pixel: closer than last frame's pixel does."""
    truths = [t for _, t in simulate(cell, part, noise,
                                     SequenceSpec(n_frames=14, level=0.0, seed=2))]
    tri = FastTriangulator(cell)
    F_C = invert(cell.hand_eye.matrix())
    errs, stays = [], []
    for k in range(8, 14):
        uv = tri.expect(truths[k - 8].seam_B, truths[k - 1].seam_B, truths[k].T_B_C @ F_C)
        errs.append(np.linalg.norm(uv - truths[k].uv))
        stays.append(np.linalg.norm(truths[k - 1].uv - truths[k].uv))
    assert max(errs) < 0.5, errs
    assert np.mean(errs) < 0.5 * np.mean(stays)
    # a seam line lying in the laser plane has no crossing
    p = truths[0].seam_B
    T = truths[0].T_B_C @ F_C
    n_B = (T @ cell.hand_eye.matrix())[:3, :3] @ np.asarray(cell.laser_plane.normal)
    along = np.cross(n_B, [0.0, 0.0, 1.0])
    assert tri.expect(p, p + along, T) is None


def test_single_rotation_to_quaternion_matches_the_batched_scipy_path():
    """matrix_to_quat takes a closed form for one (3, 3) matrix (the live loop's hot path):
    the same quaternions, w >= 0, as the batched scipy path, half-turns included."""
    from scipy.spatial.transform import Rotation

    from torchseam.core.transforms import matrix_to_quat

    R = np.concatenate([Rotation.random(2000, random_state=3).as_matrix(),
                        Rotation.from_rotvec(np.pi * np.eye(3)).as_matrix(),
                        Rotation.from_rotvec([[np.pi - 1e-7, 0, 0], [0, 1e-9, 0],
                                              [0, 0, 0]]).as_matrix()])
    batch = matrix_to_quat(R)
    one = np.stack([matrix_to_quat(r) for r in R])
    np.testing.assert_allclose(one, batch, atol=1e-12)
    assert np.all(one[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(one, axis=1), 1.0, atol=1e-12)


def test_ecal_does_not_take_the_arm_angle_where_the_arm_vanishes():
    """The right arm runs straight out to 40 px, bends 12 degrees over its last stretch and ends
    at 49 px (hidden by the other pipe): the circle at 45 px crosses the bent stretch, the one
    at 55 px finds one arm only. ECAL keeps the clean circle before the vanishing one."""
    ecal = load_ecal()
    c = np.array([150.0, 150.0])
    right = np.array([np.cos(np.radians(-25.0)), np.sin(np.radians(-25.0))])
    bent = np.array([np.cos(np.radians(-37.0)), np.sin(np.radians(-37.0))])
    knee = c + 40.0 * right

    def mask_with(end_px: float) -> np.ndarray:
        m = np.zeros((300, 300), np.uint8)
        cv2.line(m, (150, 150), (20, 90), 255, 5)
        cv2.line(m, (150, 150), tuple(int(round(v)) for v in knee), 255, 5)
        if end_px > 40:
            tip = knee + (end_px - 40.0) * bent
            cv2.line(m, tuple(int(round(v)) for v in knee), tuple(int(round(v)) for v in tip),
                     255, 5)
        return m
    res = ecal(mask_with(49.0), c)
    assert res.ok and res.radius == pytest.approx(ecal.circles[1])   # 35 px, not 45
    a = np.arctan2(*(res.p[1] - c)[::-1])
    assert abs(np.degrees(a) + 25.0) < 2.0                           # the straight part's angle
    # an arm ending at 40 px: clean on the 25 and 35 px circles; the 35 px one, next to where
    # it vanishes, is dropped as well (never the last one left)
    short = ecal(mask_with(30.0), c)
    assert short.ok and short.radius == pytest.approx(ecal.circles[0])


def _crossings_reference(ecal, on, val, uv):
    """ECAL's arm crossings as plain numpy (the vectorised statement the kernel replaced): runs
    paired rise -> fall on the rings doubled end to end, grey-weighted circular mean angles
    from cumulative sums, connection to the feature point from cumulative sums along radii."""
    cfg, n, rows = ecal.cfg, len(ecal._theta), ecal._circle_rows
    phasor = np.exp(1j * ecal._theta)
    ph2 = np.concatenate([[0], np.cumsum(np.tile(phasor, 2))])
    ring = on[rows]
    prev = np.roll(ring, 1, axis=1)
    rs, s0 = np.nonzero(ring & ~prev)
    re, e0 = np.nonzero(~ring & prev)
    ekey = np.sort(np.concatenate([re * 2 * n + e0, re * 2 * n + e0 + n]))
    skey = rs * 2 * n + s0
    length = ekey[np.searchsorted(ekey, skey)] - skey
    row = rows[rs]
    r = ecal.ring_radii[row]
    width = length * (2 * np.pi / n) * r
    ok = (width >= cfg.min_width_px) & (width <= cfg.max_width_px)
    z = ph2[s0 + length] - ph2[s0]
    if val is not None:
        v = val[rows]
        v2 = np.concatenate([np.zeros((len(rows), 1)), np.cumsum(np.hstack([v, v]), 1)], 1)
        vp = v * phasor
        vp2 = np.concatenate([np.zeros((len(rows), 1), complex),
                              np.cumsum(np.hstack([vp, vp]), 1)], 1)
        wsum = v2[rs, s0 + length] - v2[rs, s0]
        z = np.where(wsum > 0, vp2[rs, s0 + length] - vp2[rs, s0], z)
    ang = np.angle(z)
    k = np.rint(ang * n / (2 * np.pi)).astype(int) % n
    lo = (0.15 * row).astype(int)
    cum = np.concatenate([np.zeros((1, n), int), np.cumsum(on, axis=0)])
    good = ok & ((cum[row + 1, k] - cum[lo, k]) >= cfg.min_connected * (row + 1 - lo))
    px = uv + r[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    return [([(ang[i], px[i]) for i in np.flatnonzero(good & (rs == c))],
             int(np.sum(~good & (rs == c)))) for c in range(len(rows))]


def test_ecal_compiled_crossings_match_their_numpy_statement(cell, part, noise, tipm):
    """The compiled crossings kernel against the numpy statement, on the stripe windows the
    live loop hands ECAL (TIPM's ridge and mask around the true point) of clean and heavy-arc
    frames, spatter and glare included, and one window at the frame's border. With grey
    levels, as the live loop runs ECAL: without them an even-length run's mean angle lies
    exactly between two samples, and which of the two rays the connection test walks is left
    to rounding in either version (the ECAL tests above cover that path by behaviour)."""
    ecal = load_ecal()
    frames = list(simulate(cell, part, noise, SequenceSpec(n_frames=60, level=1.0, seed=3)))
    frames += list(simulate(cell, part, noise, SequenceSpec(n_frames=4, level=0.0, seed=3)))
    windows = []
    for img, t in frames:
        for uv in (t.uv, np.array([60.0, t.uv[1]])):  # the second: ECAL's rings leave the image
            red, mask, (x0, y0) = tipm.mask_around(img, uv, int(ecal.cfg.r_max_px) + 8)
            windows.append((red, mask, uv - (x0, y0)))
    # a V with a blob too wide for a stripe joined to its corner, grey levels rising to the right
    mask = np.zeros((200, 200), np.uint8)
    cv2.line(mask, (100, 100), (10, 60), 255, 5)
    cv2.line(mask, (100, 100), (190, 60), 255, 5)
    cv2.line(mask, (100, 100), (100, 190), 255, 31)
    windows.append((((mask > 0) * np.linspace(100, 200, 200)[None]).astype(np.uint8), mask,
                    np.array([100.0, 100.0])))
    n_cross = n_rejected = 0
    for red, mask, local in windows:
        on, val = ecal.polar(mask, local, red)
        got = ecal.crossings(on, val, local)
        want = _crossings_reference(ecal, on, val, local)
        assert [g[1] for g in got] == [w[1] for w in want]
        for (g, _), (w, _) in zip(got, want, strict=True):
            assert len(g) == len(w)
            for (ga, gp), (wa, wp) in zip(g, w, strict=True):
                assert ga == pytest.approx(wa, abs=1e-9)
                np.testing.assert_allclose(gp, wp, atol=1e-9)
            n_cross += len(g)
        n_rejected += sum(g[1] for g in got)
    assert n_cross > 500 and n_rejected > 20  # crossings and rejected spatter were compared


def test_ecal_compiled_polar_sampling_is_the_numpy_gather_to_the_bit(cell, part, noise, tipm):
    """ECAL's rings gathered in one compiled pass (``_kernels.polar``) against the numpy
    gather it replaces (ring offsets plus the point, rounded, one flat index), with and
    without grey levels, on heavy-arc stripe windows and on views of a larger window (how
    the live locator lends the tracker's planes), points at sub-pixel places."""
    ecal = load_ecal()
    rng = np.random.default_rng(2)
    n = 0
    for img, t in simulate(cell, part, noise, SequenceSpec(n_frames=6, level=1.0, seed=5)):
        red, mask, (x0, y0) = tipm.mask_around(img, t.uv, int(ecal.cfg.r_max_px) + 30)
        for dy, dx in ((0, 0), (7, 19)):
            r_win, m_win = red[dy:dy + 199, dx:dx + 201], mask[dy:dy + 199, dx:dx + 201]
            for local in (t.uv - (x0 + dx, y0 + dy), rng.uniform(92, 106, 2),
                          np.array([99.5, 100.5])):
                h, w = m_win.shape
                iu = np.rint(local[0] + ecal._ru).astype(np.intp)
                iv = np.rint(local[1] + ecal._rv).astype(np.intp)
                if iu.min() < 0 or iv.min() < 0 or iu.max() >= w or iv.max() >= h:
                    continue
                on, val = ecal.polar(m_win, local, r_win)
                np.testing.assert_array_equal(on, m_win[iv, iu] > 0)
                np.testing.assert_array_equal(val, r_win[iv, iu].astype(float))
                on2, val2 = ecal.polar(m_win, local, None)
                np.testing.assert_array_equal(on2, on)
                assert val2 is None
                n += 1
    assert n >= 24


def test_numpy_torch_frame_matches_the_torch_one():
    import torch

    from torchseam.core.transforms import axis_rotation, matrix_to_quat
    from torchseam.geometry.torch_frame import frame_from_arms, quaternions, tilt, torch_frame

    rng = np.random.default_rng(0)
    for _ in range(20):
        p, a1, a2 = rng.normal(size=3) * 300, rng.normal(size=3) * 5, rng.normal(size=3) * 5
        t = rng.normal(size=3)
        P = torch.tensor(p)[None]
        R, ok = torch_frame(P, P + torch.tensor(a1)[None], P + torch.tensor(a2)[None],
                            tangent=torch.tensor(t)[None])
        Rn, okn = frame_from_arms(p, p + a1, p + a2, t)
        assert okn == bool(ok[0])
        np.testing.assert_allclose(Rn, R[0].numpy(), atol=1e-12)
        Rt = tilt(R, 4.0, -6.0)[0].numpy()
        np.testing.assert_allclose(Rn @ axis_rotation(0, 4.0) @ axis_rotation(1, -6.0), Rt,
                                   atol=1e-12)
        np.testing.assert_allclose(matrix_to_quat(Rt), quaternions(torch.tensor(Rt[None]))[0],
                                   atol=1e-12)
    # collinear arms: no frame
    p = np.zeros(3)
    assert not frame_from_arms(p, p + [0, 1.0, 0], p + [0, 2.0, 0], np.array([1.0, 0, 0]))[1]


def test_arms_in_one_line_give_the_frame_across_it_where_the_torch_faces():
    """A butt's stripe runs on straight across its gap: no corner to bisect. With where the
    torch points now (``facing``) the frame is the line's normal in the plane across the seam,
    on that side (the surface's normal, into it); the numpy and torch frames agree; without
    ``facing`` and for arms folded onto one side (not opposite) there is still no frame."""
    import torch

    from torchseam.geometry.torch_frame import frame_from_arms, torch_frame

    rng = np.random.default_rng(1)
    for _ in range(20):
        # a surface through p with normal n, the seam along t in it, the stripe across
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        t = np.cross(n, rng.normal(size=3))
        t /= np.linalg.norm(t)
        line = np.cross(t, n)
        p = rng.normal(size=3) * 300
        a1 = 8.0 * line + 0.01 * rng.normal(size=3)          # opposite arms, within 1 degree
        a2 = -6.0 * line + 0.01 * rng.normal(size=3)
        facing = -n + 0.4 * rng.normal(size=3)                # the torch points into it, roughly
        Rn, ok = frame_from_arms(p, p + a1, p + a2, t, facing)
        assert ok
        assert Rn[:, 2] @ -n > 0.9995                         # wz: into the surface
        assert Rn[:, 0] @ t > 0.998                           # wx: along the travel
        np.testing.assert_allclose(Rn.T @ Rn, np.eye(3), atol=1e-12)
        assert np.linalg.det(Rn) > 0
        P = torch.tensor(p)[None]
        R, okt = torch_frame(P, P + torch.tensor(a1)[None], P + torch.tensor(a2)[None],
                             tangent=torch.tensor(t)[None],
                             facing=torch.tensor(facing)[None])
        assert bool(okt[0])
        np.testing.assert_allclose(Rn, R[0].numpy(), atol=1e-12)
        assert not frame_from_arms(p, p + a1, p + a2, t)[1]    # no facing: no frame
        assert not frame_from_arms(p, p + a1, p + 2 * a1, t, facing)[1]   # one side: none
