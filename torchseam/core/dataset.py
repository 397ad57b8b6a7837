"""The dataset format every stage reads: a folder of frames with labels and metadata.

::

    DIR/00000.png ...        frames, numbered from 0 in file-name order (BGR or mono, 8/16 bit)
    DIR/labels.csv           header ``frame,u,v``: the feature pixel of each labelled frame
    DIR/meta.json            optional: calibration, noise level, per-frame 3D truth (simulator)

A real recording needs only the frames and ``labels.csv`` (or only frames, for ``track``).
Every problem is reported with the folder, the file and the row or frame it concerns. Frames
are read through :mod:`torchseam.core.imageio`: a name that is not a regular file (a FIFO, a
socket) is refused without being opened, and an image is sized from its header and refused
above the pixel limit before it is decoded.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from torchseam.core.config import JOINT_PROFILES
from torchseam.core.errors import DatasetError, FrameError
from torchseam.core.imageio import image_size, read_image, regular_file

FRAME_RE = re.compile(r"^(\d+)\.png$")
LABEL_HEADER = ["frame", "u", "v"]


def frame_name(index: int) -> str:
    """File name of frame ``index``: ``00042.png``."""
    return f"{index:05d}.png"


#: bit depths a 16-bit container may carry (machine-vision cameras deliver 10, 12 or 14 bits
#: in the low bits of a 16-bit pixel)
CONTAINER_BITS = (10, 12, 14, 16)
#: smallest image side any stage works on (TIPM's ridge filter and arm fits need more)
MIN_SIDE_PX = 32


def to_8bit(img: np.ndarray, bits: int | None = None) -> np.ndarray:
    """A uint16 image scaled to uint8 by its bit depth ``bits``; None: the smallest of
    ``CONTAINER_BITS`` that holds the image's brightest pixel (a 12-bit camera's frames then
    keep their brightness, instead of ending up 16x darker than an 8-bit camera's).

    Example:
        >>> to_8bit(np.array([[0, 4095]], np.uint16))
        array([[  0, 255]], dtype=uint8)
    """
    if bits is None:
        top = int(img.max(initial=0))
        bits = next((b for b in CONTAINER_BITS if top < (1 << b)), 16)
    shift = bits - 8
    return np.clip(img >> shift if shift > 0 else img, 0, 255).astype(np.uint8)


def check_frame(img: Any, size: tuple[int, int] | None = None, name: str = "frame") -> np.ndarray:
    """Validate a camera frame and bring it to 8 bits.

    Accepted: BGR colour (H, W, 3), or mono (H, W) / (H, W, 1) as most industrial laser
    sensors deliver behind their 650 nm band-pass filter; 8-bit or 16-bit pixels (16-bit ones
    are scaled by :func:`to_8bit`). Returns (H, W, 3) or (H, W) uint8 (a view of ``img`` when
    nothing had to change): colour frames are told apart by their stripe's colour, mono ones
    by brightness alone (see :func:`~torchseam.vision.tipm.red_response`).

    Raises:
        FrameError: naming ``name`` and what is wrong (shape, dtype, too small, wrong size).
    """
    if not isinstance(img, np.ndarray):
        raise FrameError(f"{name}: expected an image array, got {type(img).__name__}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise FrameError(f"{name}: expected a mono (H, W) or BGR (H, W, 3) image, got shape "
                         f"{img.shape}")
    if img.dtype == np.uint16:
        img = to_8bit(img)
    elif img.dtype != np.uint8:
        raise FrameError(f"{name}: expected 8- or 16-bit pixels, got {img.dtype}")
    if min(img.shape[:2]) < MIN_SIDE_PX:
        raise FrameError(f"{name}: image is {img.shape[1]} x {img.shape[0]} px; at least "
                         f"{MIN_SIDE_PX} x {MIN_SIDE_PX} is needed to find a stripe")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise FrameError(f"{name}: frame is {img.shape[1]} x {img.shape[0]} px, the camera "
                         f"is configured for {size[0]} x {size[1]}")
    return img


def read_frame(path: str | os.PathLike[str], size: tuple[int, int] | None = None) -> np.ndarray:
    """Read one frame from disk (colour or mono, 8 or 16 bit), validated and brought to 8 bits
    (see :func:`check_frame`). The file is read by :func:`torchseam.core.imageio.read_image`:
    anything but a regular file is refused without being opened, and an image whose header
    declares more than :func:`~torchseam.core.imageio.max_frame_pixels` pixels without being
    decoded (:class:`FrameError` naming the file)."""
    p = Path(path)
    img = read_image(p, cv2.IMREAD_UNCHANGED)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[..., :3]
    return check_frame(img, size, str(p))


@dataclass
class Dataset:
    """A dataset folder, opened and checked.

    Attributes:
        root: the folder.
        frames: (N,) frame numbers, ascending (from the file names).
        paths: N frame paths in the same order.
        labels: (N, 2) float64 labelled pixels, NaN where a frame has no label; None when the
            folder has no ``labels.csv``.
        meta: parsed ``meta.json`` or None.
        unimaged_labels: frame numbers ``labels.csv`` labels that have no image (a gap in the
            frames, as a dropped camera frame): skipped, with a warning on stderr when opened.

    Example:
        >>> ds = Dataset.open("data/seq0")          # doctest: +SKIP
        >>> img = ds.read(0); ds.labels[0]           # doctest: +SKIP
    """

    root: Path
    frames: np.ndarray
    paths: list[Path]
    labels: np.ndarray | None
    meta: dict[str, Any] | None
    unimaged_labels: np.ndarray = field(default_factory=lambda: np.zeros(0, int))

    @classmethod
    def open(cls, root: str | os.PathLike[str], require_labels: bool = False,
             labels: bool = True) -> Dataset:
        """Open and check ``root``. ``labels=False``: leave ``labels.csv`` unread (``labels``
        is then None), for commands that need none (``track``)."""
        root = Path(root)
        if not root.exists():
            raise DatasetError(f"{root}: no such folder")
        if not root.is_dir():
            raise DatasetError(f"{root}: not a folder of frames (a video or a camera goes "
                               f"through the live loop: torchseam replay {root})")
        found = []
        for p in root.iterdir():
            m = FRAME_RE.match(p.name)
            if m:
                found.append((int(m.group(1)), p))
        if not found:
            raise DatasetError(f"{root}: no frames (expected files named like 00000.png)")
        found.sort()
        frames = np.array([f for f, _ in found])
        dup = frames[np.nonzero(np.diff(frames) == 0)[0]]
        if len(dup):
            raise DatasetError(f"{root}: frame number {dup[0]} appears twice (e.g. 1.png and "
                               "00001.png)")
        paths = [p for _, p in found]
        uv, unimaged = None, np.zeros(0, int)
        lp = root / "labels.csv"
        if not labels:
            pass
        elif lp.exists():
            _regular(lp)
            uv, unimaged = _read_labels(lp, frames, _image_size(paths))
            if len(unimaged):  # a gap in the frames, not an error; never silent
                shown = (", ".join(str(int(f)) for f in unimaged[:10])
                         + (" ..." if len(unimaged) > 10 else ""))
                print(f"warning: {lp}: {len(unimaged)} label(s) of frames with no image "
                      f"skipped (frame {shown}): a gap in the frames, not scored",
                      file=sys.stderr, flush=True)
        elif require_labels:
            raise DatasetError(f"{root}: labels.csv is missing (header: frame,u,v)")
        meta = None
        mp = root / "meta.json"
        if mp.exists():
            _regular(mp)
            try:
                meta = json.loads(mp.read_text())
            except (OSError, ValueError) as e:
                raise DatasetError(f"{mp}: not valid JSON ({e})") from None
        return cls(root, frames, paths, uv, meta, unimaged)

    def joint(self, given: str | None) -> tuple[str, str, str]:
        """``(joint, where it came from, warning)`` to read the frames as: ``given`` (a
        ``--joint``; from '') when given, with a warning when the folder's ``meta.json`` names
        another part joint (``part.joint``, as ``torchseam simulate`` writes it); else that
        joint (from the meta.json's path); else fillet (from ''). The warning is '' or one line
        for stderr."""
        part = self.meta.get("part") if isinstance(self.meta, dict) else None
        named = part.get("joint") if isinstance(part, dict) else None
        named = named if named in JOINT_PROFILES else None
        where = self.root / "meta.json"
        if given is None:
            return (named, str(where), "") if named is not None else ("fillet", "", "")
        if named is not None and named != given:
            return given, "", (f"warning: --joint {given}, but {where} says the part's joint "
                               f"is {named}")
        return given, "", ""

    def __len__(self) -> int:
        return len(self.paths)

    def read(self, i: int, size: tuple[int, int] | None = None) -> np.ndarray:
        """Frame at position ``i`` (not frame number) as validated BGR uint8."""
        return read_frame(self.paths[i], size)

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self.read(i)

    @property
    def missing(self) -> np.ndarray:
        """Frame numbers absent between the first and the last frame (a camera that dropped
        frames, a file lost on the way), ascending; empty when the numbering has no gap."""
        present = np.zeros(int(self.frames[-1] - self.frames[0]) + 1, bool)
        present[self.frames - self.frames[0]] = True
        return np.flatnonzero(~present) + int(self.frames[0])

    @property
    def labelled(self) -> np.ndarray:
        """(N,) bool: which frames carry a label."""
        if self.labels is None:
            return np.zeros(len(self), bool)
        return ~np.isnan(self.labels[:, 0])


def _regular(path: Path) -> None:
    """Refuse ``labels.csv`` / ``meta.json`` that are not regular files before opening them
    (a FIFO would block the read forever)."""
    try:
        regular_file(path)
    except FrameError as e:
        raise DatasetError(str(e)) from None


def _image_size(paths: list[Path]) -> tuple[int, int] | None:
    """The frames' size (width, height): that of the first frame whose header can be read
    (:func:`torchseam.core.imageio.image_size`: a FIFO or other non-regular file is passed
    over without being opened, as is a frame above the pixel limit; the reader marks a frame
    of another size as unreadable)."""
    for p in paths:
        try:
            return image_size(p)
        except FrameError:
            continue
    return None


def _label_value(path: Path, line: int, name: str, cell: str,
                 size: tuple[int, int] | None) -> float:
    """Label field ``name`` (u or v) of ``labels.csv`` line ``line``: a finite number, inside
    the frames of ``size`` (width, height) when known."""
    try:
        x = float(cell)
    except ValueError:
        raise DatasetError(f"{path}: line {line}: {name} {cell!r} is not a number") from None
    if not math.isfinite(x):
        raise DatasetError(f"{path}: line {line}: {name} is {cell!r}")
    if size is not None:
        side = size[0] if name == "u" else size[1]
        if not -0.5 <= x <= side - 0.5:
            raise DatasetError(
                f"{path}: line {line}: {name} {cell.strip()} lies outside the "
                f"{size[0]} x {size[1]} px frames ({name} must be in -0.5 .. {side - 0.5:g})")
    return x


def _read_labels(path: Path, frames: np.ndarray, size: tuple[int, int] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The labels of ``labels.csv`` per frame position (NaN: unlabelled), and the frame
    numbers of label rows with no image (a gap in the frames: skipped; an error when no row
    has an image). ``size``: the frames' (width, height); a label outside them (pixel centres
    on integers, so -0.5 .. W - 0.5) is refused. A UTF-8 byte-order mark (spreadsheet
    programs write one) is skipped."""
    pos = {int(f): i for i, f in enumerate(frames)}
    labels = np.full((len(frames), 2), np.nan)
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as e:
        raise DatasetError(f"{path}: cannot read ({e})") from None
    if not rows or [c.strip() for c in rows[0]] != LABEL_HEADER:
        got = ",".join(rows[0]) if rows else "an empty file"
        raise DatasetError(f"{path}: header must be 'frame,u,v', got {got!r}")
    seen: set[int] = set()
    unimaged: dict[int, int] = {}  # frame -> first line
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != 3:
            raise DatasetError(f"{path}: line {line}: expected 3 fields frame,u,v, got {len(row)}")
        try:
            f = int(row[0])
        except ValueError:
            raise DatasetError(f"{path}: line {line}: frame {row[0]!r} is not a whole number"
                               ) from None
        vals = [_label_value(path, line, name, cell, size)
                for name, cell in zip(("u", "v"), row[1:], strict=True)]
        if f in seen or f in unimaged:
            raise DatasetError(f"{path}: line {line}: frame {f} is labelled twice")
        if f not in pos:
            unimaged[f] = line
            continue
        seen.add(f)
        labels[pos[f]] = vals
    if not seen:
        if unimaged:
            f, line = next(iter(unimaged.items()))
            raise DatasetError(f"{path}: no label names a frame in the folder (line {line}: "
                               f"frame {f} has no image {frame_name(f)})")
        raise DatasetError(f"{path}: no labels below the header")
    return labels, np.array(sorted(unimaged), int)


def write_labels(path: str | os.PathLike[str], frames: np.ndarray, uv: np.ndarray) -> None:
    """Write ``labels.csv`` (frame,u,v) with 4 decimals; rows with NaN are left out."""
    with Path(path).open("w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(LABEL_HEADER)
        for f, (u, v) in zip(frames, uv, strict=True):
            if np.isfinite(u) and np.isfinite(v):
                wr.writerow([int(f), f"{u:.4f}", f"{v:.4f}"])
