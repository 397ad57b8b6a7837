"""The simulated joint against the closed form of METHOD.md section 0 and its own surfaces."""

import dataclasses

import numpy as np
import pytest
from scipy.integrate import quad

from torchseam.core.config import CONFIG_DIR, load_part
from torchseam.sim.joint import PipeJoint, closed_form_orthogonal_seam
from torchseam.sim.scene import Scene, torch_frames


def test_ideal_seam_matches_closed_form():
    part = load_part(CONFIG_DIR / "parts" / "ideal.yaml")
    joint = PipeJoint(part)
    phi = np.linspace(0, 2 * np.pi, 361)
    closed = closed_form_orthogonal_seam(101.5, 76.0, phi)
    np.testing.assert_allclose(joint.seam(phi).point, closed, atol=1e-9)


def test_ideal_seam_length_matches_integral():
    part = dataclasses.replace(load_part(), branch_offset_mm=(0.0, 0.0), main_ovality=0.0,
                               intersection_angle_deg=90.0)
    R, r = 101.5, 76.0

    def speed(p):  # |d seam / d phi| of the closed form
        dz = -(r**2) * np.sin(p) * np.cos(p) / np.sqrt(R**2 - r**2 * np.sin(p) ** 2)
        return np.sqrt(r**2 + dz**2)

    expected = quad(speed, 0, 2 * np.pi, limit=200)[0]
    _, s = PipeJoint(part).arc_length_table(8192)
    assert s[-1] == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize("angle", [60.0, 72.5, 90.0])
def test_deviated_seam_lies_on_both_surfaces(angle):
    part = dataclasses.replace(load_part(), intersection_angle_deg=angle,
                               branch_offset_mm=(3.0, -4.0), main_ovality=0.02)
    j = PipeJoint(part)
    s = j.seam(np.linspace(0, 2 * np.pi, 500, endpoint=False))
    p = s.point
    on_main = (p[:, 1] / j.a) ** 2 + (p[:, 2] / j.b) ** 2 - 1
    q = p - j.o
    radial = q - (q @ j.d)[:, None] * j.d
    np.testing.assert_allclose(on_main, 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), j.r, atol=1e-9)
    # the tangent lies in both tangent planes; numeric derivative agrees
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.tangent, s.normal_main), 0, atol=1e-9)
    np.testing.assert_allclose(np.einsum("ij,ij->i", s.tangent, s.normal_branch), 0, atol=1e-9)
    h = 1e-6
    num = (j.seam(s.phi + h).point - j.seam(s.phi - h).point) / (2 * h)
    num /= np.linalg.norm(num, axis=1, keepdims=True)
    np.testing.assert_allclose(num, s.tangent, atol=1e-6)


def test_raycast_hits_lie_on_the_surfaces():
    j = PipeJoint(dataclasses.replace(load_part(), intersection_angle_deg=75.0))
    rng = np.random.default_rng(0)
    origin = np.array([20.0, 150.0, 250.0])
    target = rng.uniform([-120, -100, 0], [120, 100, 110], (400, 3))
    d = (target - origin) / np.linalg.norm(target - origin, axis=1, keepdims=True)
    t, surf = j.raycast(origin, d)
    assert (surf > 0).sum() > 200
    P = origin + t[surf > 0, None] * d[surf > 0]
    main = surf[surf > 0] == 1
    Pm, Pb = P[main], P[~main]
    np.testing.assert_allclose((Pm[:, 1] / j.a) ** 2 + (Pm[:, 2] / j.b) ** 2, 1, atol=1e-9)
    q = Pb - j.o
    np.testing.assert_allclose(np.linalg.norm(q - (q @ j.d)[:, None] * j.d, axis=1), j.r,
                               atol=1e-9)
    # main-pipe hits are outside the branch and vice versa (first hit of the union)
    q = Pm - j.o
    hm = q @ j.d
    outside_branch = (np.linalg.norm(q - hm[:, None] * j.d, axis=1) >= j.r - 1e-9) | (hm <= 0)
    assert outside_branch.all()


def test_torch_frames_are_right_handed_and_bisect_the_corner():
    scene = Scene(load_part())
    T = scene.nominal_tcp(np.linspace(0, scene.seam_length_mm, 60, endpoint=False))
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    s = scene.nominal_joint.seam(np.linspace(0, 2 * np.pi, 60, endpoint=False))
    F = torch_frames(s)
    # the torch axis makes equal angles with both surfaces (it bisects the corner)
    a1 = np.einsum("ij,ij->i", F[:, :3, 2], s.normal_main)
    a2 = np.einsum("ij,ij->i", F[:, :3, 2], s.normal_branch)
    np.testing.assert_allclose(a1, a2, atol=1e-9)
    assert (a1 < 0).all()  # points into the metal
