"""IRB 1410 model: URDF, FK against independent references, IK, Jacobian, conventions, errors."""

from __future__ import annotations

import dataclasses
import io
import math

import numpy as np
import pytest
import torch
import yourdfpy
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from torchseam.core.config import ConfigError
from torchseam.robot.config import load_robot_config, robot_config_from_dict
from torchseam.robot.kinematics import (
    IRB1410,
    URDF_PATH,
    RobotInputError,
    URDFError,
    controller_to_urdf,
    load_irb1410,
    pose_to_xyzq,
    rotation_angle,
    urdf_to_controller,
    xyzq_to_pose,
)

F64 = torch.float64


@pytest.fixture(scope="module")
def robot():
    return load_irb1410()


def random_joints(robot, n, seed=0):
    """Controller joints uniformly inside the axis ranges (coupled check included)."""
    g = torch.Generator().manual_seed(seed)
    q = robot.min_deg + (robot.max_deg - robot.min_deg) * torch.rand(4 * n, 6, generator=g,
                                                                      dtype=F64)
    return q[robot.in_range(q)][:n]


# --------------------------------------------------------------------------- independent refs

# Standard DH table of the IRB 1410 (ARTE robots/ABB/IRB1410/parameters.m): d, a, alpha, offset.
DH = [(475.0, 150.0, -90, 0), (0.0, 600.0, 0, -90), (0.0, 120.0, -90, 0),
      (720.0, 0.0, 90, 0), (0.0, 0.0, -90, 0), (85.0, 0.0, 0, 180)]


def dh_fk(q_ctrl_deg):
    """FK straight from the DH table (numpy, mm), with the parallelogram coupling applied."""
    q = np.radians(np.asarray(q_ctrl_deg, float))
    q[2] -= q[1]  # DH theta3 is relative to link 2
    T = np.eye(4)
    for (d, a, alpha, off), th in zip(DH, q, strict=True):
        th, al = th + math.radians(off), math.radians(alpha)
        ct, st_, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
        T = T @ np.array([[ct, -st_ * ca, st_ * sa, a * ct], [st_, ct * ca, -ct * sa, a * st_],
                          [0, sa, ca, d], [0, 0, 0, 1]])
    return T


def test_urdf_loads_with_yourdfpy_and_matches_the_config():
    u = yourdfpy.URDF.load(io.StringIO(URDF_PATH.read_text()), build_scene_graph=True,
                           load_meshes=False)
    assert u.actuated_joint_names == [f"joint_{i}" for i in range(1, 7)]
    assert "tool0" in u.link_map
    cfg = load_robot_config()
    lo, hi = np.radians(cfg.axes.min_deg), np.radians(cfg.axes.max_deg)
    # joint_3 = axis3 - axis2: its URDF limit is the widest the coupled range allows
    lo[2], hi[2] = lo[2] - hi[1], hi[2] - lo[1]
    for i, name in enumerate(u.actuated_joint_names):
        lim = u.joint_map[name].limit
        assert (lim.lower, lim.upper) == pytest.approx((lo[i], hi[i]), abs=1e-12), name
        assert lim.velocity == pytest.approx(math.radians(cfg.axes.max_speed_deg_s[i])), name
    assert all(link.collisions for name, link in u.link_map.items() if name != "tool0")


def test_fk_matches_yourdfpy_within_1e6_m(robot):
    u = yourdfpy.URDF.load(io.StringIO(URDF_PATH.read_text()), build_scene_graph=True,
                           load_meshes=False)
    q = random_joints(robot, 40, seed=1)
    T = robot.fk(q).numpy()
    th = controller_to_urdf(q).numpy()
    for i in range(len(q)):
        u.update_cfg(th[i])
        ref = u.get_transform("tool0", "base_link")
        np.testing.assert_allclose(T[i, :3, 3] / 1000.0, ref[:3, 3], atol=1e-6)
        np.testing.assert_allclose(T[i, :3, :3], ref[:3, :3], atol=1e-6)


def test_fk_matches_the_dh_table(robot):
    q = random_joints(robot, 30, seed=2)
    T = robot.fk(q).numpy()
    for i in range(len(q)):
        ref = dh_fk(q[i].numpy())
        # pytorch-kinematics stores URDF offsets in float32 before .to(float64): ~4e-5 mm
        np.testing.assert_allclose(T[i, :3, 3], ref[:3, 3], atol=1e-4)
        np.testing.assert_allclose(T[i, :3, :3], ref[:3, :3], atol=1e-7)


