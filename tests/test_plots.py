"""Report figures: segment boundaries, the arc-off approach, legends, equal 3D scales."""

import numpy as np
import pytest

from torchseam.live import plots


@pytest.fixture
def figs(monkeypatch):
    """The figures the plot functions close, kept open for inspection."""
    kept, close = [], plots.plt.close
    monkeypatch.setattr(plots.plt, "close", kept.append)
    yield kept
    for f in kept:
        close(f)


def _run():
    seg = ["a"] * 50 + ["b"] * 50
    arc = np.ones(100, bool)
    arc[:8] = False
    arc[50:58] = False
    err = np.full(100, 0.05)
    err[:8] = np.linspace(3.2, 0.1, 8)       # the approach: the distance still to go
    err[50:58] = np.linspace(0.7, 0.1, 8)
    return seg, arc, err


def test_series_plot_scales_the_welding_frames_apart(tmp_path, figs):
    seg, arc, err = _run()
    out = plots.series_plot({"torch to true seam": err}, "mm", tmp_path / "t.png",
                            segments=seg, arc_on=arc)
    assert out.stat().st_size
    (fig,) = figs
    top, bottom = fig.axes
    assert top.get_ylim()[1] < 0.2               # the welding scale: not the 3.2 mm approach
    assert bottom.get_ylim()[1] > 3.0            # the whole run below
    for ax in fig.axes:
        labels = ax.get_legend_handles_labels()[1]
        assert ax.get_legend() is not None
        assert "arc off (approach)" in labels and "segment start" in labels


def test_series_plot_without_marks_is_one_panel(tmp_path, figs):
    plots.series_plot({"u": np.arange(5.0), "v": np.zeros(5)}, "px", tmp_path / "s.png")
    (fig,) = figs
    assert len(fig.axes) == 1 and fig.axes[0].get_legend() is not None


def test_quaternion_legend_on_every_panel(tmp_path, figs):
    q = np.tile([1.0, 0.0, 0.0, 0.0], (20, 1))
    mask = np.zeros(20, bool)
    mask[:4] = True
    plots.quaternion_plot([("a", q), ("b", q), ("c", np.zeros((0, 4)))], tmp_path / "q.png",
                          approach={"a": mask})
    (fig,) = figs
    assert all(ax.get_legend() is not None for ax in fig.axes[:2])
    assert "arc off (approach)" in fig.axes[0].get_legend_handles_labels()[1]


def test_seam_3d_one_view_per_segment_equal_scales(tmp_path, figs):
    t = np.linspace(0, 1, 50)[:, None]
    pieces = [np.hstack([100 * t, 2 * t, 0 * t]) + 300 * i for i in range(3)]
    mask = [np.arange(50) < 5] * 3
    plots.seam_3d_plot({"true seam": pieces, "tracked": pieces}, tmp_path / "s.png",
                       segment_names=["a", "b", "c"], approach={"tracked": mask})
    (fig,) = figs
    assert len(fig.axes) == 3
    for ax, name in zip(fig.axes, "abc", strict=True):
        spans = [np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()), np.ptp(ax.get_zlim())]
        assert max(spans) == pytest.approx(min(spans))
        assert ax.get_legend() is not None and ax.get_title() == f"segment {name}"
