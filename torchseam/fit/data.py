"""Training data: labelled sequences in the dataset format, as red-response crops in memory.

A sequence is any dataset folder (``00000.png ...`` + ``labels.csv``, see
:mod:`torchseam.core.dataset`): a real recording or a simulated one. ``--data`` names one such
folder or a folder of them. :func:`generate_sequences` writes simulated ones into a cache folder.

What the tracker trains on: each frame becomes the red-stripe response ``R - max(G, B)``
(:func:`torchseam.vision.tipm.red_response`, the grey image the trackers see, uint8) and each
sequence is cropped to one fixed square ROI (``roi`` px, default 256) placed on the centre of its
label track; the ROI grows (for every sequence alike, in steps of 16 px) when a label track plus
``margin`` on each side does not fit. Memory: 64 sequences x 300 full 656 x 492 frames would be
6.2 GB even as uint8; 256 px crops are 1.26 GB (0.25 GB for 32 x 150). Parts of the ROI outside
the image replicate the border pixels, which is what the tracker's window crop does at the image
border, so the tracker sees the same pixels in the crop as in the full frame as long as its
64 px context window stays inside the ROI (``margin`` >= half the window plus the expected
drift).

The crops are cached as ``.npy`` files (``<cache>/crops/``, keyed on the folder, its files'
sizes and times and the crop settings) and memory-mapped, so re-runs, resumed runs and several
torchrun processes share them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from torchseam.core.config import load_cell, load_noise, load_part
from torchseam.core.dataset import FRAME_RE, Dataset
from torchseam.core.errors import DatasetError
from torchseam.vision.tipm import red_response

__all__ = ["SequenceSet", "find_sequences", "generate_sequences", "load_sequences",
           "sequence_group"]

log = logging.getLogger("torchseam.fit")

CACHE_VERSION = 1
ROI_STEP = 16


@dataclass
class SequenceSet:
    """Labelled sequences as red-response crops.

    Attributes:
        frames: per sequence a (T_i, S, S) uint8 array (memory-mapped from the cache).
        labels: per sequence (T_i, 2) float32 feature points in crop pixels, NaN = unlabelled;
            frame 0 is always labelled (sequences start at their first labelled frame).
        origin: (N, 2) int crop origin (u0, v0) in the full frame (label = crop label + origin).
        names: folder of each sequence.
        groups: noise level name of each sequence (from ``meta.json``; ``"data"`` for a
            recording without one): the validation tables are per group.
        roi: S.
    """

    frames: list[np.ndarray]
    labels: list[np.ndarray]
    origin: np.ndarray
    names: list[str]
    groups: list[str]
    roi: int

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def lengths(self) -> np.ndarray:
        return np.array([len(f) for f in self.frames])

    def subset(self, idx: Sequence[int]) -> SequenceSet:
        idx = list(idx)
        return SequenceSet([self.frames[i] for i in idx], [self.labels[i] for i in idx],
                           self.origin[idx], [self.names[i] for i in idx],
                           [self.groups[i] for i in idx], self.roi)

    def batch(self, idx: Sequence[int], T: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Frames (B, T, S, S) uint8 and labels (B, T, 2) float32 of sequences ``idx``, padded
        to ``T`` frames (default: the longest one; padding repeats the last frame, its labels
        are NaN)."""
        idx = list(idx)
        T = max(len(self.frames[i]) for i in idx) if T is None else T
        S = self.roi
        fr = np.empty((len(idx), T, S, S), np.uint8)
        lab = np.full((len(idx), T, 2), np.nan, np.float32)
        for j, i in enumerate(idx):
            n = len(self.frames[i])
            fr[j, :n] = self.frames[i]
            fr[j, n:] = self.frames[i][n - 1]
            lab[j, :n] = self.labels[i]
        return fr, lab

    def describe(self) -> str:
        counts: dict[str, int] = {}
        for g in self.groups:
            counts[g] = counts.get(g, 0) + 1
        return (f"{len(self)} sequences ({', '.join(f'{g} {n}' for g, n in counts.items())}), "
                f"{int(self.lengths.sum())} frames, ROI {self.roi} px")


def _has_frames(d: Path) -> bool:
    try:
        return any(FRAME_RE.match(p.name) for p in d.iterdir())
    except OSError:
        return False


