"""Hostile frame files (issue 36): a FIFO among the frames and a PNG bomb (30 000 x 30 000 px
in under 1 MB) through every frame reader: ``detect``, ``track``, ``eval``, ``replay``,
``console --source DIR`` and the calibration sets.

A FIFO is refused without being opened (a reader that opens one blocks until somebody writes:
forever), an image is sized from its header and refused above the pixel limit before it is
decoded (:mod:`torchseam.core.imageio`). A single frame on the command line: one line on
stderr, exit 2; a frame in a sequence: ``unreadable``, the run goes on (``replay`` and the
console stop at it with one line, as they do at any broken frame). The commands run in
subprocesses with timeouts (a hang fails, it does not block the suite) and their peak memory
is measured (``ru_maxrss`` of the child).
"""

from __future__ import annotations

import csv
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseam.core import imageio
from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.dataset import Dataset, read_frame
from torchseam.core.errors import DatasetError, FrameError, TorchseamError
from torchseam.core.imageio import (
    MAX_FRAME_PIXELS,
    PIXELS_ENV,
    header_size,
    image_size,
    read_image,
)
from torchseam.sim.record import write_sequence
from torchseam.sim.sequence import SequenceSpec

BOMB_SIDE = 30_000
#: the issue's bar for the bomb
PEAK_MB = 500
#: seconds a command gets before it counts as hung
TIMEOUT_S = 120


def _chunk(kind: bytes, data: bytes) -> bytes:
    return (struct.pack(">I", len(data)) + kind + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))


