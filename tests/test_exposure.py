"""Automatic exposure: the controller (frame statistics in, next exposure out) and the
simulator's frames at a requested exposure."""

import dataclasses

import numpy as np
import pytest
import yaml

from torchseam.core.config import ConfigError
from torchseam.sim.sequence import SequenceSpec, simulate
from torchseam.vision.exposure import (
    ExposureConfig,
    ExposureController,
    FrameStats,
    frame_stats,
    load_exposure_config,
)

CFG = load_exposure_config()


def _window(scale: float, stripe: float, glare: float, rng: np.random.Generator) -> np.ndarray:
    """A small mono frame as a camera at exposure ``scale`` takes it: a stripe of peak
    ``stripe`` across the middle and a glare blob of peak ``glare`` on it (light before the
    exposure), clipped at 255, with read noise."""
    yy, xx = np.mgrid[0:81, 0:81].astype(float)
    light = stripe * np.exp(-0.5 * ((yy - 40) / 2.0) ** 2)
    light += glare * np.exp(-0.5 * ((xx - 40) ** 2 + (yy - 44) ** 2) / 12.0 ** 2)
    light = scale * light + rng.normal(0, 2.0, light.shape)
    return np.clip(np.rint(light), 0, 255).astype(np.uint8)


def _run(glare_of_frame, n: int, stripe: float = 160.0, seed: int = 0) -> np.ndarray:
    """The scales the controller chooses over ``n`` frames, each frame taken at the scale
    chosen from the frames before it (``glare_of_frame(k)``: the glare's light)."""
    ae, rng, out = ExposureController(CFG), np.random.default_rng(seed), []
    for k in range(n):
        out.append(ae.scale)
        frame = _window(ae.scale, stripe, glare_of_frame(k), rng)
        ae.update(frame_stats(frame, np.array([40.0, 40.0]), CFG))
    return np.array(out)


def test_the_shipped_settings_load_and_do_not_overshoot_their_band():
    assert CFG.min_scale < CFG.max_scale == 1.0
    assert CFG.step_up * CFG.level_low < CFG.level_high


def test_exposure_drops_while_the_arc_clips_the_stripe_and_comes_back_after():
    """Glare that clips the window at the configured exposure from frame 20 to 119: the scale
    goes down within a few frames until the window no longer clips, holds there, and returns
    to the configured exposure once the glare is gone; never more than one reversal of
    direction per change in the scene (no oscillation)."""
    scales = _run(lambda k: 400.0 if 20 <= k < 120 else 0.0, 220)
    assert np.all(scales[:21] == 1.0)                 # clean frames: the configured exposure
    assert scales[30] < 0.7                           # the arc: down within 10 frames
    assert scales[60:120].max() == scales[60:120].min()    # settled, not hunting
    # the glare's window at the settled scale no longer clips
    win = _window(scales[100], 160.0, 400.0, np.random.default_rng(1))
    s = frame_stats(win, np.array([40.0, 40.0]), CFG)
    assert s.clipped <= CFG.clip_high and s.level <= CFG.level_high
    assert np.all(scales[200:] == 1.0)                # back on clean frames
    steps = np.sign(np.diff(scales))
    turns = np.count_nonzero(np.diff(steps[steps != 0]))
    assert turns <= 2


def test_a_flickering_arc_does_not_make_the_exposure_hunt():
    """Glare flickering +-20 % frame to frame: after settling, the scale moves in one
    direction at most once per 10 frames (the band and the hold), not every frame."""
    rng = np.random.default_rng(3)
    flick = 400.0 * (1.0 + 0.2 * rng.uniform(-1, 1, 300))
    scales = _run(lambda k: flick[k], 300)
    changes = np.count_nonzero(np.diff(scales[50:]))
    assert changes <= 25, changes
    assert scales[50:].max() < 1.0                    # it stays down under the arc


def test_light_that_clips_at_any_exposure_is_not_chased_down():
    """A weld pool flaring over the corner for 40 frames (a disc clipped at any exposure,
    pasted on the frame): steps down change nothing in the window, so after respond_steps of
    them the exposure goes back to where it was before them (they only darkened the stripe)
    and holds there while the disc clips, instead of darkening the stripe to min_scale."""
    ae, rng, scales = ExposureController(CFG), np.random.default_rng(2), []
    yy, xx = np.mgrid[0:81, 0:81]
    disc = (xx - 40) ** 2 + (yy - 40) ** 2 <= 30 ** 2
    for k in range(130):
        scales.append(ae.scale)
        frame = _window(ae.scale, 160.0, 0.0, rng)
        if 20 <= k < 60:
            frame[disc] = 255
        ae.update(frame_stats(frame, np.array([40.0, 40.0]), CFG))
    scales = np.array(scales)
    tell = CFG.step_down ** CFG.respond_steps          # the steps it takes to tell
    assert scales[21] == CFG.step_down                 # a step down: the disc clips
    assert scales[20:61].min() == pytest.approx(tell)  # and no more than those
    assert tell > CFG.min_scale
    back = 21 + CFG.respond_steps                      # then undone: none of them helped
    assert np.all(scales[back:61] == 1.0), scales[20:61]
    assert np.all(scales[-5:] == 1.0)                  # and so after it