def find_sequences(root: str | os.PathLike[str]) -> list[Path]:
    """Sequence folders under ``root``: ``root`` itself when it holds frames, else its
    sub-folders that do (sorted by name).

    Raises:
        DatasetError: ``root`` is missing, not a folder, or holds no sequence.
    """
    root = Path(root)
    if not root.exists():
        raise DatasetError(f"{root}: no such folder (expected labelled sequences: frames "
                           "00000.png ... and labels.csv, in the folder or in sub-folders)")
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder")
    if _has_frames(root):
        return [root]
    subs = sorted(d for d in root.iterdir() if d.is_dir() and _has_frames(d))
    if not subs:
        raise DatasetError(f"{root}: no sequences (expected frames 00000.png ... and "
                           "labels.csv in the folder or in its sub-folders)")
    return subs


def sequence_group(meta: dict | None) -> str:
    """Noise level name of a sequence from its ``meta.json`` (``"data"`` without one)."""
    if not meta:
        return "data"
    noise = meta.get("noise") or {}
    if noise.get("name"):
        return str(noise["name"])
    if noise.get("level") is not None:
        return f"level {float(noise['level']):g}"
    return "data"


def _level_folder(name: str, level: float) -> str:
    return name if name.isidentifier() else f"level{level:g}"


def generate_sequences(cache: str | os.PathLike[str], levels: Sequence[str],
                       seeds: Sequence[int], n_frames: int, *, cell: str | None = None,
                       part: str | None = None, noise_model: str | None = None,
                       progress: bool = True, families: Sequence[str] = ("sim",)
                       ) -> list[Path]:
    """Simulate one sequence per (family, level, seed) into ``cache/<level>-s<seed>`` (family
    ``sim``) or ``cache/<family>-<level>-s<seed>`` (dataset format).

    A folder already holding a finished sequence of the same level, seed and length is reused.

    Returns:
        The folders, level by level, seed by seed.
    """
    from torchseam.sim.record import write_sequence
    from torchseam.sim.sequence import SequenceSpec

    if n_frames < 2:
        raise DatasetError(f"frames: a training sequence needs at least 2 frames, got {n_frames}")
    cache = Path(cache)
    cell_c, part_c, noise_c = load_cell(cell), load_part(part), load_noise(noise_model)
    jobs = []
    for fam in families:
        for name in levels:
            try:
                level = noise_c.level(name)
            except ValueError as e:
                raise DatasetError(f"levels: {e}") from None
            for s in seeds:
                head = "" if fam == "sim" else f"{fam}-"
                jobs.append((fam, name, level, s,
                             cache / f"{head}{_level_folder(name, level)}-s{s:05d}"))
    out = []
    todo = [j for j in jobs if not _finished(j[4], j[2], j[3], n_frames)]
    bar = tqdm(total=len(todo) * n_frames, desc="simulate", unit="frame",
               disable=not progress or not todo)
    for fam, name, level, s, d in jobs:
        if (fam, name, level, s, d) in todo:
            spec = SequenceSpec(n_frames=n_frames, level=level, seed=s, family=fam)
            (d / "meta.json").unlink(missing_ok=True)
            write_sequence(d, cell_c, part_c, noise_c, spec,
                           name if name in noise_c.levels else None, progress=False,
                           overwrite=True)
            bar.update(n_frames)
        out.append(d)
    bar.close()
    return out


def _finished(d: Path, level: float, seed: int, n_frames: int) -> bool:
    mp = d / "meta.json"
    if not mp.is_file():
        return False
    try:
        meta = json.loads(mp.read_text())
        noise, seq = meta["noise"], meta["sequence"]
        return (seq["n_frames"] == n_frames and noise["seed"] == seed
                and abs(float(noise["level"]) - level) < 1e-9)
    except (OSError, ValueError, KeyError, TypeError):
        return False


# --------------------------------------------------------------------------- crops

@dataclass
class _Plan:
    ds: Dataset
    first: int          # first labelled frame (the start)
    n: int              # frames used
    labels: np.ndarray  # (n, 2) full-frame labels
    group: str


def _plan(d: Path, max_frames: int) -> _Plan:
    ds = Dataset.open(d, require_labels=True)
    assert ds.labels is not None
    lab = ds.labelled
    first = int(np.argmax(lab))
    n = len(ds) - first
    if max_frames:
        n = min(n, max_frames)
    if n < 2:
        raise DatasetError(f"{d}: needs at least 2 frames from the first labelled one "
                           f"(frame {int(ds.frames[first])}), has {n}")
    labels = ds.labels[first:first + n].astype(np.float32)
    return _Plan(ds, first, n, labels, sequence_group(ds.meta))


def _needed_side(labels: np.ndarray, margin: int) -> int:
    ok = np.isfinite(labels[:, 0])
    ext = np.ptp(labels[ok], axis=0).max() if ok.any() else 0.0
    return int(np.ceil(ext + 2 * margin + 1))