def bomb_png(w: int, h: int) -> bytes:
    """A valid 8-bit grey PNG of ``w`` x ``h`` black pixels, every row compressed: 875 KB for
    30 000 x 30 000 (900 MB decoded, 2.7 GB as BGR)."""
    z = zlib.compressobj(6)
    block = bytes(w + 1) * 100   # a hundred rows of filter byte 0 and zeros
    rows = b"".join(z.compress(block) for _ in range(h // 100))
    rows += z.compress(bytes(w + 1) * (h % 100)) + z.flush()
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + _chunk(b"IDAT", rows) + _chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def bomb(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("bomb") / "bomb.png"
    p.write_bytes(bomb_png(BOMB_SIDE, BOMB_SIDE))
    assert p.stat().st_size < 1_000_000
    return p


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    """Eight clean simulated frames with labels and meta.json (the dataset format)."""
    d = tmp_path_factory.mktemp("frames") / "seq"
    write_sequence(d, load_cell(), load_part(), load_noise(),
                   SequenceSpec(n_frames=8, level=0.0, seed=5), progress=False)
    return d


def _folder(seq: Path, dst: Path, fifo: tuple[int, ...] = (), bombs: tuple[int, ...] = (),
            bomb: Path | None = None) -> Path:
    """A copy of ``seq`` (copied file by file: copying a FIFO would block) with FIFOs and
    bombs in place of the frames numbered ``fifo`` and ``bombs``."""
    dst.mkdir()
    for p in seq.iterdir():
        i = int(p.stem) if p.stem.isdigit() else -1
        if i in fifo:
            os.mkfifo(dst / p.name)
        elif i in bombs:
            assert bomb is not None
            (dst / p.name).write_bytes(bomb.read_bytes())
        else:
            (dst / p.name).write_bytes(p.read_bytes())
    return dst


_WRAP = r"""
import json, resource, subprocess, sys
try:
    r = subprocess.run(sys.argv[2:], capture_output=True, text=True, timeout=float(sys.argv[1]))
    out = {"rc": r.returncode, "out": r.stdout, "err": r.stderr}
except subprocess.TimeoutExpired as e:   # the child is killed: a hang is a failure, not a wait
    out = {"rc": None, "out": str(e.stdout), "err": str(e.stderr)}
out["maxrss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
print(json.dumps(out))
"""


def _measured(args: list[str], timeout: float = TIMEOUT_S) -> dict:
    """``torchseam ARGS`` in a child process: rc (None: killed after ``timeout``), out, err
    and its peak resident memory in MB (``ru_maxrss`` of that child alone: a fresh wrapper
    process per command)."""
    env = {**os.environ, "TQDM_DISABLE": "1"}
    env.pop(PIXELS_ENV, None)
    r = subprocess.run([sys.executable, "-c", _WRAP, str(timeout), sys.executable, "-m",
                        "torchseam", *args], capture_output=True, text=True,
                       timeout=timeout + 60, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def _one_line(res: dict, command: str) -> str:
    assert res["rc"] is not None, f"torchseam {command} hung: {res}"
    lines = [s for s in res["err"].strip().splitlines() if s.strip()]
    assert len(lines) == 1, res["err"]
    assert lines[0].startswith(f"torchseam {command}: error: "), lines[0]
    return lines[0]


# --------------------------------------------------------------------------- the header reader

#: (suffix, channels, dtype) of every format whose size is read from its header
FORMATS = [(".png", 3, np.uint8), (".png", 1, np.uint16), (".jpg", 3, np.uint8),
           (".bmp", 3, np.uint8), (".tif", 3, np.uint8), (".tif", 1, np.uint16),
           (".pgm", 1, np.uint8), (".ppm", 3, np.uint8), (".pbm", 1, np.uint8),
           (".pam", 3, np.uint8), (".webp", 3, np.uint8), (".gif", 3, np.uint8),
           (".ras", 3, np.uint8), (".hdr", 3, np.float32), (".pfm", 3, np.float32)]


def _encoded(suffix: str, channels: int, dtype, w: int, h: int, seed: int = 0) -> bytes:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (h, w, channels)).astype(dtype)
    if dtype == np.float32:
        img /= 255
    ok, buf = cv2.imencode(suffix, img[..., 0] if channels == 1 else img)
    assert ok
    return buf.tobytes()


def _reader(data: bytes):
    def read_at(offset: int, n: int) -> bytes:
        assert 0 <= offset and n >= 0, (offset, n)
        return data[offset:offset + n]
    return read_at


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fmt=st.sampled_from(FORMATS), w=st.integers(1, 300), h=st.integers(1, 300))
def test_the_header_gives_the_size_the_decoder_makes(fmt, w, h):
    data = _encoded(*fmt, w, h)
    name, hw, hh = header_size(_reader(data), len(data))
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert (hw, hh) == (w, h) == (img.shape[1], img.shape[0]), (name, fmt)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fmt=st.sampled_from(FORMATS), cut=st.integers(0, 2000),
       flips=st.lists(st.tuples(st.integers(0, 300), st.integers(0, 255)), max_size=6),
       data=st.data())
def test_a_mangled_header_is_a_value_error_never_a_crash(fmt, cut, flips, data):
    """Truncated and byte-flipped files of every format: the size, or a ValueError saying
    why; never another exception, a read out of the file, or a read beyond the limits."""
    raw = bytearray(_encoded(*fmt, 40, 30))
    for pos, val in flips:
        if pos < len(raw):
            raw[pos] = val
    raw = bytes(raw[:cut]) if data.draw(st.booleans(), label="truncate") else bytes(raw)
    try:
        name, w, h = header_size(_reader(raw), len(raw))
    except ValueError as e:
        assert str(e) and "\n" not in str(e)
        return
    assert w > 0 and h > 0 and name


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"BM", b"II*\0", b"MM\0*",
                        b"II+\0", b"MM\0+", b"P5\n", b"P7\n", b"PF\n", b"RIFF\0\0\0\0WEBP",
                        b"GIF89a", b"\x59\xa6\x6a\x95", b"#?RADIANCE\n", b""]),
       st.binary(max_size=200))
def test_random_bytes_behind_a_signature(lead, tail):
    raw = lead + tail
    try:
        header_size(_reader(raw), len(raw))
    except ValueError:
        pass


