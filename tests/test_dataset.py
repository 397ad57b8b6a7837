"""The dataset format: write, read back, and clear errors for broken folders."""

import json

import cv2
import numpy as np
import pytest

from torchseam.core.dataset import Dataset
from torchseam.core.errors import DatasetError
from torchseam.sim.record import write_sequence
from torchseam.sim.sequence import SequenceSpec


def test_write_and_read_back(tmp_path, cell, part, noise):
    truths = write_sequence(tmp_path / "s", cell, part, noise,
                            SequenceSpec(n_frames=8, level=1.0, seed=4), "heavy", progress=False)
    ds = Dataset.open(tmp_path / "s", require_labels=True)
    assert len(ds) == 8 and list(ds.frames) == list(range(8))
    np.testing.assert_allclose(ds.labels, [t.uv for t in truths], atol=1e-4)
    assert ds.meta["noise"] == {"level": 1.0, "name": "heavy", "seed": 4,
                                "clean_lead_frames": noise.clean_lead_frames}
    f3 = ds.meta["frames"][3]
    np.testing.assert_allclose(f3["seam_mm"], truths[3].seam_B)
    np.testing.assert_allclose(f3["camera_pose"]["position_mm"], truths[3].T_B_C[:3, 3],
                               atol=1e-5)
    assert ds.read(0).shape == (492, 656, 3)
    with pytest.raises(DatasetError, match="already holds 8 frames"):
        write_sequence(tmp_path / "s", cell, part, noise, SequenceSpec(n_frames=2),
                       progress=False)


def test_an_interrupted_write_leaves_a_dataset_of_the_frames_written(tmp_path, cell, part,
                                                                      noise, monkeypatch):
    """Ctrl-C while simulating: the frames written so far keep their labels and meta.json (a
    dataset of 3 frames, said so), and the interrupt goes on to the command."""
    import torchseam.sim.record as record
    from torchseam.sim.sequence import simulate

    def three_then_ctrl_c(*args, **kwargs):
        yield from list(simulate(*args, **kwargs))[:3]
        raise KeyboardInterrupt

    monkeypatch.setattr(record, "simulate", three_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        write_sequence(tmp_path / "s", cell, part, noise,
                       SequenceSpec(n_frames=5, level=0.0, seed=4), progress=False)
    ds = Dataset.open(tmp_path / "s", require_labels=True)
    truths = list(simulate(cell, part, noise, SequenceSpec(n_frames=3, level=0.0, seed=4)))
    assert len(ds) == 3 and ds.meta["sequence"]["n_frames"] == 3
    np.testing.assert_allclose(ds.labels, [t.uv for _, t in truths], atol=1e-4)


def _folder(tmp_path, n=3, labels="frame,u,v\n0,1.5,2.5\n1,3,4\n2,5,6\n"):
    d = tmp_path / "rec"
    d.mkdir()
    for i in range(n):
        cv2.imwrite(str(d / f"{i:05d}.png"), np.zeros((16, 16, 3), np.uint8))
    if labels is not None:
        (d / "labels.csv").write_text(labels)
    return d


def test_real_recording_with_only_frames_and_labels(tmp_path):
    ds = Dataset.open(_folder(tmp_path, labels="frame,u,v\n0,1.5,2.5\n2,5,6\n"))
    assert ds.meta is None
    assert ds.labelled.tolist() == [True, False, True]
    np.testing.assert_allclose(ds.labels[0], [1.5, 2.5])


@pytest.mark.parametrize(
    ("labels", "message"),
    [
        ("u,v\n1,2\n", "header must be 'frame,u,v'"),
        ("frame,u,v\n0,1,2\nx,1,2\n", r"line 3: frame 'x' is not a whole number"),
        ("frame,u,v\n0,1,abc\n", r"line 2: v 'abc' is not a number"),
        ("frame,u,v\n0,1,nan\n", r"line 2: v is 'nan'"),
        ("frame,u,v\n7,1,2\n", r"line 2: frame 7 has no image 00007.png"),
        ("frame,u,v\n0,1,2\n0,1,2\n", r"line 3: frame 0 is labelled twice"),
        ("frame,u,v\n0,1\n", r"line 2: expected 3 fields"),
        ("frame,u,v\n", "no labels below the header"),
        ("frame,u,v\n0,16,2\n", r"line 2: u 16 lies outside the 16 x 16 px frames"),
        ("frame,u,v\n0,1,-0.6\n", r"line 2: v -0.6 lies outside the 16 x 16 px frames"),
        ("frame,u,v\n0,1,3e11\n", r"line 2: v 3e11 lies outside"),
    ],
)
def test_mislabelled_folders(tmp_path, labels, message):
    with pytest.raises(DatasetError, match=message):
        Dataset.open(_folder(tmp_path, labels=labels))


def test_a_label_without_its_image_is_a_gap_skipped_with_a_warning(tmp_path, capsys):
    """A label row whose frame has no image (a dropped frame) is a gap in the frames, as the
    numbering's gaps are: skipped, counted and named in one warning line on stderr."""
    ds = Dataset.open(_folder(tmp_path, labels="frame,u,v\n0,1.5,2.5\n7,3,4\n2,5,6\n9,1,1\n"))
    assert ds.unimaged_labels.tolist() == [7, 9]
    assert ds.labelled.tolist() == [True, False, True]
    np.testing.assert_allclose(ds.labels[2], [5, 6])
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("warning: ") and "labels.csv: 2 label(s) of frames with no image " \
        "skipped (frame 7, 9)" in err
    # still refused: twice the same frame, with or without an image
    (tmp_path / "b").mkdir()
    with pytest.raises(DatasetError, match="line 3: frame 7 is labelled twice"):
        Dataset.open(_folder(tmp_path / "b", labels="frame,u,v\n7,1,2\n7,1,2\n0,1,1\n"))


def test_labels_on_the_image_edge_and_with_a_byte_order_mark(tmp_path):
    """Pixel centres are on integers: -0.5 .. 15.5 lies on a 16 px frame. A spreadsheet's
    UTF-8 byte-order mark before the header is skipped."""
    d = _folder(tmp_path, labels=None)
    (d / "labels.csv").write_bytes(b"\xef\xbb\xbfframe,u,v\r\n0,-0.5,15.5\r\n")
    np.testing.assert_allclose(Dataset.open(d).labels[0], [-0.5, 15.5])


def test_labels_can_be_left_unread(tmp_path):
    """``track`` needs no labels: a labels.csv naming a frame without an image is not read."""
    d = _folder(tmp_path, labels="frame,u,v\n7,1,2\n")
    with pytest.raises(DatasetError, match="frame 7 has no image"):
        Dataset.open(d)
    ds = Dataset.open(d, labels=False)
    assert ds.labels is None and len(ds) == 3


def test_missing_or_empty_folders(tmp_path):
    with pytest.raises(DatasetError, match="no such folder"):
        Dataset.open(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no frames"):
        Dataset.open(tmp_path / "empty")
    with pytest.raises(DatasetError, match="labels.csv is missing"):
        Dataset.open(_folder(tmp_path, labels=None), require_labels=True)
    d = tmp_path / "rec"
    (d / "meta.json").write_text("{broken")
    with pytest.raises(DatasetError, match="meta.json: not valid JSON"):
        Dataset.open(d)
    assert json  # the module is used by the format
