"""The simulated sensor: labels are projections of the 3D truth; stripes lie on the plane."""

import cv2
import numpy as np
import pytest
import torch

from torchseam.core.camera import intrinsics, laser_plane_tensor, pixels_to_plane, project_points
from torchseam.core.transforms import apply, invert
from torchseam.sim.noise import ArcNoise
from torchseam.sim.scene import Scene
from torchseam.sim.sensor import ARM_DISTANCE_MM


def test_label_is_the_projection_of_the_3d_seam_point(cell, clean_seq):
    K, dist = intrinsics(cell.camera)
    for _, t in clean_seq:
        X_C = apply(invert(t.T_B_C), t.seam_B)
        uv = project_points(torch.tensor(X_C), K, dist).numpy()
        assert np.linalg.norm(uv - t.uv) < 0.01
        assert t.visible


def test_torch_camera_matches_opencv(cell):
    K, dist = intrinsics(cell.camera)
    rng = np.random.default_rng(1)
    X = rng.uniform([-40, -30, 100], [40, 30, 180], (200, 3))
    ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), cell.camera.K,
                               np.array(cell.camera.dist))
    uv = project_points(torch.tensor(X), K, dist)
    np.testing.assert_allclose(uv.numpy(), ref.reshape(-1, 2), atol=1e-9)
    und = cv2.undistortPoints(ref, cell.camera.K, np.array(cell.camera.dist),
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 0))
    from torchseam.core.camera import undistort_points

    np.testing.assert_allclose(undistort_points(uv, K, dist).numpy(), und.reshape(-1, 2),
                               atol=1e-9)
    np.testing.assert_allclose(undistort_points(uv, K, dist).numpy(), X[:, :2] / X[:, 2:],
                               atol=1e-9)


def test_back_projected_stripe_lies_on_plane_and_part(cell, part, clean_seq):
    """Stripe pixels back-projected onto the laser plane land on the true 3D points."""
    K, dist = intrinsics(cell.camera)
    plane = laser_plane_tensor(cell.laser_plane)
    scene = Scene(part)
    for _, t in clean_seq[:4]:
        uv = torch.tensor(np.vstack([t.uv[None], t.arm_uv]))
        X_C = pixels_to_plane(uv, K, dist, plane).numpy()
        X_B = apply(t.T_B_C, X_C)
        np.testing.assert_allclose(X_B[0], t.seam_B, atol=1e-6)
        np.testing.assert_allclose(X_B[1:], t.arm_B, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(t.arm_B - t.seam_B, axis=1), ARM_DISTANCE_MM,
                                   atol=1e-6)
        # the arm points lie on the branch (first) and main pipe (second) surfaces
        j = scene.true_joint
        P_T = apply(invert(scene.part_pose(t.t_s)), t.arm_B)
        q = P_T[0] - j.o
        assert abs(np.linalg.norm(q - (q @ j.d) * j.d) - j.r) < 1e-6
        assert abs((P_T[1, 1] / j.a) ** 2 + (P_T[1, 2] / j.b) ** 2 - 1) < 1e-9


def test_rendered_stripe_centre_is_on_the_part(cell, part, clean_seq):
    """The brightest row in each column of the rendered stripe back-projects onto the part."""
    K, dist = intrinsics(cell.camera)
    plane = laser_plane_tensor(cell.laser_plane)
    scene = Scene(part)
    img, t = clean_seq[0]
    red = img[..., 2].astype(float)
    cols = np.arange(40, 620, 7)
    v = np.array([np.sum(np.arange(492) * np.where(red[:, c] > 120, red[:, c], 0))
                  / max(np.sum(np.where(red[:, c] > 120, red[:, c], 0)), 1) for c in cols])
    keep = np.abs(cols - t.uv[0]) > 8  # skip the corner where the two arms overlap
    uv = torch.tensor(np.stack([cols[keep], v[keep]], axis=1).astype(float))
    P_T = apply(invert(scene.part_pose(t.t_s)) @ t.T_B_C,
                pixels_to_plane(uv, K, dist, plane).numpy())
    j = scene.true_joint
    q = P_T - j.o
    d_branch = np.abs(np.linalg.norm(q - (q @ j.d)[:, None] * j.d, axis=1) - j.r)
    d_main = np.abs(np.sqrt((P_T[:, 1] / j.a) ** 2 + (P_T[:, 2] / j.b) ** 2) - 1) * j.a
    # within 0.1 mm of one of the surfaces (about a pixel at 0.08 mm/px)
    assert np.max(np.minimum(d_branch, d_main)) < 0.1


