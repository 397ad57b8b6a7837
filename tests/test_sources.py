"""Frame sources (folder, video, simulator, threaded reader) and the open-loop replay."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from torchseam.cli import main
from torchseam.core.errors import DatasetError, FrameError
from torchseam.live.loop import RecordingSink
from torchseam.live.replay import run_replay
from torchseam.live.sources import (
    BaseSource,
    CameraSource,
    FolderSource,
    Frame,
    FrameSource,
    SimulatedSource,
    ThreadedSource,
    VideoSource,
    open_source,
)
from torchseam.sim.record import write_sequence
from torchseam.sim.sequence import SequenceSpec
from torchseam.track.peers import make_tracker

pytestmark = pytest.mark.realtime  # wall-clock timing: run alone (README's test command)

N_FRAMES = 24
SPEC = SequenceSpec(n_frames=N_FRAMES, level=0.3, seed=4, start_mm=40.0)


@pytest.fixture(scope="module")
def recording(tmp_path_factory, cell, part, noise):
    """A small recorded folder (dataset format with meta.json) and its truths."""
    out = tmp_path_factory.mktemp("rec")
    truths = write_sequence(out, cell, part, noise, SPEC, progress=False)
    return out, truths


@pytest.fixture(scope="module")
def video(tmp_path_factory, recording):
    """The same frames as an MJPG AVI at 25 fps."""
    folder, _ = recording
    path = tmp_path_factory.mktemp("vid") / "weld.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (656, 492))
    assert w.isOpened()
    for i in range(N_FRAMES):
        w.write(cv2.imread(str(folder / f"{i:05d}.png")))
    w.release()
    return path


def test_folder_source_gives_frames_times_poses_and_labels(recording, cell):
    folder, truths = recording
    size = (cell.camera.width, cell.camera.height)
    with FolderSource(folder, size) as src:
        assert isinstance(src, FrameSource) and len(src) == N_FRAMES
        frames = list(src)
    assert [f.index for f in frames] == list(range(N_FRAMES))
    for f, t in zip(frames, truths, strict=True):
        assert f.image.shape == (492, 656, 3) and f.image.dtype == np.uint8
        np.testing.assert_array_equal(f.image, cv2.imread(str(folder / f"{f.index:05d}.png")))
        assert f.t_s == pytest.approx(t.t_s, abs=1e-6)
        np.testing.assert_allclose(f.T_B_W, t.T_B_W, atol=1e-5)
        np.testing.assert_allclose(f.label, t.uv, atol=1e-4)


def test_simulated_source_matches_the_recording(recording, cell, part, noise):
    folder, truths = recording
    src = SimulatedSource(cell, part, noise, SPEC)
    for f, g in zip(src, FolderSource(folder), strict=True):
        np.testing.assert_array_equal(f.image, g.image)   # PNG is lossless
        np.testing.assert_allclose(f.T_B_W, g.T_B_W, atol=1e-5)
    assert len(src.truths) == N_FRAMES


def test_folder_source_names_bad_frames_and_files(recording, tmp_path):
    folder, _ = recording
    bad = tmp_path / "bad"
    bad.mkdir()
    for i in range(3):
        (bad / f"{i:05d}.png").write_bytes((folder / f"{i:05d}.png").read_bytes())
    (bad / "00002.png").write_text("not a png")
    it = iter(FolderSource(bad))
    assert next(it).index == 0 and next(it).index == 1   # good frames still come
    with pytest.raises(FrameError, match=r"frame 2: .*00002\.png: cannot be decoded"):
        next(it)
    # wrong size for the configured camera
    with pytest.raises(FrameError, match="frame 0: .*frame is 656 x 492 px"):
        next(iter(FolderSource(folder, size=(640, 480))))
    with pytest.raises(DatasetError, match="no such folder"):
        FolderSource(tmp_path / "missing")
    # a broken pose in meta.json names the file and the frame
    (bad / "00002.png").write_bytes((folder / "00002.png").read_bytes())
    (bad / "meta.json").write_text('{"frames": [{"frame": 1, "t_s": 0.04, '
                                   '"tcp_pose": {"position_mm": [1, 2]}}]}')
    with pytest.raises(DatasetError, match=r"meta\.json: frames\[0\] \(frame 1\)"):
        FolderSource(bad)


def test_video_source_reads_frames_with_time_stamps(video, recording):
    folder, _ = recording
    with VideoSource(video, size=(656, 492)) as src:
        assert src.fps == pytest.approx(25.0)
        frames = list(src)
    assert len(frames) == N_FRAMES
    assert [f.index for f in frames] == list(range(N_FRAMES))
    np.testing.assert_allclose([f.t_s for f in frames], np.arange(N_FRAMES) / 25.0, atol=1e-6)
    ref = cv2.imread(str(folder / "00005.png")).astype(float)
    assert np.abs(frames[5].image.astype(float) - ref).mean() < 3.0   # MJPG is lossy
    assert frames[5].T_B_W is None and frames[5].label is None
    assert isinstance(open_source(video), VideoSource)
    assert isinstance(open_source(folder), FolderSource)


def test_video_source_names_bad_input(tmp_path, video):
    with pytest.raises(FrameError, match=r"nope\.mp4: no such video file"):
        VideoSource(tmp_path / "nope.mp4")
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"\0" * 1000)
    with pytest.raises(FrameError, match=r"junk\.mp4: cannot be opened as a video"):
        VideoSource(junk)
    with pytest.raises(FrameError, match=r"weld\.avi: frame 0: frame is 656 x 492"):
        next(iter(VideoSource(video, size=(320, 240))))
    with pytest.raises(DatasetError, match="no such folder or video file"):
        open_source(tmp_path / "nothing")


def test_camera_source_streams_with_host_time_and_ends_with_a_named_error(video):
    # OpenCV opens a stream given by name like a device; the video plays the camera here
    cam = CameraSource(str(video), size=(656, 492), max_failed_reads=3)
    frames = []
    with pytest.raises(FrameError, match=r"no frame in 3 reads after frame 23 .*stream ended"):
        for f in cam:
            frames.append(f)
    cam.close()
    assert [f.index for f in frames] == list(range(N_FRAMES))
    t = np.array([f.t_s for f in frames])
    assert t[0] == 0.0 and np.all(np.diff(t) > 0)          # host clock, from the first frame
    with pytest.raises(FrameError, match="frame 0: frame is 656 x 492"):
        next(iter(CameraSource(str(video), size=(320, 240))))


def test_open_source_takes_cameras_and_names_bad_ones(video, capfd):
    src = open_source(f"camera:{video}")
    assert isinstance(src, ThreadedSource) and isinstance(src.source, CameraSource)
    with src, pytest.raises(FrameError, match="stream ended"):
        for _ in src:
            pass
    capfd.readouterr()
    with pytest.raises(FrameError, match="camera 97: cannot be opened"):
        open_source("camera:97")
    # the error is the one line: OpenCV's own warnings about the device are held back
    assert "WARN" not in capfd.readouterr().err
    with pytest.raises(FrameError, match="give the camera as camera:N"):
        open_source("camera:")


class _Burst(BaseSource):
    """A fast source: ``n`` tiny frames as quickly as possible, optionally failing at one."""

    def __init__(self, n: int, fail_at: int | None = None) -> None:
        self.n, self.fail_at = n, fail_at
        self.closed = False

    def __iter__(self):
        for k in range(self.n):
            if k == self.fail_at:
                raise FrameError(f"camera: frame {k} is corrupt")
            yield Frame(np.zeros((4, 4, 3), np.uint8), k / 25.0, k)

    def close(self) -> None:
        self.closed = True


def test_threaded_source_is_bounded_and_drops_the_oldest():
    inner = _Burst(200)
    src = ThreadedSource(inner, maxsize=3)
    got = []
    with src:
        for f in src:
            assert src._q.qsize() <= 3   # never more than maxsize waiting
            got.append(f.index)
            time.sleep(0.002)   # a consumer slower than the camera
    assert inner.closed
    assert got == sorted(got) and got[-1] == 199   # in order, and the newest arrives
    assert src.dropped > 0 and len(got) + src.dropped == 200


def test_threaded_source_passes_reader_errors_on():
    src = ThreadedSource(_Burst(10, fail_at=6), maxsize=16)
    got = []
    with pytest.raises(FrameError, match="frame 6 is corrupt"):
        for f in src:
            got.append(f.index)
    assert got == list(range(6)) and src.dropped == 0
    src.close()
    assert not any(t.name == "frame-reader" and t.is_alive() for t in threading.enumerate())


def test_replay_of_a_recording_tracks_and_locates(recording, cell, parts):
    folder, truths = recording
    truth = {t.index: t.seam_B for t in truths}
    sink = RecordingSink()
    res = run_replay(cell, FolderSource(folder), make_tracker("anchored", parts.tipm),
                     parts=parts, sink=sink, truth=truth)
    assert res.poses_known and res.start_index == 0 and len(res.index) == N_FRAMES - 1
    err = res.pixel_errors()
    assert len(err) == N_FRAMES - 1 and np.sqrt(np.mean(err**2)) < 2.0
    d = np.linalg.norm(res.p - res.p_true, axis=1)
    assert np.isfinite(d).sum() >= N_FRAMES - 3 and np.nanmax(d) < 0.5
    # poses planned from the located seam, handed to the sink (the current target is also
    # re-sent while the torch moves to it), all finite with unit quaternions
    assert len(res.commands) >= 2 and sink.accepted >= sum(c.ok for c in res.commands)
    sent = [p.tolist() for p, _, _ in sink.poses]
    assert all(c.p.tolist() in sent for c in res.commands)
    for p, q, _ in sink.poses:
        assert np.isfinite(p).all() and abs(np.linalg.norm(q) - 1) < 1e-9
    for stage in ("track", "ecal", "triangulate", "plan+gate+send", "frame->command"):
        p50, p99 = res.latency[stage]
        assert 0 <= p50 <= p99


def test_replay_command_on_folder_and_video(recording, video, tmp_path, capsys):
    folder, _ = recording
    out = tmp_path / "track.csv"
    assert main(["replay", str(folder), "--max-frames", "12", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "feature point vs label, RMSE" in text and "frame->command p50 / p99" in text
    assert "from the recording" in text
    lines = out.read_text().splitlines()
    assert lines[0] == "frame,t_s,u,v,status,x,y,z" and len(lines) == 12
    assert main(["replay", str(video), "--max-frames", "8"]) == 0
    assert "not recorded" in capsys.readouterr().out
    assert main(["replay", str(tmp_path / "none.avi")]) == 2
    assert "no such folder or video file" in capsys.readouterr().err
    assert main(["replay", str(folder), "--init", "1,2,3"]) == 2
    assert "--init" in capsys.readouterr().err


def test_ctrl_c_stops_the_replay_with_the_figures_of_the_frames_done(recording, tmp_path,
                                                                     monkeypatch, capsys):
    """SIGINT (Ctrl-C) while the 11th frame is read: the replay stops before the next frame,
    prints the figures of the frames done, writes --out for them and exits 130."""
    import os
    import signal

    from torchseam.core.dataset import Dataset

    folder, _ = recording
    read = Dataset.read

    def read_then_ctrl_c(self, i, *a, **k):
        if i == 10:
            os.kill(os.getpid(), signal.SIGINT)
        return read(self, i, *a, **k)

    monkeypatch.setattr(Dataset, "read", read_then_ctrl_c)
    out = tmp_path / "c.csv"
    before = signal.getsignal(signal.SIGINT)
    assert main(["replay", str(folder), "--out", str(out)]) == 130
    assert signal.getsignal(signal.SIGINT) is before  # the handler put back
    cap = capsys.readouterr()
    assert "replay of" in cap.out and ": 11 frames (start frame 0)" in cap.out
    assert "[frame 11] stopped by SIGINT" in cap.out
    assert "interrupted by SIGINT after 11 frames" in cap.err
    lines = out.read_text().splitlines()
    assert lines[0] == "frame,t_s,u,v,status,x,y,z" and len(lines) == 11  # frames 1-10