def test_all_axes_zero_hand_computed(robot):
    T = robot.fk(torch.zeros(6, dtype=F64))
    np.testing.assert_allclose(T[:3, 3].numpy(), [955.0, 0.0, 1195.0], atol=1e-4)
    # ABB tool0 at zero: z along base x, x pointing down = 90 deg about base y
    np.testing.assert_allclose(pose_to_xyzq(T)[3:].numpy(), [math.sqrt(0.5), 0, math.sqrt(0.5), 0],
                               atol=1e-9)


def test_reach_is_1444_mm(robot):
    """The datasheet's reach: 0.15 + 0.6 sin 70 + sqrt(0.72^2 + 0.12^2) = 1.444 m, the wrist
    centre's furthest
    horizontal distance from axis 1 (axis 2 at +70, forearm's wrist line horizontal)."""
    expected = 150 + 600 * math.sin(math.radians(70)) + math.hypot(720, 120)
    a2, a3 = torch.meshgrid(torch.linspace(-70, 70, 29, dtype=F64),
                            torch.linspace(-65, 70, 271, dtype=F64), indexing="ij")
    q = torch.zeros(a2.numel(), 6, dtype=F64)
    q[:, 1], q[:, 2], q[:, 4] = a2.reshape(-1), a3.reshape(-1), 30.0
    wrist = robot.wrist_centre(robot.fk(q))
    reach = wrist[:, :2].norm(dim=-1).max().item()
    assert reach == pytest.approx(expected, abs=0.05)
    assert round(reach) == 1444


# --------------------------------------------------------------------------- RobotStudio pairs

# Published RobotStudio joint/pose pairs of the IRB 1410 (tool0 in the base, mm, quaternion
# w x y z): Malla, O. and Shanmugavel, M. (2024), "Simplified model to study the kinematics of
# manipulators with parallelogram linkages", Industrial Robot 51(5), 704-714,
# doi:10.1108/IR-01-2024-0046; data from the authors' code, github.com/OmarMalla/ABB-IRB1410,
# IRB1410.m (commit 67a68922), section "Test Cases" (Target_j_n / Target_n). The joints are
# printed with 2 decimals (e.g. -12.13 for -12.1333), so FK of the printed joints can only agree
# to ~0.1 mm; IK of the published pose must round to the printed joints.
ROBOTSTUDIO = [
    ([30.80, -12.13, 15.33, -40.00, 59.80, -28.00],
     [691.027481335, 356.960034976, 921.353218153, 0.129239344, -0.572731138, 0.746819702,
      -0.31230845]),
    ([40.80, -17.73, 39.17, -30.00, 47.53, 32.00],
     [483.357754156, 375.80817434, 606.4456307, 0.13862261, -0.242750247, 0.949700763,
      -0.141154349]),
    ([-11.33, 27.07, 19.00, -30.00, 39.87, 80.00],
     [1160.639819891, -260.405414977, 822.484566064, 0.334258363, 0.56295022, 0.755295025,
      -0.029796333]),
    ([9.07, 39.20, 46.50, -8.00, 62.87, 44.00],
     [1072.337088003, 160.459738433, 420.616108119, 0.125173499, -0.255279144, -0.95055749,
      0.124918423]),
    ([-20.40, 36.40, 63.00, 2.00, 35.27, 84.00],
     [870.067200235, -321.74769978, 286.787197393, 0.066003952, -0.797135821, -0.59941592,
      0.03030703]),
    ([-27.20, 27.07, 42.83, -40.00, 59.80, -8.00],
     [890.685775054, -510.842808247, 537.443556083, 0.18166292, 0.044911271, -0.95484921,
      0.230747801]),
    # pair 7 is printed with axis 1 = -134, but its pose is that of -133.733 (see below)
    ([-134, 17.73, 28.17, 44.00, 21.47, 40.00],
     [-733.279630613, -797.697667876, 755.346436265, 0.400395276, 0.884247649, -0.231926932,
      -0.06324252]),
    ([-95.20, 28.93, 6.17, -20.00, 21.47, 40.00],
     [-123.388011229, -1238.419066418, 1004.513593115, 0.387932122, 0.738800923, 0.418458807,
      -0.358572296]),
    ([22.67, 28.93, 9.83, -14.00, 6.13, 72.00],
     [1156.106596183, 480.438829756, 972.267553245, 0.466271708, 0.249945798, 0.757299548,
      0.382903625]),
    ([43.07, 2.80, 17.17, -4.00, 18.40, 20.00],
     [711.246065239, 662.234742188, 927.050306672, 0.402628515, -0.201610983, 0.865916047,
      0.217790472]),
    ([43.07, 4.67, 30.00, 6.00, -4.60, -44.00],
     [701.179733179, 654.41229213, 780.442154315, 0.533800484, -0.547804799, 0.643869325,
      0.019980928]),
    ([31.73, -8.40, 61.17, 12.00, -36.80, 24.00],
     [508.349971408, 301.925043085, 460.090671293, 0.479876027, 0.047676194, 0.840934416,
      0.245510259]),
    ([54.40, 22.40, 48.33, 34.00, 10.73, -52.00],
     [570.648656609, 812.280300102, 500.534152205, 0.252265907, -0.580868779, 0.762162053,
      0.134396353]),
    ([-38.53, 5.60, 15.33, -62.00, 9.20, -24.00],
     [785.63241451, -641.006224447, 969.131559959, 0.217540104, -0.288867915, 0.763718218,
      -0.534757996]),
    ([29.47, -12.13, -3.00, -12.00, -39.87, 84.00],
     [690.055363126, 402.895981694, 1275.750141652, 0.53911998, 0.099061876, 0.396274635,
      0.736547898]),
    ([2.27, 0.93, 8.00, -62.00, -73.60, 28.00],
     [914.994192705, 108.270208169, 1128.116862725, 0.818602029, -0.460420568, 0.29097464,
      0.18231121]),
    ([15.87, -7.47, 15.33, -88.00, -53.67, -28.00],
     [796.340913702, 297.486304705, 984.235735011, 0.630447989, -0.750672555, 0.03563847,
      -0.194308897]),
    # axis 5 = 0: the wrist is singular, only axis 4 + axis 6 is defined by the pose
    ([15.87, -12.13, 6.17, 0.00, 0.00, 40.00],
     [805.226227667, 228.868334277, 1094.428431439, 0.590216816, 0.15555747, 0.727675996,
      0.31294349]),
    ([20.40, -12.13, 35.50, 2.00, -13.80, 28.00],
     [711.366428473, 263.799855159, 709.74587652, 0.509463159, 0.071165143, 0.824541115,
      0.235615709]),
    ([-6.80, -9.33, 8.00, -4.00, 9.20, -4.00],
     [857.403131805, -103.193832995, 1060.582052718, 0.588078816, -0.00475728, 0.804759938,
      -0.080635707]),
]
PAIR7 = 6