def test_arc_noise_levels_scale_the_light(noise):
    size = (656, 492)
    arc, stripe = np.array([330.0, 420.0]), np.array([330.0, 240.0])
    energy = []
    for level in (0.0, 0.3, 1.0):
        gen = ArcNoise(noise, level, size, seed=5)
        e = 0.0
        for _ in range(20):
            layers = gen.next(arc, stripe)
            e += float(layers.glare.sum() + layers.spatter.sum())
        energy.append(e)
    assert energy[0] == 0.0 and energy[0] < energy[1] < energy[2]


def test_heavy_noise_has_bursts_flashes_and_dropouts(cell, part, noise):
    from torchseam.sim.sequence import SequenceSpec, simulate

    flags = [t.flags for _, t in simulate(cell, part, noise,
                                          SequenceSpec(n_frames=150, level=1.0, seed=11))]
    assert sum(f.burst for f in flags) > 0
    assert sum(f.dropout for f in flags) > 10
    assert sum(f.spatter for f in flags) > 150 * 5
    assert not any(f.spatter for f in flags[: noise.clean_lead_frames])


def test_laser_off_frames_have_no_stripe(cell, part, noise):
    from torchseam.sim.sequence import SequenceSpec, simulate

    out = list(simulate(cell, part, noise, SequenceSpec(n_frames=3, seed=2, laser_off=(1,))))
    (on, t_on), (off, t_off) = out[0], out[1]
    assert t_on.visible and not t_off.visible and not t_off.laser_on
    assert on[..., 2].max() > 200 and off[..., 2].max() < 60


def test_compiled_finish_pass_is_numpys_to_the_bit():
    """The renderer's last pass (background, read noise times sigma, clip, uint8) compiled in
    one pass gives the numpy passes' pixels exactly (float32, same order of operations)."""
    from torchseam.core.kernels import load_kernels

    k = load_kernels("torchseam.sim")
    rng = np.random.default_rng(4)
    h, w = 61, 83
    for trial in range(30):
        light = (rng.random((h, w, 3), dtype=np.float32) * rng.choice([5, 300, 900])
                 - rng.choice([0, 20])).astype(np.float32)
        bg = rng.random((h, w, 3), dtype=np.float32) * 6
        field = rng.standard_normal((h + 16, w + 16, 3), dtype=np.float32)
        dy, dx = (int(x) for x in rng.integers(0, 16, 2))
        sigma = float(rng.uniform(0.5, 12.0)) if trial % 2 else float(np.hypot(3.0, 1.7))
        img = light.copy()
        img += bg
        tmp = np.empty_like(img)
        np.multiply(field[dy:dy + h, dx:dx + w], sigma, out=tmp)
        img += tmp
        ref = np.clip(img, 0, 255, out=img).astype(np.uint8)
        out = np.empty((h, w, 3), np.uint8)
        k.finish_frame(light.reshape(h, -1), bg.reshape(h, -1), field.reshape(h + 16, -1), dy,
                       dx * 3, np.float32(sigma), out.reshape(h, -1))
        np.testing.assert_array_equal(out, ref)


