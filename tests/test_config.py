from pathlib import Path

import numpy as np
import pytest
import yaml

from torchseam.core.config import (
    CONFIG_DIR,
    CellConfig,
    ConfigError,
    PartConfig,
    load_cell,
    load_config,
    load_noise,
    load_part,
    save_config,
)


def test_defaults_load_with_the_briefs_figures():
    cell, part = load_cell(), load_part()
    assert (cell.camera.width, cell.camera.height) == (656, 492)
    assert cell.process.look_ahead_mm == 20.0
    assert cell.process.step_mm == 2.0
    assert cell.process.weld_speed_mm_s == 8.0
    assert (part.main_od_mm, part.branch_od_mm) == (203.0, 152.0)
    assert 60.0 <= part.intersection_angle_deg <= 90.0
    # the hand-eye and tool poses give a real rigid transform
    T = cell.hand_eye.matrix()
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)


def _write(tmp_path: Path, data: dict, name: str = "cell.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


def _cell_dict() -> dict:
    return yaml.safe_load((CONFIG_DIR / "cell.yaml").read_text())


def test_missing_field_names_file_and_field(tmp_path):
    d = _cell_dict()
    del d["camera"]["fx"]
    p = _write(tmp_path, d)
    with pytest.raises(ConfigError, match=r"cell\.yaml: camera\.fx: missing"):
        load_cell(p)


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (("camera", "fx"), -3, r"camera\.fx: expected a number > 0"),
        (("camera", "width"), 656.5, r"camera\.width: expected a whole number"),
        (("camera", "dist"), [0.1, 0.2], r"camera\.dist: expected 5 values, got 2"),
        (("camera", "cy"), "abc", r"camera\.cy: expected a number"),
        (("hand_eye", "quaternion"), [1, 1, 0, 0], r"hand_eye\.quaternion: expected a unit"),
        (("laser_plane", "source_mm"), [0, 0, 0], r"laser_plane\.source_mm: lies .* off"),
        (("process", "step_mm"), 0, r"process\.step_mm: expected a number > 0"),
    ],
)
def test_wrong_field_values(tmp_path, path, value, message):
    d = _cell_dict()
    d[path[0]][path[1]] = value
    with pytest.raises(ConfigError, match=message):
        load_cell(_write(tmp_path, d))


def test_unknown_field_and_bad_files(tmp_path):
    d = _cell_dict()
    d["camera"]["fz"] = 1.0
    with pytest.raises(ConfigError, match=r"camera\.fz: unknown field"):
        load_cell(_write(tmp_path, d))
    with pytest.raises(ConfigError, match="cannot read config"):
        load_cell(tmp_path / "absent.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("camera: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML") as e:
        load_config(CellConfig, bad)
    # one line: PyYAML's problem and where (not its multi-line text)
    assert str(e.value) == (f"{bad}: not valid YAML: expected ',' or ']', but got "
                            "'<stream end>' (line 2, column 1)")


def test_part_sizes_must_be_positive(tmp_path):
    """A pipe's diameter or a sphere's radius given as 0 or below: "> 0", not "missing" nor
    ">= 0"; left out: missing. (0 stays the value of a kind that has none: files round-trip.)"""
    d = yaml.safe_load((CONFIG_DIR / "parts" / "t_joint.yaml").read_text())
    for v in (0, -5):
        d["main_od_mm"] = v
        with pytest.raises(ConfigError, match=r"main_od_mm: the main pipe's outer diameter "
                                              rf"must be > 0 \(at least 10 mm\), got {v}\.0$"):
            load_part(_write(tmp_path, d, "p.yaml"))
    del d["main_od_mm"]
    with pytest.raises(ConfigError, match=r"main_od_mm: missing \(the main pipe's outer"):
        load_part(_write(tmp_path, d, "p.yaml"))
    s = yaml.safe_load((CONFIG_DIR / "parts" / "pipe_on_sphere.yaml").read_text())
    s["sphere_radius_mm"] = 0
    with pytest.raises(ConfigError, match=r"sphere_radius_mm: the sphere's radius must be > 0, "
                                          r"got 0\.0$"):
        load_part(_write(tmp_path, s, "p.yaml"))
    plate = yaml.safe_load((CONFIG_DIR / "parts" / "pipe_on_plate.yaml").read_text())
    plate["main_od_mm"] = 0.0  # as save_config writes a plate
    assert load_part(_write(tmp_path, plate, "p.yaml")).main_od_mm == 0.0
    plate["main_od_mm"] = -5.0
    with pytest.raises(ConfigError, match="main_od_mm: a part of kind plate has none"):
        load_part(_write(tmp_path, plate, "p.yaml"))


@pytest.mark.parametrize("name", sorted(p.name for p in (CONFIG_DIR / "parts").glob("*.yaml")))
def test_every_shipped_part_saves_and_loads_back(tmp_path, name):
    """A part written with save_config (as ``plan --out`` and the demo's report write each
    segment's turned part, which ``robot check --part`` reads) loads back equal: a coupon's file
    once held branch_od_mm 0.0, which its loader refuses."""
    part = load_part(CONFIG_DIR / "parts" / name)
    save_config(part, tmp_path / name)
    assert load_part(tmp_path / name) == part


def test_part_validation(tmp_path):
    d = yaml.safe_load((CONFIG_DIR / "parts" / "t_joint.yaml").read_text())
    d["intersection_angle_deg"] = 45.0
    with pytest.raises(ConfigError, match=r"intersection_angle_deg: expected a number >= 60"):
        load_part(_write(tmp_path, d, "p.yaml"))
    d["intersection_angle_deg"] = 90.0
    d["branch_od_mm"] = 210.0
    with pytest.raises(ConfigError, match="branch_od_mm: branch radius"):
        load_config(PartConfig, _write(tmp_path, d, "p.yaml"))


def test_noise_levels():
    n = load_noise()
    assert n.level("clean") == 0.0 and n.level("heavy") == 1.0
    assert n.level("0.4") == pytest.approx(0.4)
    with pytest.raises(ValueError, match="use a number in"):
        n.level("loud")
    # above 1: heavier arc than the amplitudes as written (issue 35: 1.5 x heavy), up to 2
    assert n.level("extreme") == 1.5 and n.level(1.5) == 1.5
    with pytest.raises(ValueError, match=r"must lie in \[0, 2\]"):
        n.level(2.5)
    with pytest.raises(ValueError, match=r"must lie in \[0, 2\]"):
        n.level(-0.1)
