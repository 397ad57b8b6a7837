"""The GenICam camera input against a real GigE Vision stack: Aravis' fake camera on loopback
(GVCP control, GVSP stream). Skips, with the reason, where the optional extra
(`pip install ".[genicam]"`) or Aravis' tools (Debian: aravis-tools) are not installed;
.ci/run installs both."""

from __future__ import annotations

import shutil
import subprocess
import time

import numpy as np
import pytest

from torchseam.live.clocks import ClockOffset
from torchseam.live.framestream import FrameStreamError

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)

FAKE = shutil.which("arv-fake-gv-camera-0.8")


def _aravis():
    try:
        from torchseam.live.genicam import load_aravis

        return load_aravis()
    except FrameStreamError as e:
        pytest.skip(f"GenICam extra not installed: {e}")


@pytest.fixture
def fake_camera():
    _aravis()
    if FAKE is None:
        pytest.skip("arv-fake-gv-camera-0.8 not found (Debian: apt-get install aravis-tools)")
    p = subprocess.Popen([FAKE, "-i", "127.0.0.1", "-s", "TS0001"], stdout=subprocess.DEVNULL,
                         stderr=subprocess.DEVNULL)
    time.sleep(0.5)
    yield "aravis://127.0.0.1"
    p.terminate()
    p.wait(5)


def test_aravis_camera_gives_frames_with_the_cameras_own_time(fake_camera):
    from torchseam.live.genicam import AravisCamera

    with AravisCamera(fake_camera, frame_rate_hz=25.0, size=(656, 492)) as cam:
        frames = [cam.get(3.0) for _ in range(12)]
    frames = [f for f in frames if f is not None][2:]   # (the rate applies from the next frames)
    assert len(frames) >= 8
    assert all(f.image.shape == (492, 656) and f.image.dtype == np.uint8 for f in frames)
    ids = np.array([f.index for f in frames])
    assert np.all(np.diff(ids) >= 1)                     # the camera's own frame numbers
    t_exp = np.array([f.t_exp_s for f in frames])
    dt = np.diff(t_exp) / np.diff(ids)
    # its clock ticks at the frame rate (the fake camera's software timer jitters by a few ms
    # on a busy machine; its median does not)
    assert abs(np.median(dt) - 0.04) < 0.001 and np.all(np.abs(dt - 0.04) < 0.01), dt
    t_arr = np.array([f.t_arrival_s for f in frames])
    assert np.all(np.diff(t_arr) > 0)
    # its clock related to this PC's as the weld does it, a plausible latency apart
    off = ClockOffset(known_delay_s=0.0)
    for f in frames:
        off.add(f.t_exp_s, f.t_arrival_s)
    lat = t_arr - np.array([off.to_pc(t) for t in t_exp])
    # (times near 1.8e9 s carry ~2e-7 s of float64 rounding)
    assert np.all(lat >= -1e-6) and np.all(lat < 0.1), lat


def test_aravis_url_that_names_no_camera_is_one_clear_error():
    _aravis()
    from torchseam.live.genicam import AravisCamera

    with pytest.raises(FrameStreamError, match="Aravis cannot open it"):
        AravisCamera("aravis://No-Such-Camera-0000")


def test_aravis_camera_takes_the_cell_files_exposure_time(fake_camera):
    """The weld sets camera.exposure_us on a GenICam camera, and reads back what it took; its
    automatic exposure's requests are taken the same way."""
    from torchseam.live.genicam import AravisCamera

    with AravisCamera(fake_camera, frame_rate_hz=25.0, exposure_us=1500.0) as cam:
        assert cam.exposure_us == pytest.approx(1500.0)
        assert cam.camera.get_exposure_time() == pytest.approx(1500.0)
        assert cam.get(3.0) is not None              # and it streams
        # the weld's automatic exposure: scale x the time set at open, within the camera's
        # bounds and the frame period
        cam.request_exposure(0.5)
        assert cam.exposure_us == pytest.approx(750.0)
        assert cam.camera.get_exposure_time() == pytest.approx(750.0)
        cam.request_exposure(100.0)
        assert cam.exposure_us == pytest.approx(40_000.0)


@pytest.mark.parametrize("us, fps, message", [
    (5e7, None, r"camera.exposure_us 5e\+07 is outside what the camera takes \(10 .. 1e\+07 us\)"),
    (50_000.0, 25.0, r"longer than the frame period at 25 frames/s \(40000 us\)")])
def test_aravis_exposure_the_camera_cannot_take_is_one_clear_error(fake_camera, us, fps,
                                                                   message):
    """The fake camera, like some real ones, stores any number it is sent: the bounds and the
    frame period are checked before it is."""
    from torchseam.live.genicam import AravisCamera

    with pytest.raises(FrameStreamError, match=message):
        AravisCamera(fake_camera, frame_rate_hz=fps, exposure_us=us)
