"""The one pose-CSV format (issue 27 item 3): what the writer writes the reader reads, with and
without time stamps and labels; the calibration sets' old header is still read; every bad file
gives one message naming the file, the line and the field; the writer refuses what the reader
would."""

from __future__ import annotations

import doctest

import numpy as np
import pytest

import torchseam.core.poses_csv
from torchseam.core.poses_csv import PoseFileError, read_pose_csv, write_pose_csv
from torchseam.core.transforms import matrix_to_quat

P = np.array([[900.0, 0.0, 500.0], [902.5, -1.25, 500.125], [905.0, -2.5, 499.75]])
Q = np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.6, 0.8, 0.0], [0.5, 0.5, 0.5, 0.5]])


def check_poses(T: np.ndarray) -> None:
    np.testing.assert_allclose(T[:, :3, 3], P, atol=1e-6)
    np.testing.assert_allclose(matrix_to_quat(T[:, :3, :3]), Q, atol=1e-8)


def test_round_trip_with_and_without_time_and_label(tmp_path):
    path = write_pose_csv(tmp_path / "path.csv", P, Q, [0.0, 0.25, 0.25])
    assert path.read_text().splitlines()[0] == "t,x,y,z,q1,q2,q3,q4"
    got = read_pose_csv(path)
    check_poses(got.T)
    np.testing.assert_array_equal(got.t, [0.0, 0.25, 0.25])  # equal stamps are not backwards
    assert got.labels is None

    path = write_pose_csv(tmp_path / "bare.csv", P, 2.0 * Q)  # normalised on the way
    assert path.read_text().splitlines()[0] == "x,y,z,q1,q2,q3,q4"
    got = read_pose_csv(path)
    check_poses(got.T)
    assert got.t is None and got.labels is None

    names = ["00.png", "01 b.png", "a,b.png"]  # blanks and commas survive (quoted)
    path = write_pose_csv(tmp_path / "set.csv", P, Q, label="image", labels=names)
    assert path.read_text().splitlines()[0] == "image,x,y,z,q1,q2,q3,q4"
    got = read_pose_csv(path, label="image")
    check_poses(got.T)
    assert got.labels == names and got.t is None
    assert read_pose_csv(path).labels is None  # not asked for: an ignored extra column

    path = write_pose_csv(tmp_path / "both.csv", P, Q, [1.0, 2.0, 3.0], label="pose",
                          labels=["p0", "p1", "p2"])
    got = read_pose_csv(path, label="pose")
    assert path.read_text().splitlines()[0] == "pose,t,x,y,z,q1,q2,q3,q4"
    check_poses(got.T)
    assert got.labels == ["p0", "p1", "p2"] and list(got.t) == [1.0, 2.0, 3.0]


def test_columns_in_any_order_comments_blanks_and_old_header(tmp_path):
    path = tmp_path / "any.csv"
    path.write_text("\ufeff# torch poses\n Q4 , q3,q2,q1,z,y,x,T,note\n\n"
                    + "".join(f"{q[3]},{q[2]},{q[1]},{q[0]},{p[2]},{p[1]},{p[0]},{i},n{i}\n"
                              for i, (p, q) in enumerate(zip(P, Q, strict=True))))
    got = read_pose_csv(path)
    check_poses(got.T)
    assert list(got.t) == [0.0, 1.0, 2.0]
    # a calibration set recorded with the old spelling x_mm..qz reads unchanged
    path = tmp_path / "old.csv"
    path.write_text("image,x_mm,y_mm,z_mm,qw,qx,qy,qz\n"
                    + "".join(f"{i:02d}.png," + ",".join(map(str, [*p, *q])) + "\n"
                              for i, (p, q) in enumerate(zip(P, Q, strict=True))))
    got = read_pose_csv(path, label="image")
    check_poses(got.T)
    assert got.labels == ["00.png", "01.png", "02.png"]


