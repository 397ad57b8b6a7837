"""The torch body of the reachability gate's clearance check (configs/robot.yaml ``torch``): a
bottleneck nozzle (a cone widening from the nozzle's front to the body) and the body (a
cylinder), against hand-computed clearances and a brute-force sweep along the torch axis."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from torchseam.core.config import CONFIG_DIR, ConfigError, load_cell, load_part
from torchseam.robot.config import load_robot_config, robot_config_from_dict
from torchseam.robot.kinematics import IRB1410
from torchseam.robot.reach import ReachGate, _segment_convex_distance

PARTS = CONFIG_DIR / "parts"


def _gate(part_name: str, **torch_kw) -> ReachGate:
    cfg = load_robot_config()
    cfg = dataclasses.replace(cfg, torch=dataclasses.replace(cfg.torch, **torch_kw))
    return ReachGate(IRB1410(config=cfg), cell=load_cell(),
                     part=load_part(PARTS / f"{part_name}.yaml"))


def _plate_pose(part, alpha_deg: float, h_mm: float, x_mm: float = -200.0) -> np.ndarray:
    """A torch TCP h mm above the plate's top, its axis (z, into the part) tilted alpha from
    the plate's normal about the base y axis, far from the branch."""
    a = np.radians(alpha_deg)
    z = np.array([np.sin(a), 0.0, -np.cos(a)])   # tip first: the body lies along -z, up
    y = np.array([0.0, 1.0, 0.0])
    T = np.eye(4)
    T[:3, :3] = np.column_stack([np.cross(y, z), y, z])
    T[:3, 3] = part.placement.matrix()[:3, 3] + [x_mm, 0.0, h_mm]
    return T


def test_the_configured_torch_is_a_bottleneck_nozzle_on_a_wider_body():
    tc = load_robot_config().torch
    (d0, d1, r0, r1), (e0, e1, s0, s1) = tc.pieces()
    assert (d0, d1) == (tc.tip_exclusion_mm, tc.nozzle_length_mm) and (e0, e1) == (
        tc.nozzle_length_mm, tc.length_mm)
    assert r0 == tc.nozzle_radius_mm < r1 == s0 == s1 == tc.radius_mm
    assert 6.5 <= tc.nozzle_radius_mm <= 8.0   # a 13-16 mm nozzle front
    assert tc.radius_at(tc.tip_exclusion_mm) == tc.nozzle_radius_mm
    assert tc.radius_at(0.5 * (d0 + d1)) == pytest.approx(0.5 * (r0 + r1))
    assert tc.radius_at(200.0) == tc.radius_mm and tc.radius_at(10.0) == 0.0


@pytest.mark.parametrize("alpha", [0.0, 60.0, 88.0])
def test_clearance_to_the_plate_hand_computed(alpha):
    """Over a plate the clearance of the axis point d mm behind the tip is h + d cos(alpha)
    less the torch's radius there: with the nozzle the smallest is at its front (steep torch)
    or at its back end where the body starts (a torch nearly parallel to the plate: the cone
    widens faster than the axis rises)."""
    g = _gate("pipe_on_plate")
    tc = g.config.torch
    part = g.part
    h = 20.0
    T = _plate_pose(part, alpha, h)
    c = g._clearance(T[None])[0, 0]
    d = np.linspace(tc.tip_exclusion_mm, tc.length_mm, 100001)
    expected = min(h + di * np.cos(np.radians(alpha)) - tc.radius_at(di) for di in
                   (tc.tip_exclusion_mm, tc.nozzle_length_mm, tc.length_mm))
    r = np.interp(d, [tc.tip_exclusion_mm, tc.nozzle_length_mm, tc.length_mm],
                  [tc.nozzle_radius_mm, tc.radius_mm, tc.radius_mm])
    brute = float(np.min(h + d * np.cos(np.radians(alpha)) - r))
    assert c == pytest.approx(expected, abs=1e-6) and c == pytest.approx(brute, abs=1e-4)
    if alpha == 88.0:   # the nozzle's back end is nearest: the cone is checked all along
        assert expected == pytest.approx(h + tc.nozzle_length_mm * np.cos(np.radians(alpha))
                                         - tc.radius_mm)
    # the same torch as a cylinder is nearer by (radius - nozzle radius) at a steep angle
    cyl = _gate("pipe_on_plate", nozzle_length_mm=0.0)._clearance(T[None])[0, 0]
    if alpha == 0.0:
        assert c - cyl == pytest.approx(tc.radius_mm - tc.nozzle_radius_mm, abs=1e-6)