def test_jpeg_segments_before_the_frame_header_are_skipped():
    data = _encoded(".jpg", 3, np.uint8, 64, 48)
    app = b"\xff\xe1" + struct.pack(">H", 60002) + bytes(60000)   # a large EXIF-like segment
    fill = b"\xff\xff\xff"
    moved = data[:2] + app + fill + data[2:]
    assert header_size(_reader(moved), len(moved)) == ("JPEG", 64, 48)
    img = cv2.imdecode(np.frombuffer(moved, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape[:2] == (48, 64)


def test_a_tiff_directory_at_the_end_of_a_large_file(tmp_path):
    """libtiff-style files put the directory after the pixels: read wherever it points."""
    img = np.zeros((2000, 3000, 3), np.uint8)   # 18 MB uncompressed
    p = tmp_path / "big.tif"
    assert cv2.imwrite(str(p), img, [cv2.IMWRITE_TIFF_COMPRESSION, 1])
    assert image_size(p) == (3000, 2000)
    assert read_image(p).shape == (2000, 3000, 3)


def test_read_image_decodes_as_imread(tmp_path):
    for k, fmt in enumerate(FORMATS):
        p = tmp_path / f"f{k}{fmt[0]}"
        p.write_bytes(_encoded(*fmt, 33, 21, seed=k))
        want = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        got = read_image(p)
        assert got.dtype == want.dtype and np.array_equal(got, want), fmt
        assert np.array_equal(read_image(p, cv2.IMREAD_COLOR),
                              cv2.imread(str(p), cv2.IMREAD_COLOR)), fmt


def test_formats_whose_size_cannot_be_read_first_are_refused(tmp_path):
    p = tmp_path / "x.png"
    p.write_bytes(b"\x00\x00\x00\x0cjP  \r\n\x87\n" + bytes(100))   # JPEG 2000
    with pytest.raises(FrameError, match=r"x\.png: cannot be decoded as an image \(not a PNG, "
                                         r"JPEG, .* or Radiance HDR file\)$"):
        read_image(p)
    p.write_bytes(b"")
    with pytest.raises(FrameError, match=r"cannot be decoded as an image \(empty file\)"):
        read_image(p)


# --------------------------------------------------------------------------- the pixel limit

def test_the_bomb_is_refused_from_its_header(bomb):
    msg = (f"{bomb}: PNG of 30000 x 30000 px is 900000000 pixels, above the limit of "
           f"{MAX_FRAME_PIXELS} ({PIXELS_ENV}); not decoded")
    for read in (image_size, read_image, read_frame):
        with pytest.raises(FrameError) as e:
            read(bomb)
        assert str(e.value) == msg


def test_the_limit_can_be_set_in_the_environment(tmp_path, monkeypatch):
    p = tmp_path / "f.png"
    cv2.imwrite(str(p), np.zeros((40, 50, 3), np.uint8))
    monkeypatch.setenv(PIXELS_ENV, "1999")
    with pytest.raises(FrameError, match=r"2000 pixels, above the limit of 1999"):
        read_frame(p)
    monkeypatch.setenv(PIXELS_ENV, "2000")
    assert read_frame(p).shape == (40, 50, 3)
    for bad in ("0", "-5", "lots", "1e9"):
        monkeypatch.setenv(PIXELS_ENV, bad)
        with pytest.raises(TorchseamError, match=rf"{PIXELS_ENV}=.*whole number") as e:
            read_frame(p)
        assert not isinstance(e.value, FrameError)   # the setting is wrong, not the frame


def test_a_file_larger_than_any_image_within_the_limit(tmp_path, monkeypatch):
    p = tmp_path / "f.png"
    cv2.imwrite(str(p), np.zeros((40, 50, 3), np.uint8))
    with p.open("ab") as fh:
        fh.truncate(17 << 20)   # a 40 x 50 PNG followed by 17 MB of zeros (sparse)
    monkeypatch.setenv(PIXELS_ENV, "2000")
    with pytest.raises(FrameError, match=r"17825792 bytes is larger than an image of at most "
                                         r"2000 pixels can be"):
        read_image(p)


# --------------------------------------------------------------------------- non-regular files

def _non_regular(tmp_path: Path) -> list[tuple[Path, str]]:
    fifo = tmp_path / "fifo.png"
    os.mkfifo(fifo)
    sock_path = tmp_path / "sock.png"
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(sock_path))
    folder = tmp_path / "folder.png"
    folder.mkdir()
    link = tmp_path / "link.png"
    link.symlink_to(fifo)
    return [(fifo, "a FIFO"), (sock_path, "a socket"), (folder, "a folder"),
            (Path("/dev/null"), "a character device"), (link, "a FIFO")]


def test_non_regular_files_are_refused_without_being_opened(tmp_path, monkeypatch):
    opened: list[str] = []
    real_open = os.open

    def spy(path, *a, **kw):
        opened.append(os.fspath(path))
        return real_open(path, *a, **kw)

    monkeypatch.setattr(imageio.os, "open", spy)
    for path, kind in _non_regular(tmp_path):
        for read in (image_size, read_image, read_frame):
            with pytest.raises(FrameError) as e:
                read(path)
            assert str(e.value) == f"{path}: not a regular file ({kind})"
    assert opened == []
    with pytest.raises(FrameError, match=r"nope\.png: no such file$"):
        read_frame(tmp_path / "nope.png")


def test_a_fifo_swapped_in_after_the_check_does_not_block(tmp_path, monkeypatch):
    """The stat check passed (a file was there), then a FIFO took its place: the open is
    non-blocking and the descriptor is checked again."""
    fifo = tmp_path / "f.png"
    os.mkfifo(fifo)
    monkeypatch.setattr(imageio, "regular_file", lambda p: None)
    t0 = time.monotonic()
    with pytest.raises(FrameError, match=r"f\.png: not a regular file \(a FIFO\)"):
        read_image(fifo)
    assert time.monotonic() - t0 < 5


def test_dataset_open_passes_fifos_over_and_refuses_fifo_labels(seq, tmp_path):
    d = _folder(seq, tmp_path / "d", fifo=(0, 2))
    ds = Dataset.open(d, require_labels=True)   # sized from frame 1's header: no block
    assert len(ds) == 8 and ds.labelled.all()
    with pytest.raises(FrameError, match=r"00002\.png: not a regular file \(a FIFO\)"):
        ds.read(2)
    for name in ("labels.csv", "meta.json"):
        e = _folder(seq, tmp_path / f"e_{name}")
        (e / name).unlink()
        os.mkfifo(e / name)
        with pytest.raises(DatasetError, match=rf"{name}: not a regular file \(a FIFO\)"):
            Dataset.open(e, require_labels=True)


# --------------------------------------------------------------------------- each reader

def test_detect_the_bomb_one_line_exit_2_little_memory(bomb):
    res = _measured(["detect", str(bomb)])
    line = _one_line(res, "detect")
    assert res["rc"] == 2 and res["out"] == ""
    assert line.endswith(f"{bomb}: PNG of 30000 x 30000 px is 900000000 pixels, above the limit "
                         f"of {MAX_FRAME_PIXELS} ({PIXELS_ENV}); not decoded")
    print(f"detect on the 30000 x 30000 PNG: peak {res['maxrss_mb']:.0f} MB")
    assert res["maxrss_mb"] < PEAK_MB, res


def test_detect_a_fifo_one_line_exit_2(tmp_path):
    fifo = tmp_path / "f.png"
    os.mkfifo(fifo)
    res = _measured(["detect", str(fifo)], timeout=60)
    assert _one_line(res, "detect").endswith(f"{fifo}: not a regular file (a FIFO)")
    assert res["rc"] == 2


def _statuses(path: Path) -> dict[int, str]:
    return {int(r["frame"]): r["status"] for r in csv.DictReader(path.open())}


def test_track_marks_the_fifo_and_the_bomb_unreadable_and_goes_on(seq, bomb, tmp_path):
    clean = _measured(["track", str(seq), "--out", str(tmp_path / "clean.csv")])
    assert clean["rc"] == 0, clean
    d = _folder(seq, tmp_path / "hostile", fifo=(2,), bombs=(4,), bomb=bomb)
    res = _measured(["track", str(d), "--out", str(tmp_path / "t.csv")])
    assert res["rc"] == 0, res
    status = _statuses(tmp_path / "t.csv")
    assert status[2] == status[4] == "unreadable"
    assert {status[f] for f in (0, 1, 3, 5, 6, 7)} == {"tracked"}
    assert "not a regular file (a FIFO): marked unreadable" in res["err"]
    assert "30000 x 30000 px is 900000000 pixels" in res["err"]
    assert "unreadable 2" in res["out"]
    print(f"track: peak {res['maxrss_mb']:.0f} MB with the bomb, {clean['maxrss_mb']:.0f} MB "
          "without")
    assert res["maxrss_mb"] < clean["maxrss_mb"] + 64, (res, clean)   # never decoded
    # the bomb as the first frame: passed over, the tracker starts on the next one
    first = _folder(seq, tmp_path / "first", bombs=(0,), bomb=bomb)
    res = _measured(["track", str(first), "--out", str(tmp_path / "f.csv")])
    assert res["rc"] == 0 and _statuses(tmp_path / "f.csv")[0] == "unreadable", res


def test_eval_with_a_fifo_and_a_bomb_does_not_hang(seq, bomb, tmp_path):
    d = _folder(seq, tmp_path / "hostile", fifo=(0,), bombs=(4,), bomb=bomb)
    res = _measured(["eval", str(d)])
    assert res["rc"] == 0, res
    assert "2 unreadable, counted lost" in res["out"]


def test_replay_stops_at_the_fifo_or_the_bomb_with_one_line(seq, bomb, tmp_path):
    d = _folder(seq, tmp_path / "fifo", fifo=(2,))
    res = _measured(["replay", str(d)])
    assert res["rc"] == 2
    assert _one_line(res, "replay").endswith(f"frame 2: {d / '00002.png'}: not a regular file "
                                             "(a FIFO)")
    d = _folder(seq, tmp_path / "bomb", bombs=(0,), bomb=bomb)
    res = _measured(["replay", str(d)])
    assert res["rc"] == 2
    assert "frame 0: " in _one_line(res, "replay") and "not decoded" in res["err"]
    assert res["maxrss_mb"] < PEAK_MB + 200, res   # torch and the live stack, no 900 MB image


def _console(args: list[str], timeout: float) -> tuple[int | None, str, str]:
    """``torchseam console ARGS`` until it prints its address (then Ctrl-C) or exits:
    (exit code, stdout, stderr); rc None: neither within ``timeout`` (a hang)."""
    # Ctrl-C as in a terminal: the console starts with SIGINT's default action (a pytest-xdist
    # worker runs with SIGINT ignored, which a child inherits across exec; the console,
    # started so, would rightly go on ignoring it, as a shell's background job does)
    p = subprocess.Popen([sys.executable, "-m", "torchseam", "console", "--port", "0", *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    out = ""
    try:
        end = time.monotonic() + timeout
        while time.monotonic() < end and p.poll() is None:
            ready, _, _ = select.select([p.stdout], [], [], 0.5)
            if ready:
                out += p.stdout.readline()
                if "torchseam console on http://" in out:
                    p.send_signal(signal.SIGINT)
                    break
        else:
            if p.poll() is None:
                p.kill()
                p.wait()
                return None, out, p.stderr.read()
        rest, err = p.communicate(timeout=30)
        return p.returncode, out + rest, err
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_console_source_with_a_fifo(seq, tmp_path):
    # the first frame a FIFO: refused at start, one line
    d = _folder(seq, tmp_path / "first", fifo=(0,))
    rc, out, err = _console(["--source", str(d)], TIMEOUT_S)
    assert rc == 2, (out, err)
    assert err.strip().splitlines() == [
        f"torchseam console: error: frame 0: {d / '00000.png'}: not a regular file (a FIFO)"]
    # a later frame a FIFO: the folder opens (its size read from frame 0's header) and the
    # console serves; a weld stops at the FIFO with its message, as at any broken frame
    d = _folder(seq, tmp_path / "later", fifo=(1, 3))
    rc, out, err = _console(["--source", str(d)], TIMEOUT_S)
    assert rc is not None and "torchseam console on http://" in out, (out, err)


def test_console_source_with_a_bomb(seq, bomb, tmp_path):
    d = _folder(seq, tmp_path / "bomb", bombs=(0,), bomb=bomb)
    rc, out, err = _console(["--source", str(d)], TIMEOUT_S)
    assert rc == 2, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith("pixels, above the limit of "
                                                 f"{MAX_FRAME_PIXELS} ({PIXELS_ENV}); not "
                                                 "decoded"), err


def test_calibration_sets_refuse_a_fifo_and_a_bomb(tmp_path, bomb):
    from torchseam.core.calibration import CalibrationError
    from torchseam.geometry.calibrate import load_camera_set

    cam = tmp_path / "cam"
    cam.mkdir()
    for i in range(3):
        cv2.imwrite(str(cam / f"{i:02d}.png"), np.full((60, 80, 3), 128, np.uint8))
    os.mkfifo(cam / "03.png")
    with pytest.raises(CalibrationError, match=r"03\.png: not a regular file \(a FIFO\)$"):
        load_camera_set(cam)
    (cam / "03.png").unlink()
    (cam / "01.jpg").write_bytes(bomb.read_bytes())   # a PNG named .jpg: sized by content
    with pytest.raises(CalibrationError, match=r"01\.jpg: PNG of 30000 x 30000 px .* not "
                                               r"decoded$"):
        load_camera_set(cam)
    # the command: one line, exit 2, no hang
    os.mkfifo(cam / "00b.png")
    res = _measured(["calibrate", "camera", str(cam)], timeout=60)
    assert res["rc"] == 2
    assert _one_line(res, "calibrate").endswith(f"{cam / '00b.png'}: not a regular file "
                                                "(a FIFO)")