@pytest.mark.parametrize("text, label, message", [
    ("", None, "no header and no poses (expected a header row x,y,z,q1,q2,q3,q4[,t])"),
    ("# only a comment\n\n", "image", "no header and no poses (expected a header row "
                                      "image,x,y,z,q1,q2,q3,q4)"),
    ("x,y,z,q1,q2,q3,q4\n", None, "header only, no poses"),
    ("x,y,z,q1,q2,q3\n1,2,3,1,0,0\n", None, "line 1: header lacks column(s) q4"),
    ("x,y,z,q1,q2,q3,q4\n1,2,3,1,0,0,0\n", "image", "line 1: header lacks column(s) image"),
    ("x,x_mm,y,z,q1,q2,q3,q4\n1,1,2,3,1,0,0,0\n", None,
     "line 1: column 'x' given twice ('x' and 'x_mm')"),
    ("x,y,z,q1,q2,q3,q4\n900,0,800,1,0,0,0\n900,0,eight,1,0,0,0\n", None,
     "line 3: field 'z': not a number ('eight')"),
    ("x,y,z,q1,q2,q3,q4\n900,0,800,1,0,0,0\n\n900,inf,800,1,0,0,0\n", None,
     "line 4: field 'y': not finite (inf)"),
    ("image,x_mm,y_mm,z_mm,qw,qx,qy,qz\na.png,900,0,nan,1,0,0,0\n", "image",
     "line 2: field 'z_mm': not finite (nan)"),
    ("x,y,z,q1,q2,q3,q4\n900,0,800,2,0,0,0\n", None,
     "line 2: quaternion q1..q4 has norm 2.000000 (must be 1; order w, x, y, z)"),
    ("x,y,z,q1,q2,q3,q4\n900,0,800\n", None, "line 2: expected 7 fields, got 3"),
    ("x,y,z,q1,q2,q3,q4\n900,0,800,1,0,0,0,5\n", None, "line 2: expected 7 fields, got 8"),
    ("image,x,y,z,q1,q2,q3,q4\n ,900,0,800,1,0,0,0\n", "image", "line 2: field 'image': empty"),
    ("x,y,z,q1,q2,q3,q4,t\n900,0,800,1,0,0,0,1\n# pause\n901,0,800,1,0,0,0,0.5\n", None,
     "line 4: field 't': time goes backwards (1 -> 0.5)"),
])
def test_bad_file_names_file_line_and_field(tmp_path, text, label, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(PoseFileError) as e:
        read_pose_csv(path, label=label)
    assert str(e.value).startswith(f"{path}: {message}")
    assert isinstance(e.value, ValueError)  # callers that catch ValueError still do


def test_unreadable_file(tmp_path):
    with pytest.raises(PoseFileError, match=r"missing\.csv: cannot read \(No such file"):
        read_pose_csv(tmp_path / "missing.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00x,y")
    with pytest.raises(PoseFileError, match=r"bin\.csv: not a text file"):
        read_pose_csv(tmp_path / "bin.csv")


def test_writer_refuses_what_the_reader_would(tmp_path):
    for kw, msg in (({"quaternion": Q[:1]}, "quaternion: expected shape"),
                    ({"position_mm": P * np.nan}, "finite"),
                    ({"quaternion": Q * 0}, "zero quaternion"),
                    ({"t_s": [1.0, 0.0, 2.0]}, "time goes backwards"),
                    ({"t_s": [1.0]}, "expected 3 time stamps"),
                    ({"label": "image"}, "give both"),
                    ({"label": "image", "labels": ["a", "b"]}, "expected 3 labels"),
                    ({"label": "image", "labels": ["a", "", "c"]}, "non-empty"),
                    ({"label": "image", "labels": ["a", "#b", "c"]}, "not start with #")):
        args = {"position_mm": P, "quaternion": Q, **kw}
        with pytest.raises(ValueError, match=msg):
            write_pose_csv(tmp_path / "bad.csv", **args)


def test_docstring_example_runs():
    result = doctest.testmod(torchseam.core.poses_csv)
    assert result.failed == 0 and result.attempted > 0
