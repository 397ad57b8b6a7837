"""The one pose-CSV format of the project, its one reader and its one writer.

Robot poses travel between the tools and the user as CSV: the torch path that ``torchseam plan
--out``, ``torchseam demo`` and ``torchseam ring`` write and ``torchseam robot check`` reads, and
the flange poses of a hand-eye or TCP calibration set that the user notes from the controller
(``torchseam calibrate simulate`` writes them for a simulated set). One format for all, so a file
written by one tool is read by every other and the checks (and their messages) are the same.

Format: a header row naming the columns, in any order, then one row per pose in path order.

* ``x,y,z,q1,q2,q3,q4`` (required): position in mm and orientation as an ABB quaternion
  ``q1..q4 = w, x, y, z`` (a robtarget as the controller shows it). Which pose (torch TCP or
  flange, in the robot base) is the caller's to say.
* ``t`` (optional): the pose's time stamp in s, not decreasing.
* a label column (optional; a caller may require one): a name per pose, e.g. ``image`` (the
  image taken at the pose) in a hand-eye set, ``pose`` in a TCP set.

Header names are matched without case or surrounding blanks; other columns are ignored, blank
lines and lines starting with ``#`` skipped. For the calibration files users recorded before
this format, the reader also takes the old spellings ``x_mm,y_mm,z_mm,qw,qx,qy,qz`` for
``x,y,z,q1,q2,q3,q4`` (:data:`ALIASES`); the writer writes the one spelling only: ``image,x,y,
z,q1,q2,q3,q4`` for a calibration set, ``t,x,y,z,q1,q2,q3,q4`` for a path.

Every problem a file can have (unreadable, empty, a missing column, a wrong number of fields, a
value that is not a finite number, a quaternion whose norm is not 1, time going backwards) is a
:class:`PoseFileError` naming the file, the line and the field: the command line prints it as
one line.

Example:
    >>> import tempfile, numpy as np
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "poses.csv"
    >>> _ = write_pose_csv(path, np.array([[900.0, 0, 500]]), np.array([[0.0, 1, 0, 0]]), [0.0])
    >>> path.read_text().splitlines()[0]
    't,x,y,z,q1,q2,q3,q4'
    >>> poses = read_pose_csv(path)
    >>> poses.T[0, :3, 3], poses.t
    (array([900.,   0., 500.]), array([0.]))
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchseam.core.errors import TorchseamError

__all__ = ["ALIASES", "POSE_COLUMNS", "TIME_COLUMN", "PoseFile", "PoseFileError",
           "read_pose_csv", "write_pose_csv"]

#: The required columns: position (mm), then the ABB quaternion w, x, y, z.
POSE_COLUMNS = ("x", "y", "z", "q1", "q2", "q3", "q4")
#: The optional time-stamp column (s, not decreasing).
TIME_COLUMN = "t"
#: Old spellings the reader also accepts (the calibration sets' former header), old -> new.
ALIASES = {"x_mm": "x", "y_mm": "y", "z_mm": "z", "qw": "q1", "qx": "q2", "qy": "q3", "qz": "q4"}
#: How far a quaternion's norm may be from 1 (the file's rounding), before it is refused.
NORM_TOLERANCE = 1e-3


class PoseFileError(TorchseamError, ValueError):
    """A pose CSV cannot be read: the message names the file, the line and the field."""


@dataclass(frozen=True)
class PoseFile:
    """What :func:`read_pose_csv` read, in file order.

    Attributes:
        T: (N, 4, 4) poses, mm (quaternions normalised).
        t: (N,) time stamps in s, or None when the file has no ``t`` column.
        labels: the label column's N values when the caller asked for one, else None.
    """

    T: np.ndarray
    t: np.ndarray | None
    labels: list[str] | None


def _expected(label: str | None) -> str:
    return ",".join(([label] if label else []) + list(POSE_COLUMNS)) + (
        "" if label else f"[,{TIME_COLUMN}]")


def read_pose_csv(path: str | Path, label: str | None = None) -> PoseFile:
    """Poses from a pose CSV (module docstring; old ``x_mm..qz`` spellings accepted).

    Args:
        path: the file.
        label: the label column the caller requires (e.g. ``"image"``), or None for none.

    Returns:
        The poses, their time stamps when the file has ``t``, their labels when asked for.

    Raises:
        PoseFileError: the file cannot be read, is empty or holds a header only; the header lacks
            a column or names one twice; a row has another number of fields than the header; a
            value is not a finite number or a label is empty; a quaternion's norm is not 1
            (within 1e-3); ``t`` decreases -- naming the file, the line and the field.
    """
    # here, not at the top: transforms pulls in scipy (half a second), and the command modules
    # that import this one at start-up (``torchseam robot --help``) should not wait for it
    from torchseam.core.transforms import pose_matrix

    path = Path(path)
    (header_no, header), *rows = _rows(path, label)
    spelled, where = _columns(path, header_no, header, label)
    numeric = list(POSE_COLUMNS) + ([TIME_COLUMN] if TIME_COLUMN in where else [])
    data, labels = [], []
    for line_no, row in rows:
        if len(row) != len(spelled):
            raise PoseFileError(f"{path}: line {line_no}: expected {len(spelled)} fields, "
                                f"got {len(row)}")
        values = [_number(f"{path}: line {line_no}: field {spelled[where[c]]!r}",
                          row[where[c]].strip()) for c in numeric]
        norm = math.sqrt(sum(x * x for x in values[3:7]))
        if abs(norm - 1.0) > NORM_TOLERANCE:
            q = [spelled[where[c]] for c in POSE_COLUMNS[3:]]
            raise PoseFileError(f"{path}: line {line_no}: quaternion {q[0]}..{q[3]} has norm "
                                f"{norm:.6f} (must be 1; order w, x, y, z)")
        if label:
            name = row[where[label.lower()]].strip()
            if not name:
                raise PoseFileError(f"{path}: line {line_no}: field "
                                    f"{spelled[where[label.lower()]]!r}: empty")
            labels.append(name)
        data.append(values)
    if not data:
        raise PoseFileError(f"{path}: header only, no poses")
    arr = np.asarray(data)
    T = pose_matrix(arr[:, :3], arr[:, 3:7] / np.linalg.norm(arr[:, 3:7], axis=1, keepdims=True))
    t = arr[:, 7] if TIME_COLUMN in where else None
    if t is not None and (np.diff(t) < 0).any():
        i = int(np.flatnonzero(np.diff(t) < 0)[0]) + 1
        raise PoseFileError(f"{path}: line {rows[i][0]}: field "
                            f"{spelled[where[TIME_COLUMN]]!r}: time goes backwards "
                            f"({t[i - 1]:g} -> {t[i]:g})")
    return PoseFile(T, t, labels if label else None)


def _rows(path: Path, label: str | None) -> list[tuple[int, list[str]]]:
    """The file's CSV rows with their line numbers, blank and ``#`` lines left out; at least
    the header."""
    try:
        text = path.read_text(encoding="utf-8-sig")  # a spreadsheet's byte-order mark dropped
    except OSError as e:
        raise PoseFileError(f"{path}: cannot read ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise PoseFileError(f"{path}: not a text file (expected a CSV with a header row "
                            f"{_expected(label)})") from None
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines())
             if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise PoseFileError(f"{path}: no header and no poses (expected a header row "
                            f"{_expected(label)})")
    rows = csv.reader(ln for _, ln in lines)
    return [(no, row) for (no, _), row in zip(lines, rows, strict=True)]


def _columns(path: Path, line_no: int, header: list[str],
             label: str | None) -> tuple[list[str], dict[str, int]]:
    """The header as the file spells it (for the messages) and each column's index by its name
    in the one spelling (lower case, old spellings mapped by :data:`ALIASES`)."""
    spelled = [h.strip() for h in header]
    where: dict[str, int] = {}
    for i, h in enumerate(spelled):
        name = ALIASES.get(h.lower(), h.lower())
        if name in where:
            raise PoseFileError(f"{path}: line {line_no}: column {name!r} given twice "
                                f"({spelled[where[name]]!r} and {h!r})")
        where[name] = i
    want = ([label.lower()] if label else []) + list(POSE_COLUMNS)
    missing = [c for c in want if c not in where]
    if missing:
        raise PoseFileError(f"{path}: line {line_no}: header lacks column(s) "
                            f"{', '.join(missing)} (expected {_expected(label)})")
    return spelled, where


def _number(where: str, raw: str) -> float:
    """``raw`` as a finite float; else a :class:`PoseFileError` starting with ``where``."""
    try:
        v = float(raw)
    except ValueError:
        raise PoseFileError(f"{where}: not a number ({raw!r})") from None
    if not math.isfinite(v):
        raise PoseFileError(f"{where}: not finite ({raw})")
    return v


def write_pose_csv(path: str | Path, position_mm: np.ndarray, quaternion: np.ndarray,
                   t_s: np.ndarray | Sequence[float] | None = None, *,
                   label: str | None = None, labels: Sequence[str] | None = None) -> Path:
    """Write poses as a pose CSV that :func:`read_pose_csv` (and so every command) reads.

    The header is ``[LABEL,][t,]x,y,z,q1,q2,q3,q4``; mm, s and positions to 1e-6, quaternions
    to 1e-9 (the readers' rounding stays far below the calibrations' and the gate's tolerances).

    Args:
        path: the file to write (its folder must exist).
        position_mm: (N, 3) positions, mm.
        quaternion: (N, 4) orientations, w x y z (normalised here; signs kept as given).
        t_s: (N,) time stamps in s, not decreasing; None leaves the ``t`` column out
            (``robot check`` then times the poses by the TCP distance at the weld speed).
        label: the label column's name (e.g. ``"image"``), given with ``labels``.
        labels: (N,) the label of each pose (non-empty, not starting with ``#``).

    Returns:
        ``path``.

    Raises:
        ValueError: wrong shapes, values that are not finite, a zero quaternion, time going
            backwards, a label column without labels (or labels without a column name), an
            empty label or one starting with ``#`` (the reader would skip its row).
    """
    p = np.asarray(position_mm, dtype=float).reshape(-1, 3)
    q = np.asarray(quaternion, dtype=float)
    if q.shape != (len(p), 4):
        raise ValueError(f"quaternion: expected shape ({len(p)}, 4), got {q.shape}")
    if (label is None) != (labels is None):
        raise ValueError("label and labels: give both (the column's name and its values) or "
                         "neither")
    names = [str(s) for s in labels] if labels is not None else []
    if label is not None and len(names) != len(p):
        raise ValueError(f"labels: expected {len(p)} labels, got {len(names)}")
    bad = [n for n in names if not n.strip() or n.lstrip().startswith("#")]
    if bad:  # the reader would find no label, or skip the row as a comment
        raise ValueError(f"labels: {bad[0]!r}: a label must be non-empty and not start with #")
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
    header = (([label] if label is not None else []) + ([TIME_COLUMN] if t_s is not None else [])
              + list(POSE_COLUMNS))
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for i in range(len(p)):
        row = [names[i]] if label is not None else []
        row += [f"{cols[0][i, 0]:.6f}"] if t_s is not None else []
        row += [f"{v:.6f}" for v in p[i]] + [f"{v:.9f}" for v in q[i]]
        w.writerow(row)
    path = Path(path)
    path.write_text(buf.getvalue())
    return path