def test_fused_colour_mix_and_finish_pass_is_the_two_calls_to_the_bit():
    """The renderer's colour mix (cv2.transform of the merged stripe, glare and spatter
    layers) and its last pass, compiled in one pass (``_kernels.mix_finish``), give the two
    calls' light and frame exactly where the renderer uses it (``_fused_mix_agrees``: OpenCV's
    AVX2 path, this machine); a whole rendered frame is the same either way."""
    from torchseam.core.config import load_cell, load_noise, load_part
    from torchseam.sim.sequence import COLOUR_MIX, SensorRenderer, _fused_mix_agrees

    cell = load_cell()
    w, h = cell.camera.width, cell.camera.height
    if not _fused_mix_agrees(COLOUR_MIX, w, h):
        pytest.skip("this OpenCV's cv2.transform is not the kernel's arithmetic: the renderer "
                    "makes the two calls here")
    for size in ((96, 64), (640, 480), (w, h)):
        assert _fused_mix_agrees(COLOUR_MIX * np.float32(0.7), *size)
    scene = Scene(load_part(), 0.0)
    noise = load_noise()
    fused = SensorRenderer(cell, scene, noise, 1.0, 3)
    calls = SensorRenderer(cell, scene, noise, 1.0, 3)
    assert fused._fused
    calls._fused = False
    s0 = 30.0
    for k in range(6):
        T = scene.nominal_tcp(np.array([s0 + 0.4 * k]))[0]
        a, ta = fused.render(T, 0.04 * k, arc_on=k > 1, force_flash=k == 4)
        b, tb = calls.render(T, 0.04 * k, arc_on=k > 1, force_flash=k == 4)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(ta.uv, tb.uv)


def test_compiled_projection_is_opencvs_to_the_bit():
    """The sensor's projection, compiled (``_kernels.project_points``: OpenCV's arithmetic
    without the Jacobian it also computes), gives ``cv2.projectPoints``'s pixels to the bit:
    on points all over the view, behind the camera and at depth zero, and on a rendered
    view's stripe; where a probe finds otherwise the sensor calls OpenCV."""
    from torchseam.core.config import load_cell, load_part
    from torchseam.sim.sensor import LaserSensor, _projection_agrees

    cell = load_cell()
    sensor = LaserSensor(cell)
    if sensor._project is None:
        pytest.skip("this OpenCV's projectPoints is not the kernel's arithmetic: the sensor "
                    "calls OpenCV here")
    kernel = sensor._project
    rng = np.random.default_rng(11)
    X = np.c_[rng.uniform(-80.0, 80.0, (20000, 2)), rng.uniform(-20.0, 300.0, 20000)]
    X[::37, 2] = 0.0
    X[5] = np.nan

    def opencv(P):
        return cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), sensor.K,
                                 sensor.dist)[0].reshape(-1, 2)

    np.testing.assert_array_equal(sensor.project(X), opencv(X))
    scene = Scene(load_part(), 0.0)
    T_B_C = scene.nominal_tcp(np.array([30.0]))[0] @ invert(cell.tool.matrix()) \
        @ cell.hand_eye.matrix()
    T_T_C = invert(scene.part_pose(0.0)) @ T_B_C
    view = sensor.view(scene.true_joint, T_T_C)
    sensor._project = None   # OpenCV's call
    ref = sensor.view(scene.true_joint, T_T_C)
    assert len(view.uv) > 500 and view.visible
    for a, b in ((view.uv, ref.uv), (view.seam_uv, ref.seam_uv), (view.arm_uv, ref.arm_uv)):
        np.testing.assert_array_equal(a, b)
    # a probe that disagrees (another camera model's arithmetic) falls back to OpenCV
    assert _projection_agrees(kernel, sensor._K, sensor.dist, sensor._k14)
    wrong = sensor._k14.copy()
    wrong[0] += 1e-9
    assert not _projection_agrees(kernel, sensor._K, sensor.dist, wrong)