def test_fk_agrees_with_published_robotstudio_pairs(robot):
    q = torch.tensor([j for j, _ in ROBOTSTUDIO], dtype=F64)
    pose = torch.tensor([p for _, p in ROBOTSTUDIO], dtype=F64)
    T = robot.fk(q)
    ref = xyzq_to_pose(pose)
    pos = (T[:, :3, 3] - ref[:, :3, 3]).norm(dim=-1)
    rot = torch.rad2deg(rotation_angle(T[:, :3, :3], ref[:, :3, :3]))
    keep = torch.arange(len(q)) != PAIR7
    # joints printed to 0.01 deg: up to ~0.005 deg per axis at ~1.4 m lever arms
    assert pos[keep].max() < 0.12 and rot[keep].max() < 0.01
    assert pos[PAIR7] > 4.0  # axis 1 printed as -134 (off by 0.27 deg at ~1.08 m)


def test_ik_of_robotstudio_poses_rounds_to_the_published_joints(robot):
    q_pub = torch.tensor([j for j, _ in ROBOTSTUDIO], dtype=F64)
    T = xyzq_to_pose(torch.tensor([p for _, p in ROBOTSTUDIO], dtype=F64))
    sol = robot.solve_ik(T, q_pub)
    assert bool(sol.reached.all())
    assert sol.pos_err_mm.max() < 1e-6
    d = (sol.q_deg - q_pub).abs()
    d[17, 3] = d[17, 5] = 0.0  # singular wrist: compare axis 4 + axis 6 instead
    assert abs(float(sol.q_deg[17, 3] + sol.q_deg[17, 5]) - 40.0) < 0.0051
    d[PAIR7, 0] = 0.0
    assert float(sol.q_deg[PAIR7, 0]) == pytest.approx(-133.733, abs=0.001)
    # every other published joint value is the solution rounded to 0.01 deg
    assert d.max() < 0.0051