def _cache_key(p: _Plan, roi: int, margin: int) -> str:
    h = hashlib.sha1()
    files = [p.ds.root / "labels.csv", *p.ds.paths[p.first:p.first + p.n]]
    h.update(f"v{CACHE_VERSION} {p.ds.root.resolve()} {p.first} {p.n} {roi} {margin}".encode())
    for f in (files[0], files[1], files[-1]):
        st = f.stat()
        h.update(f"{f.name} {st.st_size} {st.st_mtime_ns}".encode())
    return h.hexdigest()[:20]


def _crop_sequence(p: _Plan, roi: int, origin: np.ndarray, out: np.ndarray,
                   tick: Callable[[], None]) -> None:
    u0, v0 = (int(x) for x in origin)
    for k in range(p.n):
        red = red_response(p.ds.read(p.first + k))
        h, w = red.shape
        top, left = max(0, -v0), max(0, -u0)
        bottom, right = max(0, v0 + roi - h), max(0, u0 + roi - w)
        if top or left or bottom or right:  # ROI beyond the image: replicate the border
            red = cv2.copyMakeBorder(red, top, bottom, left, right, cv2.BORDER_REPLICATE)
        out[k] = red[v0 + top:v0 + top + roi, u0 + left:u0 + left + roi]
        tick()


def load_sequences(dirs: Sequence[str | os.PathLike[str]], roi: int = 256, margin: int = 48,
                   max_frames: int = 0, cache: str | os.PathLike[str] | None = None,
                   progress: bool = True, build: bool = True) -> SequenceSet:
    """Read labelled sequences as red-response crops (see the module docstring).

    Args:
        dirs: sequence folders (:func:`find_sequences`).
        roi: crop side (px); grows in steps of 16 px for every sequence when a label track
            plus ``margin`` does not fit.
        margin: px kept around each label track.
        max_frames: use at most this many frames per sequence (0: all).
        cache: crop cache folder (None: no cache, crops held in memory).
        progress: tqdm bar while cropping.
        build: when False, a crop missing from the cache raises instead of being built (the
            other torchrun processes wait for rank 0 to build the cache, then load it).

    Raises:
        DatasetError: missing/empty/mislabelled folders (the message names folder and line).
    """
    if not dirs:
        raise DatasetError("no sequences to load")
    plans = [_plan(Path(d), max_frames) for d in dirs]
    need = max(_needed_side(p.labels, margin) for p in plans)
    side = max(roi, int(np.ceil(need / ROI_STEP) * ROI_STEP))
    if side > roi:
        log.info("ROI %d px does not hold every label track with %d px margin: using %d px",
                 roi, margin, side)
    cdir = Path(cache) / "crops" if cache is not None else None
    if cdir is not None:
        cdir.mkdir(parents=True, exist_ok=True)
    frames, labels, origins = [], [], []
    todo = []
    for p in plans:
        ok = np.isfinite(p.labels[:, 0])
        centre = 0.5 * (p.labels[ok].min(axis=0) + p.labels[ok].max(axis=0))
        origin = np.floor(centre - (side - 1) / 2.0 + 0.5).astype(int)
        origins.append(origin)
        labels.append(p.labels - origin.astype(np.float32))
        if cdir is not None:
            f = cdir / f"{_cache_key(p, side, margin)}.npy"
            if f.is_file():
                try:
                    arr = np.load(f, mmap_mode="r")
                    if arr.shape == (p.n, side, side) and arr.dtype == np.uint8:
                        frames.append(arr)
                        continue
                except (OSError, ValueError):
                    pass
            if not build:
                raise DatasetError(f"{f}: crop cache missing (rank 0 builds it first)")
        frames.append(None)
        todo.append(len(frames) - 1)
    bar = tqdm(total=sum(plans[i].n for i in todo), desc="crop", unit="frame",
               disable=not progress or not todo)
    for i in todo:
        p = plans[i]
        arr = np.empty((p.n, side, side), np.uint8)
        _crop_sequence(p, side, origins[i], arr, lambda: bar.update(1))
        if cdir is not None:
            f = cdir / f"{_cache_key(p, side, margin)}.npy"
            tmp = f.with_suffix(f".tmp{os.getpid()}.npy")
            np.save(tmp, arr)
            os.replace(tmp, f)
            arr = np.load(f, mmap_mode="r")
        frames[i] = arr
    bar.close()
    return SequenceSet(frames=frames, labels=labels, origin=np.array(origins).reshape(-1, 2),
                       names=[str(p.ds.root) for p in plans], groups=[p.group for p in plans],
                       roi=side)