def test_reused_planes_zeroed_where_drawn_give_the_frames_of_planes_zeroed_whole():
    """The renderer's stripe plane and its arc noise's spatter plane are zeroed, frame to
    frame, only where the last frame drew into them: a sequence (the stripe moving, spatter
    streaks coming and going, a frame without the laser) is the same to the bit as with both
    planes zeroed whole before every frame."""
    from torchseam.core.config import load_cell, load_noise, load_part
    from torchseam.sim.sequence import SensorRenderer

    cell = load_cell()
    scene = Scene(load_part(), 0.0)
    noise = load_noise()
    part, whole = (SensorRenderer(cell, scene, noise, 2.0, 5) for _ in range(2))
    drawn = 0
    for k in range(6):
        T = scene.nominal_tcp(np.array([30.0 + 1.5 * k]))[0]
        whole.sensor._stripe_drawn = None          # the whole plane zeroed
        whole.arc_noise._spatter_drawn = (slice(None), slice(None))
        if whole.arc_noise._planes is not None:   # the glare plane: written whole, or zeroed
            whole.arc_noise._planes[0].fill(np.nan)
        a, _ = part.render(T, 0.04 * k, laser_on=k != 4)
        b, _ = whole.render(T, 0.04 * k, laser_on=k != 4)
        np.testing.assert_array_equal(a, b, err_msg=f"frame {k}")
        drawn += part.arc_noise._spatter_drawn is not None
        assert part.sensor._stripe_drawn is not None
    assert drawn >= 3   # spatter drawn in several frames, so stale streaks would show


def test_arc_noise_reusing_its_planes_gives_fresh_planes_numbers():
    """The arc noise's own planes, reused (the glare plane left unzeroed where the glare
    template covers the whole image, the spatter plane zeroed where the last frame drew),
    hold the numbers of fresh all-zero planes frame after frame, the arc off the image
    (the template covering part of it) included."""
    from torchseam.core.config import load_noise

    noise = load_noise()
    reused, fresh = (ArcNoise(noise, 2.0, (160, 120), 9) for _ in range(2))
    stripe = np.array([80.0, 40.0])
    # (the template's radius is ~1 000 px at this level: far off the image it covers part of
    # it, or none)
    for k, arc in enumerate([(80, 100), (80, 100), (1100, 60), (70, 110), (2500, -1800),
                             (75, 105), (-1100, 50), (80, 101)]):
        a = reused.next(np.array(arc, float), stripe, reuse=True)
        b = fresh.next(np.array(arc, float), stripe)
        np.testing.assert_array_equal(a.glare, b.glare, err_msg=f"glare, frame {k}")
        np.testing.assert_array_equal(a.spatter, b.spatter, err_msg=f"spatter, frame {k}")


def test_roots_refined_in_lockstep_are_each_brackets_own():
    """The sensor's arm points: two roots refined together (one call of the function per
    round) are the roots each search finds alone, to the bit; a bracket without a sign change
    stops narrowing on its own."""
    from torchseam.sim.sensor import _refine_root, _refine_roots

    def f(x):
        return np.sin(3.0 * x) - 0.2 * x

    brackets = [(0.9, 1.2), (-0.4, 0.3), (2.0, 2.1)]  # the last holds no root
    together = _refine_roots(f, brackets)
    alone = []
    for lo, hi in brackets:  # the search as it was written for one bracket
        for _ in range(4):
            x = np.linspace(lo, hi, 33)
            y = f(x)
            kk = np.nonzero(np.sign(y[1:]) != np.sign(y[:-1]))[0]
            if len(kk) == 0:
                break
            lo, hi = x[kk[0]], x[kk[0] + 1]
        ylo, yhi = f(np.array([lo, hi]))
        alone.append(float(lo - ylo * (hi - lo) / (yhi - ylo)) if yhi != ylo else float(lo))
    assert together == alone
    assert [_refine_root(f, *b) for b in brackets] == alone
    calls = []
    _refine_roots(lambda x: calls.append(len(x)) or f(x), brackets)
    # four rounds, the interpolation on values the rounds computed (the bracket without a
    # root is evaluated in the first round only)
    assert calls == [99, 66, 66, 66]
    assert abs(f(np.array([together[0]]))[0]) < 1e-12