# --------------------------------------------------------------------------- conventions

@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-400, 400), min_size=6, max_size=6))
def test_coupling_round_trip(q):
    qt = torch.tensor(q, dtype=F64)
    back = urdf_to_controller(controller_to_urdf(qt))
    assert torch.allclose(back, qt, atol=1e-9)
    assert float(controller_to_urdf(qt)[2]) == pytest.approx(math.radians(q[2] - q[1]), abs=1e-12)


def test_coupling_is_the_half_metre_effect(robot):
    """Feeding controller values to the URDF unconverted turns the forearm by axis 2 about axis 3:
    the flange moves by 2 r sin(a2 / 2), r = its distance from the axis-3 line (hand computed)."""
    for a2 in (0.0, 20.0, 35.0, -35.0):
        q = torch.tensor([[10.0, a2, 15.0, 20.0, 40.0, 0.0]], dtype=F64)
        right = robot.fk(q)[0, :3, 3]
        th = controller_to_urdf(q)
        th[0, 2] = math.radians(15.0)  # the mistake: axis 3 used as joint_3
        wrong = robot.chain.forward_kinematics_tensor(th)[robot._eef][0, :3, 3] * 1000.0
        link3 = robot.chain.forward_kinematics_tensor(th)[robot.chain.get_frame_indices("link_3")]
        v = wrong - link3[0, 0, :3, 3] * 1000.0
        axis = link3[0, 0, :3, 1]  # joint_3 turns about y of link_3
        r = (v - (v @ axis) * axis).norm()
        off = (right - wrong).norm().item()
        assert off == pytest.approx(2 * r.item() * abs(math.sin(math.radians(a2) / 2)), abs=1e-6)
        if abs(a2) == 35.0:
            assert off > 450.0  # off by up to 0.5 m without the coupling


def test_pose_helpers_round_trip_in_abb_order():
    assert pose_to_xyzq(torch.eye(4, dtype=F64)).tolist() == [0, 0, 0, 1, 0, 0, 0]
    g = torch.Generator().manual_seed(3)
    x = torch.randn(20, 7, generator=g, dtype=F64)
    x[:, 3:] /= x[:, 3:].norm(dim=-1, keepdim=True)
    x[:, 3:] *= torch.sign(x[:, 3:4])
    np.testing.assert_allclose(pose_to_xyzq(xyzq_to_pose(x)).numpy(), x.numpy(), atol=1e-12)
    R = Rotation.from_quat(x[:, 3:].numpy(), scalar_first=True).as_matrix()
    np.testing.assert_allclose(xyzq_to_pose(x)[:, :3, :3].numpy(), R, atol=1e-12)
    with pytest.raises(RobotInputError, match="quaternion norm"):
        xyzq_to_pose(torch.tensor([0, 0, 0, 2.0, 0, 0, 0]))


# --------------------------------------------------------------------------- IK

def test_ik_round_trip_random_poses(robot):
    q = random_joints(robot, 300, seed=4)
    T = robot.fk(q)
    sol = robot.solve_ik(T, q)  # seeded with the truth: the same solution comes back
    assert bool(sol.ok.all())
    assert sol.pos_err_mm.max() < 0.01 and sol.rot_err_deg.max() < 0.01
    wrist_regular = q[:, 4].abs() > 1.0
    assert (sol.q_deg - q)[wrist_regular].abs().max() < 0.01
    # all 8 closed-form candidates reach the pose (checked with the chain's FK)
    cand, valid = robot.ik_candidates(T, q)
    Tc = robot.fk(cand.reshape(-1, 6)).reshape(-1, 8, 4, 4)
    err = (Tc[..., :3, 3] - T[:, None, :3, 3]).norm(dim=-1)
    assert err[valid].max() < 1e-6 and valid.float().mean() > 0.5