def test_a_dim_stripe_keeps_the_configured_exposure():
    """A clean frame whose stripe is under level_low never goes over max_scale."""
    scales = _run(lambda k: 0.0, 40, stripe=120.0)
    assert np.all(scales == CFG.max_scale)


def test_the_exposure_stays_within_its_bounds():
    ae = ExposureController(CFG)
    for k in range(200):   # a flickering arc: the clipped share changes frame to frame
        ae.update(FrameStats(255.0, (0.5, 0.2)[k % 2], 1.0))
    assert ae.scale == CFG.min_scale
    ae = ExposureController(CFG, start=0.01)
    assert ae.scale == CFG.min_scale
    for _ in range(500):
        ae.update(FrameStats(10.0, 0.0, 0.0))
    assert ae.scale == CFG.max_scale


def test_frame_stats_reads_colour_16_bit_and_a_point_off_the_frame():
    f = np.zeros((60, 80), np.uint8)
    f[28:32, :] = 255
    mono = frame_stats(f, np.array([40.0, 30.0]), CFG)
    assert mono.level == 255.0 and mono.clipped == pytest.approx(4 / 60)
    col = np.zeros((60, 80, 3), np.uint8)
    col[28:32, :, 2] = 255                           # red clipped only: clipped
    assert frame_stats(col, np.array([40.0, 30.0]), CFG) == mono
    assert frame_stats(f.astype(np.uint16) * 257, np.array([40.0, 30.0]), CFG) == mono
    # no point, or one off the frame: the whole frame
    assert frame_stats(f, None, CFG) == frame_stats(f, np.array([np.nan, 1.0]), CFG)
    assert frame_stats(f, np.array([900.0, 900.0]), CFG).clipped == pytest.approx(4 / 60)


def test_settings_that_would_oscillate_are_refused_in_one_line(tmp_path):
    bad = dataclasses.asdict(CFG) | {"step_up": 1.5}
    p = tmp_path / "exposure.yaml"
    p.write_text(yaml.safe_dump(bad))
    with pytest.raises(ConfigError, match="oscillation") as e:
        load_exposure_config(p)
    assert "\n" not in str(e.value)
    p.write_text(yaml.safe_dump(dataclasses.asdict(CFG) | {"level_low": 250.0}))
    with pytest.raises(ConfigError, match="level_low"):
        load_exposure_config(p)
    assert isinstance(load_exposure_config(), ExposureConfig)


def test_a_frame_rendered_at_half_exposure_is_the_family_with_half_the_gain(cell, part, noise):
    """``exposure`` scales the light as the family's exposure gain does (the same frame as a
    family with half the gain), darker than at the family's own, with the same random draws;
    and ``simulate`` asks for each frame's exposure just before rendering it."""
    fam = "sim"
    spec = SequenceSpec(n_frames=2, level=1.5, seed=2, family=fam, arc_on_frame=1)
    asked = []

    def half(k: int) -> float:
        asked.append(k)
        return 0.5

    got = [f for f, _ in simulate(cell, part, noise, spec, exposure=half)]
    assert asked == [0, 1]
    look = getattr(noise.families, fam)
    halved = dataclasses.replace(look, exposure=dataclasses.replace(look.exposure,
                                                                    gain=0.5 * look.exposure.gain))
    noise_h = dataclasses.replace(noise, families=dataclasses.replace(noise.families,
                                                                      **{fam: halved}))
    want = [f for f, _ in simulate(cell, part, noise_h, spec)]
    for a, b in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    full = [f for f, _ in simulate(cell, part, noise, spec)]
    assert np.mean(got[-1]) < 0.7 * np.mean(full[-1])
    assert (full[-1] >= 250).sum() > 2 * (got[-1] >= 250).sum()
    with pytest.raises(ValueError, match="exposure must be > 0"):
        next(simulate(cell, part, noise, spec, exposure=lambda k: 0.0))


# --------------------------------------------------------------------------- the live cell


def _wait_for(cond, timeout_s: float = 2.0) -> bool:
    import time

    end = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > end:
            return False
        time.sleep(0.005)
    return True