def test_compiled_splat_sums_as_bincount_does():
    """The stripe's bilinear splat, compiled: the four corners' np.bincount sums, to the bit
    (points in and off the image, dense and sparse)."""
    from torchseam.sim.sensor import _splat

    rng = np.random.default_rng(6)
    h, w = 70, 90
    for trial in range(60):
        n = int(rng.integers(1, 3000))
        pts = rng.uniform(-4, 95, (n, 2)) if trial % 2 else rng.normal(40, 3, (n, 2))
        weight = rng.random(n) * float(rng.choice([0.01, 1.0, 100.0]))
        img, box = _splat(pts, weight, w, h)
        inside = (pts[:, 0] > -1) & (pts[:, 0] < w) & (pts[:, 1] > -1) & (pts[:, 1] < h)
        p, wt = pts[inside], weight[inside]
        ref = np.zeros((h, w), np.float32)
        if len(p):
            x0, y0 = np.floor(p[:, 0]).astype(int), np.floor(p[:, 1]).astype(int)
            fx, fy = p[:, 0] - x0, p[:, 1] - y0
            bx, by = x0.min(), y0.min()
            bw, bh = x0.max() - bx + 2, y0.max() - by + 2
            acc = np.zeros(bw * bh)
            for dx, dy, c in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                              (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
                acc += np.bincount((y0 - by + dy) * bw + (x0 - bx + dx), weights=wt * c,
                                   minlength=acc.size)
            acc = acc.reshape(bh, bw)
            sx, sy, ex, ey = max(0, -bx), max(0, -by), min(bw, w - bx), min(bh, h - by)
            ref[by + sy:by + ey, bx + sx:bx + ex] = acc[sy:ey, sx:ex]
            assert box == (int(bx + sx), int(by + sy), int(bx + ex), int(by + ey))
        else:
            assert box is None
        np.testing.assert_array_equal(img, ref)


def test_a_camera_that_sees_no_part_projects_nothing():
    """OpenCV answers None to no points; a camera looking past the part (the virtual cell's
    robot on its way to a girth joint's start: the laser misses the pipe) gets no points, and
    the frame renders dark instead of the camera process dying."""
    import numpy as np

    from torchseam.core.config import load_cell
    from torchseam.sim.sensor import LaserSensor

    assert LaserSensor(load_cell()).project(np.zeros((0, 3))).shape == (0, 2)


def test_compiled_stripe_samples_are_the_numpy_statements():
    """The stripe's splat samples, compiled: np.diff, the row norms, np.repeat and the
    interpolated brightness of the numpy statement, to the bit (gaps not bridged)."""
    from torchseam.core.kernels import load_kernels
    from torchseam.sim.sensor import SPLAT_STEP_PX

    k = load_kernels("torchseam.sim")
    rng = np.random.default_rng(8)
    for trial in range(40):
        n = int(rng.integers(2, 400))
        uv = np.cumsum(rng.normal(0.0, 1.5 if trial % 2 else 4.0, (n, 2)), axis=0) + 300.0
        bright = rng.random(n)
        pts, step, weight, starts = k.stripe_samples(uv, bright, SPLAT_STEP_PX, 6.0)
        seg = np.diff(uv, axis=0)
        seg_len = np.linalg.norm(seg, axis=1)
        n_sub = np.maximum(1, np.ceil(seg_len / SPLAT_STEP_PX).astype(int)) * (seg_len < 6.0)
        s = np.repeat(np.arange(len(seg)), n_sub)
        frac = (np.arange(n_sub.sum()) - np.repeat(np.cumsum(n_sub) - n_sub, n_sub)) / np.repeat(
            np.maximum(n_sub, 1), n_sub)
        want_step = seg_len[s] / np.maximum(n_sub[s], 1)
        np.testing.assert_array_equal(starts, s)
        np.testing.assert_array_equal(pts, uv[s] + frac[:, None] * seg[s])
        np.testing.assert_array_equal(step, want_step)
        np.testing.assert_array_equal(weight, (bright[s] * (1 - frac) + bright[s + 1] * frac)
                                      * want_step)
