"""The closed loop under faults: no crash, no unsafe pose, the right hold, and recovery."""

import numpy as np
import pytest

from torchseam.live.demo import FAULT_FRAMES, run_demo

LENGTH_MM = 24.0  # weld only the start of segment a (the fault lands in its middle)


def _run(cell, part, noise, faults=(), level=0.3):
    return run_demo(cell, part, noise, level, seed=1, faults=faults, segments="a",
                    length_mm=LENGTH_MM)


@pytest.fixture(scope="module")
def baseline(cell, part, noise):
    return _run(cell, part, noise)


def _after_fault(res):
    """Frames after the fault window and the poses sent after it."""
    k = max(i for i, f in enumerate(res.frames) if f.fault)
    return res.frames[k + 1:]


def test_closed_loop_follows_the_true_seam(baseline):
    s = baseline.summary
    assert s["unsafe_poses_sent"] == 0 and s["poses_refused"] == 0
    assert s["seam_rmse_mm"] < 0.1 and s["seam_max_mm"] < 0.3
    assert s["nominal_rmse_mm"] > 0.5  # the part really deviates from its design
    assert s["poses_sent"] >= LENGTH_MM / 2


@pytest.mark.parametrize(("fault", "why"), [
    ("dropped-frames", "no camera frame"),
    ("laser-off", "stale"),     # no stripe: nothing located, the link refuses stale poses
    ("arc-flash", "stale"),
])
def test_input_faults_hold_and_recover(cell, part, noise, fault, why):
    res = _run(cell, part, noise, (fault,))
    s = res.summary
    assert s["unsafe_poses_sent"] == 0
    faulted = [f for f in res.frames if f.fault]
    assert len(faulted) == FAULT_FRAMES
    # the loop held and said why
    assert any("hold" in m and why in m for m in res.messages), res.messages
    assert any(f.state == "hold" for f in faulted)
    # and came back: tracking again after the fault, the torch on the seam at the end
    after = _after_fault(res)
    assert any(f.state == "tracking" for f in after)
    assert after[-1].torch_err_mm < 0.3
    assert s["poses_sent"] >= LENGTH_MM / 2 - 2


@pytest.mark.parametrize("fault", ["packet-loss", "controller-silence"])
def test_link_faults_do_not_move_the_robot_off_the_seam(cell, part, noise, fault):
    res = _run(cell, part, noise, (fault,))
    assert res.summary["unsafe_poses_sent"] == 0
    after = _after_fault(res)
    assert any(f.state == "tracking" for f in after)
    errs = np.array([f.torch_err_mm for f in res.frames if f.arc_on])
    assert errs.max() < 0.3