def test_ik_warm_started_along_a_seam_path(robot, cell, part):
    from torchseam.robot.reach import nominal_torch_poses

    T_tcp = nominal_torch_poses(part, 360)
    T = T_tcp @ torch.linalg.inv(torch.as_tensor(cell.tool.matrix()))
    sol = robot.ik_path(T)
    assert bool(sol.ok.all())
    back = robot.fk(sol.q_deg)
    assert (back[:, :3, 3] - T[:, :3, 3]).norm(dim=-1).max() < 0.01
    assert torch.rad2deg(rotation_angle(back[:, :3, :3], T[:, :3, :3])).max() < 0.01
    # neighbours seed each other: no branch switch, no 360 deg turn along the ring
    step = (sol.q_deg[1:] - sol.q_deg[:-1]).abs().max().item()
    assert step < 15.0
    # the same poses solved independently from the path's own joints: identical
    again = robot.solve_ik(T, sol.q_deg)
    assert (again.q_deg - sol.q_deg).abs().max() < 1e-6


def test_numeric_ik_pseudoinverse_warm_and_cold(robot):
    q = random_joints(robot, 12, seed=5)
    T = robot.fk(q)
    warm = robot.solve_ik(T, q + 2.0, method="numeric")
    assert bool(warm.reached.all())
    assert warm.pos_err_mm.max() < 0.01 and warm.rot_err_deg.max() < 0.01
    torch.manual_seed(0)
    cold = robot.solve_ik(T, None, method="numeric")
    assert cold.reached.float().mean() >= 0.75


def test_unreachable_pose_is_not_ok(robot):
    T = torch.eye(4, dtype=F64)[None].clone()
    T[0, :3, 3] = torch.tensor([3000.0, 0, 500])
    q, ok = robot.ik(T)
    assert not bool(ok[0])


def test_jacobian_matches_closed_form_and_finite_differences(robot):
    q = random_joints(robot, 8, seed=6)
    J = robot.jacobian(q)
    assert torch.allclose(J, robot.arm_jacobian(q), atol=1e-8)
    assert torch.allclose(robot.arm_fk(q), robot.fk(q), atol=1e-6)
    h = 1e-6  # rad
    for k in range(6):
        dq = torch.zeros(6, dtype=F64)
        dq[k] = math.degrees(h)
        Tp, Tm = robot.fk(q + dq), robot.fk(q - dq)
        lin = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
        dR = Tp[:, :3, :3] @ Tm[:, :3, :3].transpose(1, 2)
        ang = torch.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                           dR[:, 1, 0] - dR[:, 0, 1]], dim=-1) / 2 / (2 * h)
        np.testing.assert_allclose(J[:, :3, k].numpy(), lin.numpy(), atol=1e-4)
        np.testing.assert_allclose(J[:, 3:, k].numpy(), ang.numpy(), atol=1e-6)


def test_numpy_closed_form_is_the_chain_and_the_tool_jacobian_is_the_tcps(robot):
    """The numpy path of the closed form (what the simulated controller runs every cycle) is
    the chain's FK and Jacobian; with a tool its pose and Jacobian are the TCP's (central
    differences of the chain's FK times the tool)."""
    from torchseam.core.transforms import rotation_about
    from torchseam.robot.kinematics import arm_forward

    q = random_joints(robot, 8, seed=11)
    qn = q.numpy()
    T, J = arm_forward(np, robot.geometry, qn)
    np.testing.assert_allclose(T, robot.fk(q).numpy(), atol=1e-6)
    np.testing.assert_allclose(J, robot.jacobian(q).numpy(), atol=1e-8)
    T0, J0 = arm_forward(np, robot.geometry, qn, np.eye(4))
    np.testing.assert_allclose(T0, T, atol=1e-12)
    np.testing.assert_allclose(J0, J, atol=1e-12)
    tool = np.eye(4)
    tool[:3, :3] = rotation_about(np.array([0.0, 1.0, 0.0]), 0.6)
    tool[:3, 3] = [12.0, -30.0, 310.0]
    Tt, Jt = arm_forward(np, robot.geometry, qn, tool)
    np.testing.assert_allclose(Tt, robot.fk(q).numpy() @ tool, atol=1e-6)
    Tt_torch, Jt_torch = arm_forward(torch, robot.geometry, q, torch.as_tensor(tool))
    np.testing.assert_allclose(Jt_torch.numpy(), Jt, atol=1e-9)
    h = 1e-6  # rad
    for k in range(6):
        dq = np.zeros(6)
        dq[k] = math.degrees(h)
        Tp, Tm = (robot.fk(torch.as_tensor(qn + s * dq)).numpy() @ tool for s in (1, -1))
        lin = (Tp[:, :3, 3] - Tm[:, :3, 3]) / (2 * h)
        dR = Tp[:, :3, :3] @ Tm[:, :3, :3].transpose(0, 2, 1)
        ang = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0],
                        dR[:, 1, 0] - dR[:, 0, 1]], axis=-1) / 2 / (2 * h)
        np.testing.assert_allclose(Jt[:, :3, k], lin, atol=1e-4)
        np.testing.assert_allclose(Jt[:, 3:, k], ang, atol=1e-6)


