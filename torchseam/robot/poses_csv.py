"""The torch-pose CSV format that ``torchseam robot check`` reads, and its one writer.

A header row ``t,x,y,z,q1,q2,q3,q4`` (``t`` optional), then one row per pose in path order: the
time stamp (s), the torch TCP position in the robot base frame (mm) and its orientation as an
ABB quaternion ``q1..q4 = w, x, y, z``. ``torchseam plan --out`` and
:func:`torchseam.live.ring.write_ring_poses` write it with :func:`write_pose_csv`;
:func:`torchseam.robot.cli.read_pose_csv` reads it.

Example:
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "poses.csv"
    >>> _ = write_pose_csv(path, np.array([[900.0, 0, 500]]), np.array([[0.0, 1, 0, 0]]), [0.0])
    >>> path.read_text().splitlines()[0]
    't,x,y,z,q1,q2,q3,q4'
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["CSV_COLUMNS", "TIME_COLUMN", "write_pose_csv"]

#: Required columns of a pose CSV (``t`` is optional).
CSV_COLUMNS = ("x", "y", "z", "q1", "q2", "q3", "q4")
#: The optional time-stamp column (seconds).
TIME_COLUMN = "t"


def write_pose_csv(path: str | Path, position_mm: np.ndarray, quaternion: np.ndarray,
                   t_s: np.ndarray | list[float] | None = None) -> Path:
    """Write torch TCP poses as a pose CSV that ``torchseam robot check`` reads unchanged.

    Args:
        path: the file to write (its folder must exist).
        position_mm: (N, 3) TCP positions in the robot base frame, mm.
        quaternion: (N, 4) orientations, w x y z (normalised here; signs kept as given).
        t_s: (N,) time stamps in seconds, not decreasing; None leaves the ``t`` column out
            (``robot check`` then times the poses by the TCP distance at the weld speed).

    Returns:
        ``path``.

    Raises:
        ValueError: wrong shapes, values that are not finite, a zero quaternion, time going
            backwards.
    """
    p = np.asarray(position_mm, dtype=float).reshape(-1, 3)
    q = np.asarray(quaternion, dtype=float)
    if q.shape != (len(p), 4):
        raise ValueError(f"quaternion: expected shape ({len(p)}, 4), got {q.shape}")
    cols = [p, q]
    if t_s is not None:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if t.shape != (len(p),):
            raise ValueError(f"t_s: expected {len(p)} time stamps, got {t.shape[0]}")
        if (np.diff(t) < 0).any():
            raise ValueError("t_s: time goes backwards")
        cols.insert(0, t[:, None])
    if not all(np.isfinite(c).all() for c in cols):
        raise ValueError("poses: every value must be finite")
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if (norm < 1e-9).any():
        raise ValueError("quaternion: a zero quaternion is no orientation")
    q = q / norm
    header = ([TIME_COLUMN] if t_s is not None else []) + list(CSV_COLUMNS)
    lines = [",".join(header)]
    for i in range(len(p)):
        row = [f"{cols[0][i, 0]:.4f}"] if t_s is not None else []
        row += [f"{v:.4f}" for v in p[i]] + [f"{v:.9f}" for v in q[i]]
        lines.append(",".join(row))
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path
