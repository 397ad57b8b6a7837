"""The command line: simulate, detect, demo, and clear errors."""

import subprocess
import sys

import numpy as np
import pytest

from torchseam.cli import build_parser, main
from torchseam.core.dataset import Dataset


def test_every_command_has_help(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in sub.choices:
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
        assert "usage: torchseam " + name in capsys.readouterr().out


def test_simulate_with_preview_then_detect(tmp_path, capsys):
    out = tmp_path / "seq"
    assert main(["simulate", str(out), "--frames", "6", "--noise", "heavy", "--seed", "2",
                 "--preview"]) == 0
    assert (out / "preview.png").exists()
    ds = Dataset.open(out, require_labels=True)
    assert len(ds) == 6 and ds.meta["noise"]["name"] == "heavy"
    capsys.readouterr()
    # frame 0 is arc-off (clean lead frames): TIPM must find the labelled point
    assert main(["detect", str(out / "00000.png"), "--overlay", str(tmp_path / "ov")]) == 0
    line = capsys.readouterr().out.strip().split()
    np.testing.assert_allclose([float(line[1]), float(line[2])], ds.labels[0], atol=1.0)
    assert (tmp_path / "ov" / "00000_tipm.png").exists()


@pytest.mark.parametrize(("camera", "dtype"), [("mono", np.uint8), ("mono16", np.uint16)])
def test_simulate_writes_a_mono_cameras_frames(camera, dtype, tmp_path, capsys):
    """A mono camera behind the band-pass: one channel, 8 or 16 bit, the same scene (TIPM finds
    the labelled point on the arc-off frame 0), the camera said in meta.json."""
    import cv2

    out = tmp_path / camera
    assert main(["simulate", str(out), "--frames", "2", "--camera", camera]) == 0
    img = cv2.imread(str(out / "00000.png"), cv2.IMREAD_UNCHANGED)
    assert img.ndim == 2 and img.dtype == dtype and int(img.max()) > np.iinfo(dtype).max // 4
    ds = Dataset.open(out, require_labels=True)
    assert ds.meta["camera"] == camera
    capsys.readouterr()
    assert main(["detect", str(out / "00000.png")]) == 0
    line = capsys.readouterr().out.strip().split()
    np.testing.assert_allclose([float(line[1]), float(line[2])], ds.labels[0], atol=0.5)


def test_bad_noise_level_is_a_clear_error(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "x"), "--noise", "loud"]) == 2
    err = capsys.readouterr().err
    assert "--noise" in err and "heavy" in err and "Traceback" not in err


def test_detect_reports_unreadable_files(tmp_path, capsys):
    bad = tmp_path / "00000.png"
    bad.write_text("nope")
    assert main(["detect", str(bad)]) == 2  # bad input
    out = capsys.readouterr()
    assert out.err.startswith("torchseam detect: error: ") and out.err.count("\n") == 1
    assert "cannot be decoded" in out.err and out.out == ""


def test_demo_runs_as_installed_command(tmp_path):
    """A short closed-loop weld through the real command; the report has the documented keys."""
    import json

    out = tmp_path / "demo"
    r = subprocess.run([sys.executable, "-m", "torchseam.cli", "demo", "--segments", "a",
                        "--length-mm", "16", "--noise", "clean", "--out",
                        str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    # the video (written on its own thread) holds every frame of the weld
    import cv2

    cap = cv2.VideoCapture(str(out / "weld.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == s["frames"]
    for key in ("seam_rmse_mm", "seam_max_mm", "nominal_rmse_mm", "pixel_rmse_px",
                "latency_p99_ms", "poses_sent", "poses_refused", "unsafe_poses_sent"):
        assert key in s
    assert s["unsafe_poses_sent"] == 0 and s["poses_sent"] > 5
    assert s["seam_rmse_mm"] < 0.1 < s["nominal_rmse_mm"]
    assert "torch path vs true seam" in r.stdout


def test_detect_takes_any_image_size(tmp_path, capsys):
    """The camera's size matters for 3D, not for finding a corner: a 320 x 240 V stripe gives
    its corner; the same file twice gets two overlays, not one overwritten."""
    import cv2

    small = tmp_path / "small.png"
    img = np.zeros((240, 320, 3), np.uint8)
    cv2.polylines(img, [np.array([[10, 60], [150, 130], [310, 50]], np.int32)], False,
                  (40, 50, 230), 2, cv2.LINE_AA)
    cv2.imwrite(str(small), img)
    assert main(["detect", str(small), str(small), "--overlay", str(tmp_path / "ov")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    u, v = (float(x) for x in lines[0].split()[1:3])
    assert abs(u - 150) < 2 and abs(v - 130) < 2
    assert len(list((tmp_path / "ov").glob("*.png"))) == 2
