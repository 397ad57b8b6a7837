"""Write simulated sequences in the dataset format, and preview contact sheets."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from torchseam.core.config import CellConfig, NoiseConfig, PartConfig, to_dict
from torchseam.core.dataset import frame_name, write_labels
from torchseam.core.errors import DatasetError
from torchseam.core.overlay import put_label
from torchseam.core.transforms import matrix_to_quat
from torchseam.sim.names import CAMERAS
from torchseam.sim.sequence import FrameTruth, SequenceSpec, simulate
from torchseam.sim.variants import to_mono

FORMAT = "torchseam-dataset/1"


def pose_dict(T: np.ndarray) -> dict[str, list[float]]:
    """4x4 pose -> {position_mm, quaternion (w, x, y, z)} for JSON."""
    return {"position_mm": [round(float(x), 6) for x in T[:3, 3]],
            "quaternion": [round(float(x), 9) for x in matrix_to_quat(T[:3, :3])]}


def truth_dict(t: FrameTruth) -> dict[str, Any]:
    return {
        "frame": t.index, "t_s": round(t.t_s, 6),
        "u": float(t.uv[0]), "v": float(t.uv[1]),
        "visible": bool(t.visible), "laser_on": bool(t.laser_on), "arc_on": bool(t.arc_on),
        "seam_mm": [float(x) for x in t.seam_B],
        "arms_mm": [[float(x) for x in p] for p in t.arm_B],
        "arms_uv": [[float(x) for x in p] for p in t.arm_uv],
        "camera_pose": pose_dict(t.T_B_C), "tcp_pose": pose_dict(t.T_B_W),
        "arc_uv": [float(x) for x in t.arc_uv],
        "noise": dataclasses.asdict(t.flags),
    }


def write_sequence(out: str | os.PathLike[str], cell: CellConfig, part: PartConfig,
                   noise: NoiseConfig, spec: SequenceSpec, noise_name: str | None = None,
                   progress: bool = True, overwrite: bool = False,
                   camera: str = "colour") -> list[FrameTruth]:
    """Simulate ``spec`` and write it to ``out`` (frames, labels.csv, meta.json).

    ``camera``: ``colour`` (BGR, as rendered), ``mono`` or ``mono16`` (the single channel a
    camera behind the 650 nm band-pass gives, 8 or 16 bit: :func:`~torchseam.sim.variants.to_mono`).
    Returns the per-frame truths. Refuses to write into a folder that already holds frames
    unless ``overwrite``.
    """
    if camera not in CAMERAS:
        raise ValueError(f"camera {camera!r}: use one of {', '.join(CAMERAS)}")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    old = sorted(out.glob("[0-9]*.png"))
    if old and not overwrite:
        raise DatasetError(f"{out}: already holds {len(old)} frames (use --overwrite)")
    for p in old:
        p.unlink()
    truths = []
    it = simulate(cell, part, noise, spec)
    bar = tqdm(it, total=spec.n_frames, desc=f"simulate {out.name}", unit="frame",
               disable=not progress, leave=False)
    try:
        for img, truth in bar:
            if camera != "colour":  # its sensor noise seeded by the sequence and the frame
                img = to_mono(img, bits=16 if camera == "mono16" else 8,
                              rng=np.random.default_rng((spec.seed, truth.index)))
            if not cv2.imwrite(str(out / frame_name(truth.index)), img):
                raise DatasetError(f"{out / frame_name(truth.index)}: could not be written")
            truths.append(truth)
    except KeyboardInterrupt:
        # the frames written so far stay a dataset: with their labels and meta.json (a frame
        # whose truth was not kept yet is removed), then the interrupt goes on
        for p in out.glob("[0-9]*.png"):
            if p.stem.isdigit() and int(p.stem) >= len(truths):
                p.unlink()
        _write_index(out, truths, cell, part, noise, spec, noise_name, camera)
        raise
    _write_index(out, truths, cell, part, noise, spec, noise_name, camera)
    return truths


def _write_index(out: Path, truths: list[FrameTruth], cell: CellConfig, part: PartConfig,
                 noise: NoiseConfig, spec: SequenceSpec, noise_name: str | None,
                 camera: str) -> None:
    """labels.csv and meta.json of the frames ``truths`` written to ``out``."""
    uv = np.array([t.uv for t in truths]).reshape(-1, 2)
    write_labels(out / "labels.csv", np.arange(len(truths)), uv)
    meta = {
        "format": FORMAT,
        "source": "torchseam simulator",
        "camera": camera,
        "noise": {"level": spec.level, "name": noise_name, "seed": spec.seed,
                  "clean_lead_frames": noise.clean_lead_frames},
        "sequence": {"n_frames": len(truths), "start_mm": spec.start_mm,
                     "rotation_deg": spec.rotation_deg, "laser_off": list(spec.laser_off)},
        "cell": to_dict(cell), "part": to_dict(part),
        "frames": [truth_dict(t) for t in truths],
    }
    (out / "meta.json").write_text(json.dumps(meta, indent=1))


def contact_sheet(frames: list[np.ndarray], points: list[np.ndarray | None],
                  captions: list[str], cols: int = 4, scale: float = 0.5) -> np.ndarray:
    """Tile frames (BGR) with a green cross on each point and a caption, into one image."""
    tiles = []
    for img, p, cap in zip(frames, points, captions, strict=True):
        t = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        if p is not None and np.all(np.isfinite(p)):
            c = (int(round(p[0] * scale)), int(round(p[1] * scale)))
            cv2.drawMarker(t, c, (0, 255, 0), cv2.MARKER_CROSS, 14, 1, cv2.LINE_AA)
            cv2.circle(t, c, 7, (0, 255, 0), 1, cv2.LINE_AA)
        put_label(t, cap, (6, 16), 0.45)
        tiles.append(t)
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + cols], axis=1) for i in range(0, len(tiles), cols)]
    return np.concatenate(rows, axis=0)
