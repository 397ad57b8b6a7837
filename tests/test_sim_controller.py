"""The simulated IRC5's parts on their own: the arm model, the fault plan, its messages."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from torchseam.core.transforms import matrix_to_quat, rotation_about
from torchseam.robot.egm import load_egm_config
from torchseam.robot.egm.messages import EgmRobot, EgmSensor
from torchseam.robot.kinematics import load_irb1410
from torchseam.robot.sim_controller import SimController
from torchseam.robot.sim_controller.arm import (
    ArmModel,
    ProgrammedPath,
    QuatCache,
    step_towards,
    straight_path,
)
from torchseam.robot.sim_controller.faults import Fault, FaultPlan
from torchseam.robot.sim_controller.messages import RobotMessages, sensor_command

CFG = load_egm_config()
TOOL = np.eye(4)
TOOL[:3, 3] = [0.0, 0.0, 300.0]


@pytest.fixture(scope="module")
def robot():
    return load_irb1410()


def test_the_config_the_arm_and_the_tool_are_the_callers_to_read():
    with pytest.raises(TypeError):
        SimController()  # type: ignore[call-arg]
    with pytest.raises(TypeError):  # no robot.yaml or cell.yaml read behind the caller's back
        SimController(CFG)  # type: ignore[call-arg]


def test_the_arm_walks_to_a_target_within_its_speed_limits(robot):
    sim = CFG.sim_controller
    arm = ArmModel(robot, TOOL, sim, "pose")
    dt = sim.period_s
    start = arm.tcp_pose()
    goal = start.copy()
    goal[:3, 3] += [0.0, 8.0, -3.0]
    goal[:3, :3] = start[:3, :3] @ rotation_about(np.array([1.0, 0.0, 0.0]), math.radians(2.0))
    arm.target = goal
    speed = np.asarray(sim.joint_speed_deg_s)
    lags = []
    for _ in range(400):
        q0 = arm.q.copy()
        *_, lag = arm.update(dt)
        lags.append(lag)
        assert np.all(np.abs(arm.q - q0) <= speed * dt * (1 + 1e-9))
    T = arm.tcp_pose()
    np.testing.assert_allclose(T[:3, 3], goal[:3, 3], atol=1e-3)
    np.testing.assert_allclose(T[:3, :3], goal[:3, :3], atol=1e-5)
    # the feedback trails the planned pose by one cycle's move: one Newton step keeps up
    assert max(lags) <= sim.tcp_speed_mm_s * dt * 1.01
    # at rest where told, nothing pending
    arm.rest_at(arm.q)
    assert arm.target is None and np.allclose(arm.planned, arm.tcp_pose())


def test_the_compiled_newton_step_is_its_numpy_statement(robot):
    """The arm's per-cycle step (compiled on one pose) against the same arithmetic in numpy:
    the batched closed-form TCP pose and Jacobian, the rotation vector of the orientation
    error, the damped 6 x 6 solve; joints all over the range, targets a few mm / degrees off
    (what a cycle sees) and far off (a restart)."""
    from torchseam.core.transforms import rotvec
    from torchseam.robot.kinematics import arm_forward
    from torchseam.robot.sim_controller import arm as arm_mod

    a = ArmModel(robot, TOOL, CFG.sim_controller, "pose")
    rng = np.random.default_rng(0)
    for k in range(200):
        q = rng.uniform(-150.0, 150.0, 6)
        q[1:3] = rng.uniform(-60.0, 60.0, 2)
        a.q = q
        T0 = arm_forward(np, robot.geometry, q[None], TOOL)[0][0]
        T_des = T0.copy()
        far = k % 10 == 0
        T_des[:3, 3] += rng.normal(0.0, 40.0 if far else 1.0, 3)
        axis = rng.normal(size=3)
        T_des[:3, :3] = rotation_about(axis / np.linalg.norm(axis), math.radians(
            rng.uniform(0.0, 60.0 if far else 3.0))) @ T0[:3, :3]
        dq, T = a._newton_step(T_des)
        Tn, J = arm_forward(np, robot.geometry, q[None], TOOL)
        J = J[0] * (math.pi / 180.0)
        J[3:] *= arm_mod._ROT_WEIGHT
        err = np.concatenate([T_des[:3, 3] - Tn[0][:3, 3],
                              rotvec(T_des[:3, :3] @ Tn[0][:3, :3].T) * arm_mod._ROT_WEIGHT])
        dq_np = np.linalg.solve(J.T @ J + arm_mod._DAMPING * np.eye(6), J.T @ err)
        np.testing.assert_allclose(T, Tn[0], atol=1e-9)
        np.testing.assert_allclose(dq, dq_np, rtol=1e-7, atol=1e-9)


def test_the_compiled_pose_cycle_is_its_numpy_statement(robot):
    """Pose mode's compiled cycle (step towards the target, Newton step, speed limits, the
    messages' quaternions and convergence) gives the numpy statement's numbers to the bit, and
    the same EgmRobot bytes."""
    from torchseam.robot.sim_controller import arm as arm_module

    sim = CFG.sim_controller
    if not arm_module._pose_kernel_agrees(robot, sim):
        pytest.skip("this machine's BLAS sums dot products otherwise: the arm keeps numpy")
    fast, ref = ArmModel(robot, TOOL, sim, "pose"), ArmModel(robot, TOOL, sim, "pose")
    ref._pose_update = None   # the numpy statement
    assert fast._pose_update is not None
    out = [RobotMessages(sim.period_s, fast.quats), RobotMessages(sim.period_s, ref.quats)]
    home = ref.tcp_pose()
    rng = np.random.default_rng(4)
    for k in range(240):
        if k % 60 == 10:   # (the first cycles without a target: the arm holds its pose)
            target = home.copy()
            target[:3, 3] += rng.normal(0.0, 8.0, 3)
            target[:3, :3] = rotation_about(np.array([0.2, 1.0, -0.3]) / np.linalg.norm(
                [0.2, 1.0, -0.3]), rng.normal(0.0, 0.1)) @ home[:3, :3]
            target.setflags(write=False)   # as the controller's commands are
            fast.target = ref.target = target
        got, want = fast.update(sim.period_s), ref.update(sim.period_s)
        for g, w in zip(got, want, strict=True):
            assert np.array_equal(g, w), k
        assert fast.last is not None and ref.last is None
        out[0].known = fast.last
        a = out[0].build(got[0], got[1], fast.q, got[2], True, 0.0)
        assert out[0].known is None
        b = out[1].build(want[0], want[1], ref.q, want[2], True, 0.0)
        assert a.SerializePartialToString() == b.SerializePartialToString(), k
    assert np.array_equal(fast.q, ref.q)


def test_the_arm_runs_its_path_with_the_correction_in_the_tool_frame(robot):
    sim = dataclasses.replace(CFG.sim_controller, path_length_mm=20.0)
    arm = ArmModel(robot, TOOL, sim, "pathcorr")
    arm.corr_cmd = np.array([0.0, 0.5, 0.0])
    n = int(math.ceil(20.0 / sim.path_speed_mm_s / sim.period_s)) + 100
    for _ in range(n):
        arm.update(sim.period_s)
    assert not arm.running and arm.s == arm.path.length
    want = arm.path.at(arm.path.length)
    want[:3, 3] += want[:3, :3] @ [0.0, 0.5, 0.0]
    np.testing.assert_allclose(arm.tcp_pose()[:3, 3], want[:3, 3], atol=1e-3)


def test_a_programmed_path_slerps_and_refuses_repeats():
    start = np.eye(4)
    poses = straight_path(start, np.array([1.0, 0.0, 0.0]), 10.0, step_mm=10.0)
    poses[1, :3, :3] = rotation_about(np.array([0.0, 0.0, 1.0]), 0.4)
    path = ProgrammedPath(poses)
    mid = path.at(5.0)
    np.testing.assert_allclose(mid[:3, 3], [5.0, 0.0, 0.0])
    np.testing.assert_allclose(mid[:3, :3], rotation_about(np.array([0.0, 0.0, 1.0]), 0.2),
                               atol=1e-12)
    np.testing.assert_allclose(path.at(99.0), poses[1])
    with pytest.raises(Exception, match="repeat"):
        ProgrammedPath(np.stack([start, start]))


def test_the_fault_plan_shapes_the_wire():
    plan = FaultPlan(oversize_bytes=2048, seed=0)
    a, b, c = b"a" * 64, b"b" * 64, b"c" * 64
    out = plan.shape(a)
    assert out.datagrams == [a] and out.expect and out.fault is None
    plan.inject(Fault.REORDER, 2)
    plan.inject("duplicate")
    plan.inject(Fault.DROP)
    r1, r2 = plan.shape(a), plan.shape(b)
    assert r1.datagrams == r2.datagrams == [] and not r1.expect and r1.fault == "reorder"
    out = plan.shape(c)  # the duplicate goes out, then the held ones, oldest first
    assert out.datagrams == [c, c, a, b] and out.expect and out.fault == "duplicate"
    assert plan.shape(a).datagrams == [] and not plan.shape(a).fault  # drop, then clean
    plan.inject(Fault.CORRUPT)
    plan.inject(Fault.OVERSIZED)
    bad = plan.shape(a).datagrams[0]
    assert len(bad) == len(a) - 1 and bad != a[:-1] and not plan.shape(b).expect
    plan.inject(Fault.OVERSIZED)
    assert len(plan.shape(a).datagrams[0]) == 2048 + 1 + 2  # field tag, 2-byte varint length
    with pytest.raises(ValueError):
        plan.inject(Fault.DROP, -1)
    plan.set_loss(0.5, 2.0, seed=1)
    outs = [plan.shape(a) for _ in range(400)]
    lost = sum(o.fault == "loss" for o in outs)
    assert 100 < lost < 300 and all(not o.datagrams for o in outs if o.fault == "loss")
    plan.clear_loss()
    assert plan.shape(a).expect


def test_messages_number_and_read_commands():
    T = np.eye(4)
    T[:3, 3] = [900.0, 10.0, 600.0]
    msgs = RobotMessages(0.004)
    q = np.arange(6.0)
    m = msgs.build(q, T, q + 1, T, True, 0.001)
    wire = [EgmRobot.FromString(msgs.stamp(m)) for _ in range(2)]
    assert [w.header.seqno for w in wire] == [1, 2]
    assert list(wire[0].planned.joints.joints) == list(q + 1)
    assert wire[0].mciConvergenceMet and wire[0].utilizationRate == pytest.approx(25.0)
    reply = EgmSensor()
    c = reply.planned.cartesian
    c.pos.x, c.pos.y, c.pos.z = 1.0, 2.0, 3.0
    qz = matrix_to_quat(rotation_about(np.array([0.0, 0.0, 1.0]), 0.3))
    c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = (2 * float(v) for v in qz)
    target = sensor_command(reply, "pose")
    assert target is not None
    np.testing.assert_allclose(target[:3, :3], rotation_about(np.array([0.0, 0.0, 1.0]), 0.3),
                               atol=1e-12)
    c.orient.u0 = c.orient.u1 = c.orient.u2 = c.orient.u3 = 0.0
    assert sensor_command(reply, "pose") is None


def test_the_cycles_caches_give_the_numbers_of_a_fresh_conversion(robot):
    """The arm's quaternion cache and the controller's last command are the conversions'
    own numbers (looked up by the rotation's / the reply's bytes), bounded and read-only."""
    cache = QuatCache()
    rots = [rotation_about(np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0]), a)
            for a in np.linspace(-3.0, 3.0, 3 * QuatCache.SIZE)]
    for R in rots + rots[::-1] + rots:
        q = cache(R)
        assert np.array_equal(q, matrix_to_quat(R)) and not q.flags.writeable
        assert cache(R.copy()) is q           # by value: a copy hits
    assert len(cache._quats) <= QuatCache.SIZE
    T, target = np.eye(4), np.eye(4)
    target[:3, :3], target[:3, 3] = rots[5], [3.0, -2.0, 1.0]
    assert np.array_equal(step_towards(T, target, 1.0, 0.01, cache),
                          step_towards(T, target, 1.0, 0.01))

    ctrl = SimController(CFG, robot=robot, tool=TOOL, mode="pose",
                         bind_address=("127.0.0.1", 0))
    try:
        reply = EgmSensor()
        c = reply.planned.cartesian
        for k, R in enumerate(rots[:4] + rots[:1]):
            c.pos.x, c.pos.y, c.pos.z = 900.0 + k, 10.0, 600.0
            c.orient.u0, c.orient.u1, c.orient.u2, c.orient.u3 = matrix_to_quat(R).tolist()
            for seqno in (1, 2):   # the header changes every cycle, the pose does not
                reply.header.seqno = seqno
                got = ctrl._command(reply)
                assert got is not None and np.array_equal(got, sensor_command(reply, "pose"))
        c.orient.u0 = c.orient.u1 = c.orient.u2 = c.orient.u3 = 0.0
        assert ctrl._command(reply) is None
    finally:
        ctrl.stop()