def test_a_frame_stream_carries_the_welds_exposure_request_to_the_camera():
    """The weld's request reaches the virtual camera's server (the exposure its next frames
    are rendered at); a new reader starts at the configured exposure; a request that breaks
    the format is refused, not applied."""
    import socket

    from torchseam.live.framestream import (
        REQUEST,
        FrameStreamError,
        FrameStreamServer,
        StreamCamera,
    )

    server = FrameStreamServer("127.0.0.1", 0)
    try:
        url = f"tcp://127.0.0.1:{server.address[1]}"
        with StreamCamera(url, connect_timeout_s=5.0) as cam:
            assert _wait_for(lambda: server.connected)
            assert server.exposure == 1.0
            cam.request_exposure(0.5)
            cam.request_exposure(0.4)
            assert _wait_for(lambda: server.exposure == 0.4 and server.requests == 2)
            with pytest.raises(FrameStreamError, match="exposure scale 0 is outside"):
                cam.request_exposure(0.0)
        with socket.create_connection(server.address) as s:
            assert _wait_for(lambda: server.exposure == 1.0)      # a new reader
            s.sendall(REQUEST.pack(b"XXXX", 1, REQUEST.size, 0.3))
            assert _wait_for(lambda: server.bad_requests == 1)
            assert server.exposure == 1.0
    finally:
        server.close()


def test_the_cell_file_turns_auto_exposure_on_only_for_a_camera_that_takes_it(tmp_path):
    from torchseam.core.config import ConfigError, load_cell, to_dict
    from torchseam.live.cellfile import CameraLink, ControllerLink, WeldCell, load_weld_cell

    cell = WeldCell(load_cell(), CameraLink(source="tcp://127.0.0.1:7000", latency_ms=20.0),
                    ControllerLink(host="127.0.0.1", port=6510, controller_host="127.0.0.1",
                                   controller_port=6511))
    assert cell.camera.auto_exposure is False                     # off by default
    data = to_dict(cell)
    data["camera"]["auto_exposure"] = True
    (tmp_path / "on.yaml").write_text(yaml.safe_dump(data))
    assert load_weld_cell(tmp_path / "on.yaml").camera.auto_exposure is True
    data["camera"]["source"] = "camera:0"
    (tmp_path / "cv.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"camera.auto_exposure: set, but camera:0 takes no "
                                          r"exposure request") as e:
        load_weld_cell(tmp_path / "cv.yaml")
    assert "\n" not in str(e.value)


def test_the_welds_exposure_step_asks_the_camera_for_less_under_clipping_glare():
    """The weld's step (its frame and tracked point in, a request out): a frame clipped round
    the point asks the camera for a lower exposure, a clean one asks nothing new; a camera
    OpenCV reads refuses a request in one line."""
    from torchseam.live.cameras import OpenCVCamera
    from torchseam.live.framestream import FrameStreamError
    from torchseam.live.weld import auto_exposure_step

    class Cam:
        def __init__(self):
            self.asked = []

        def request_exposure(self, scale):
            self.asked.append(scale)

    ae, cam, rng = ExposureController(CFG), Cam(), np.random.default_rng(0)
    clean = _window(1.0, 160.0, 0.0, rng)
    assert auto_exposure_step(ae, cam, clean, np.array([40.0, 40.0])) == 1.0
    assert cam.asked == []
    glare = np.dstack([_window(1.0, 160.0, 400.0, rng)] * 3)      # colour, clipped
    assert auto_exposure_step(ae, cam, glare, np.array([40.0, 40.0])) == CFG.step_down
    assert cam.asked == [CFG.step_down]
    opencv = OpenCVCamera.__new__(OpenCVCamera)
    opencv.url = "camera:0"
    with pytest.raises(FrameStreamError, match="camera:0: takes no exposure request"):
        opencv.request_exposure(0.5)



def test_the_welds_table_says_the_automatic_exposure_it_asked_for():
    """`torchseam weld`'s last table: the scales asked for (min / median / max, changes) when
    the automatic exposure ran, no such row when it did not; a weld that ended before its link
    ran says n/a rather than failing."""
    from torchseam.live.cell_cli import summary_rows
    from torchseam.live.weld import WeldResult, weld_summary

    res = WeldResult()
    assert not any("exposure" in r[0] for r in summary_rows(weld_summary(res, {}), "a"))
    res.exposure = [("a", 0.0, 1.0), ("a", 0.04, 0.8), ("a", 0.08, 0.8), ("b", 0.12, 0.64)]
    rows = {r[0]: r[1] for r in summary_rows(weld_summary(res, {}), "ab")}
    assert rows["automatic exposure min / median / max (changes)"] == "0.64 / 0.80 / 1.00 (2)"
    assert rows["EGM replies sent / late"] == "n/a" and rows["segments welded"] == "0 of 2"
