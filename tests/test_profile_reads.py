"""A colour frame's two readings (the red excess and the brightness): the finder reads the
brightness beside a found profile only where white light lies near its joint or in a break of
its centre line, and on frames under the arc that saving changes no result."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.orient import BRIGHTNESS
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision import profiles as P
from torchseam.vision.profiles import ProfileFinder, ProfileResult, load_profile_config
from torchseam.vision.tipm import load_tipm

PARTS = Path(__file__).resolve().parents[1] / "configs" / "parts"
WINDOW = 180  # configs/profile_track.yaml window_px


def _both_read(finder: ProfileFinder, frame: np.ndarray) -> tuple[ProfileResult, bool]:
    """The finder's rule with both readings made on every colour frame with a white pixel:
    the result, and whether the brightness's was taken beside a found red-excess profile (where
    glare whitens the stripe at the brightness's joint, and the two read the same joint or the
    red excess's centre line has no point within fit_px of it)."""
    found = finder._profile(frame)
    if not found.ok or not P._any_white(frame):
        if found.ok:
            return found, False
        grey = finder._profile(cv2.transform(frame, BRIGHTNESS))
        return (grey if grey.ok else found), False
    grey = finder._profile(cv2.transform(frame, BRIGHTNESS))
    width = finder._width
    reach = finder.cfg.stripe.max_run_px + 1
    if not grey.ok or (finder._white_at_joint(frame, grey, width)
                       <= finder.tipm.cfg.white_core_fraction):
        return found, False
    if float(np.linalg.norm(found.aim - grey.aim)) <= min(width, reach) or (
            found.centre is not None and len(found.centre) and float(np.min(
                np.linalg.norm(found.centre - grey.aim, axis=1))) > finder.cfg.fit_px):
        return grey, True
    return found, False


@pytest.mark.parametrize("part, family, level", [("pipe_lap", "wide", "heavy"),
                                                 ("pipe_lap", "wide", "extreme"),
                                                 ("t_joint_bevel", "sim", "heavy")])
def test_the_brightness_is_read_only_where_it_could_be_taken(part, family, level):
    cfg = load_part(PARTS / f"{part}.yaml")
    noise = load_noise()
    finder = ProfileFinder(load_tipm(), load_profile_config(), cfg.joint)
    calls = {"n": 0}
    inner = finder._profile

    def counted(frame):
        calls["n"] += 1
        return inner(frame)

    same = taken = saved = 0
    for img, truth in simulate(load_cell(), cfg, noise, SequenceSpec(
            n_frames=40, start_mm=100, level=noise.level(level), seed=1000, family=family)):
        if not truth.arc_on:
            continue
        u, v = np.rint(truth.uv).astype(int)
        win = np.ascontiguousarray(img[max(v - WINDOW, 0):v + WINDOW + 1,
                                       max(u - WINDOW, 0):u + WINDOW + 1])
        want, beside = _both_read(finder, win)
        finder._profile = counted
        calls["n"] = 0
        got = finder(win)
        finder._profile = inner
        assert got.ok == want.ok and got.joint == want.joint
        if got.ok:
            np.testing.assert_array_equal(got.aim, want.aim)
        same += 1
        taken += beside
        saved += calls["n"] == 1 and P._any_white(win)
    assert same >= 25
    if part == "pipe_lap":   # glare whitens the joint: the brightness is still taken there
        assert taken > 0
    else:                    # white pixels away from the joint: those frames are read once
        assert saved > 0