def test_cone_clearance_brute_force_on_every_part_kind():
    """Random torch poses near the seam of each kind of main body (pipe, plate, sphere) and the
    branch: the gate's clearance of the nozzle and body equals the brute-force minimum, over
    axis points every 0.05 mm, of the solid's distance less the radius there (never more: the
    check never calls a torch clear that is not)."""
    from torchseam.core.transforms import rotation_about
    from torchseam.robot.reach import nominal_torch_poses

    rng = np.random.default_rng(3)
    for name in ("t_joint", "pipe_on_plate", "pipe_on_sphere"):
        g = _gate(name)
        tc = g.config.torch
        T = nominal_torch_poses(g.part, 24).numpy()
        # tilted and lifted off the seam a little, so that both bodies come close
        for k in range(len(T)):
            ax = rng.normal(size=3)
            ang = np.radians(rng.uniform(-25, 25))
            T[k, :3, :3] = rotation_about(ax / np.linalg.norm(ax), ang) @ T[k, :3, :3]
            T[k, :3, 3] -= rng.uniform(0, 6) * T[k, :3, 2]
        got = g._clearance(T)
        d = np.arange(tc.tip_exclusion_mm, tc.length_mm + 1e-9, 0.05)
        r = np.array([tc.radius_at(x) for x in d])
        for k in range(len(T)):
            pts = T[k, :3, 3] - d[:, None] * T[k, :3, 2]
            main, branch = _solid_distances(g, pts)
            assert got[k, 0] == pytest.approx(float(np.min(main - r)), abs=0.02), (name, k)
            assert got[k, 1] == pytest.approx(float(np.min(branch - r)), abs=0.02), (name, k)


def _solid_distances(g: ReachGate, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of points (M, 3) in the base from the main body and the branch (radius
    0 pieces of zero length: each point's own distance)."""
    z = np.zeros(len(pts))
    return g._main_distance(pts, pts + 1e-9, z, z), g._branch_distance(pts, pts + 1e-9, z, z)


def test_convex_sampling_with_a_widening_radius_hand_case():
    """A segment along x from 0 to 100 at height 10 above the plane z = 0, radius from 2 to 12:
    the clearance 10 - r(t) is smallest at the wide end (-2); reversed (wide end first) too."""
    p, q = np.array([[0.0, 0.0, 10.0]]), np.array([[100.0, 0.0, 10.0]])

    def plane(x, y, z):
        return z

    assert _segment_convex_distance(p, q, plane, r0=2.0, r1=12.0)[0] == pytest.approx(-2.0)
    assert _segment_convex_distance(q, p, plane, r0=12.0, r1=2.0)[0] == pytest.approx(-2.0)
    # rising away from the plane faster than it widens: the narrow end is nearest
    q2 = np.array([[100.0, 0.0, 60.0]])
    assert _segment_convex_distance(p, q2, plane, r0=2.0, r1=12.0)[0] == pytest.approx(8.0)


@pytest.mark.parametrize("change, message", [
    ({"nozzle_length_mm": 20.0}, "nozzle_length_mm: 20.0 must lie between tip_exclusion_mm"),
    ({"nozzle_length_mm": 400.0}, "nozzle_length_mm: 400.0 must lie between"),
    ({"nozzle_radius_mm": 14.0}, "nozzle_radius_mm: 14.0 must be above 0 and at most radius_mm"),
    ({"nozzle_radius_mm": -1.0}, "nozzle_radius_mm"),
])
def test_bad_torch_geometry_is_one_clear_line(change, message):
    data = yaml.safe_load((CONFIG_DIR / "robot.yaml").read_text())
    data["torch"].update(change)
    with pytest.raises(ConfigError) as e:
        robot_config_from_dict(data, "robot.yaml")
    assert message in str(e.value) and len(str(e.value).splitlines()) == 1


def test_a_torch_file_without_a_nozzle_is_the_cylinder():
    data = yaml.safe_load((CONFIG_DIR / "robot.yaml").read_text())
    for k in ("nozzle_radius_mm", "nozzle_length_mm"):
        del data["torch"][k]
    tc = robot_config_from_dict(data, "robot.yaml").torch
    assert tc.pieces() == ((tc.tip_exclusion_mm, tc.length_mm, tc.radius_mm, tc.radius_mm),)