def test_axis3_check_modes(robot):
    q = torch.tensor([[0, -60.0, 20.0, 0, 45, 0], [0, 50.0, 60.0, 0, 45, 0]], dtype=F64)
    assert robot.in_range(q).tolist() == [True, True]
    diff = IRB1410(config=dataclasses.replace(robot.config,
                                              axis3_range_applies_to="difference"))
    assert diff.in_range(q).tolist() == [False, True]  # 20 - (-60) = 80 > 70
    assert diff.range_excess(q)[0, 2].item() == pytest.approx(10.0)


def test_batch_shapes_and_dtype(robot):
    q = torch.zeros(2, 3, 6, dtype=F64)
    q[..., 4] = 30.0
    assert robot.fk(q).shape == (2, 3, 4, 4)
    assert robot.jacobian(q).shape == (2, 3, 6, 6)
    r32 = load_irb1410(dtype=torch.float32)
    T = r32.fk(torch.zeros(1, 6))
    assert T.dtype == torch.float32 and abs(T[0, 0, 3].item() - 955.0) < 1e-2


def test_fk_is_differentiable(robot):
    q = torch.tensor([[10.0, 20, 10, 30, 40, 50]], dtype=F64, requires_grad=True)
    robot.fk(q)[0, 0, 3].backward()
    assert q.grad is not None and torch.isfinite(q.grad).all()


# --------------------------------------------------------------------------- errors

def test_bad_inputs_raise_clear_errors(robot, tmp_path):
    with pytest.raises(RobotInputError, match=r"\(\.\.\., 6\)"):
        robot.fk(torch.zeros(5))
    with pytest.raises(RobotInputError, match="row 1 is not finite"):
        robot.fk(torch.tensor([[0.0] * 6, [0, 0, math.nan, 0, 0, 0]]))
    T = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    T[1, 0, 0] = 2.0
    with pytest.raises(RobotInputError, match="pose 1: rotation is not orthonormal"):
        robot.ik(T)
    with pytest.raises(RobotInputError, match=r"\(\.\.\., 4, 4\)"):
        robot.ik(torch.eye(3))
    with pytest.raises(RobotInputError, match="expected 1 or 2 seeds"):
        robot.ik(torch.eye(4, dtype=F64).repeat(2, 1, 1), torch.zeros(3, 6))
    with pytest.raises(URDFError, match="cannot read URDF"):
        IRB1410(load_robot_config(), tmp_path / "none.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text(URDF_PATH.read_text().replace('xyz="0 0 0.6"', 'xyz="0 0.05 0.6"'))
    with pytest.raises(URDFError, match="not an IRB 1410-like arm"):
        IRB1410(load_robot_config(), bad)


def test_robot_config_errors_name_the_field():
    import yaml

    from torchseam.core.config import CONFIG_DIR

    data = yaml.safe_load((CONFIG_DIR / "robot.yaml").read_text())
    ok = robot_config_from_dict(data, "robot.yaml")
    assert ok.axis3_range_applies_to == "controller"
    with pytest.raises(ConfigError, match="robot.yaml: axis3_range_applies_to: expected one of"):
        robot_config_from_dict({**data, "axis3_range_applies_to": "both"}, "robot.yaml")
    with pytest.raises(ConfigError, match=r"robot.yaml: axes.max_deg: expected 6 values"):
        robot_config_from_dict({**data, "axes": {**data["axes"], "max_deg": [1, 2]}},
                               "robot.yaml")
    with pytest.raises(ConfigError, match="axis 2: min 80.0 must be below max 70.0"):
        robot_config_from_dict({**data, "axes": {**data["axes"],
                                                 "min_deg": [-170, 80, -65, -150, -115, -300]}},
                               "robot.yaml")
    with pytest.raises(ConfigError, match="home_deg: axis 5"):
        robot_config_from_dict({**data, "home_deg": [0, 0, 0, 0, 130, 0]}, "robot.yaml")
    with pytest.raises(ConfigError, match="robot.yaml: singularity: missing"):
        robot_config_from_dict({k: v for k, v in data.items() if k != "singularity"},
                               "robot.yaml")
