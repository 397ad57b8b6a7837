"""The installable package: shipped data found from the package, a fast ``--help`` that imports no
stage, ``--version``, and ``--config-dir``. (.ci/run also installs the wheel into a fresh venv
and runs the demo from an empty folder.)"""

import glob
import json
import os
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

import torchseam
from torchseam.cli import COMMANDS, build_parser, main

ROOT = Path(__file__).resolve().parents[1]
#: the repository folders that ship inside the package, and the files of each that must ship
SHIPPED = {"configs": "**/*.yaml", "urdf": "*.urdf", "models": "*.safetensors",
           "rapid": "*.mod"}
#: third-party modules that take seconds to import: ``torchseam --help`` needs none of them
HEAVY = ("torch", "cv2", "numpy", "scipy", "numba", "matplotlib", "yaml", "pytorch_kinematics",
         "aiohttp")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop(torchseam.CONFIGS_ENV, None)
    env.pop(torchseam.MODELS_ENV, None)
    return env


def _torchseam(*argv: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "torchseam", *argv], capture_output=True,
                          text=True, timeout=300, cwd=cwd, env=_env())


# --------------------------------------------------------------------------- the shipped data

def test_shipped_data_are_the_repository_folders():
    """In a checkout the package's configs/models/urdf are the repository's folders (links), so
    there is one copy to edit; the files the wheel ships (pyproject's package-data) are all of
    them."""
    for name in SHIPPED:
        assert torchseam.shipped(name) == ROOT / name, f"torchseam/{name} must link to {name}/"
    globs = _package_data_globs()
    pkg = ROOT / "torchseam"
    packaged = {Path(p).resolve() for g in globs for p in glob.glob(str(pkg / g), recursive=True)
                if Path(p).is_file()}
    for name, pattern in SHIPPED.items():
        files = {p.resolve() for p in (ROOT / name).glob(pattern) if p.is_file()}
        assert files, f"nothing to ship in {name}/"
        assert files <= packaged, f"not in the wheel: {sorted(map(str, files - packaged))}"
    # every config file is a YAML file the glob takes (a new kind of file would be left out)
    others = [p for p in (ROOT / "configs").rglob("*") if p.is_file() and p.suffix != ".yaml"]
    assert not others, f"configs/ holds files the wheel leaves out: {others}"


def _package_data_globs() -> list[str]:
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return data["tool"]["setuptools"]["package-data"]["torchseam"]


def test_lookups_resolve_to_existing_files():
    r = subprocess.run([sys.executable, "-c", """if True:
        import json
        from torchseam.core.config import CONFIG_DIR, load_cell, load_part
        from torchseam.fit.model_io import DEFAULT_MODEL, MODEL_DIR
        from torchseam.robot.kinematics import URDF_PATH
        load_cell(), load_part()
        print(json.dumps([str(CONFIG_DIR), str(MODEL_DIR), str(DEFAULT_MODEL), str(URDF_PATH)]))
        """], capture_output=True, text=True, timeout=300, cwd="/", env=_env())
    assert r.returncode == 0, r.stderr[-2000:]
    config_dir, model_dir, model, urdf = map(Path, json.loads(r.stdout))
    assert config_dir == torchseam.shipped("configs") and (config_dir / "cell.yaml").is_file()
    assert (config_dir / "parts" / "t_joint.yaml").is_file()
    assert model_dir == torchseam.shipped("models") and model.is_file()
    assert urdf == torchseam.shipped("urdf") / "irb1410.urdf" and urdf.is_file()


def test_environment_variables_name_other_folders(tmp_path, monkeypatch):
    monkeypatch.setenv(torchseam.CONFIGS_ENV, str(tmp_path / "c"))
    monkeypatch.setenv(torchseam.MODELS_ENV, str(tmp_path / "m"))
    assert torchseam.config_dir() == tmp_path / "c"
    assert torchseam.model_dir() == tmp_path / "m"


# --------------------------------------------------------------------------- the command line

def test_help_imports_no_stage():
    """``torchseam --help`` is built from the command table: no stage module, no torch."""
    r = subprocess.run([sys.executable, "-c", """if True:
        import contextlib, io, json, sys
        from torchseam.cli import main
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            try:
                main(["--help"])
            except SystemExit as e:
                assert e.code == 0, e.code
        print(json.dumps({"help": out.getvalue(), "modules": sorted(sys.modules)}))
        """], capture_output=True, text=True, timeout=120, env=_env())
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout)
    heavy = [m for m in res["modules"] if m.split(".")[0] in HEAVY]
    assert not heavy, f"--help imported {heavy[:10]}"
    ours = {m for m in res["modules"] if m.split(".")[0] == "torchseam"}
    assert ours <= {"torchseam", "torchseam.cli", "torchseam.core", "torchseam.core.cliargs",
                    "torchseam.core.errors"}, ours
    for name, _, text in COMMANDS:
        assert name in res["help"] and text.split()[0] in res["help"]
    assert "--config-dir" in res["help"] and str(torchseam.shipped("configs")) in res["help"]


def test_command_table_matches_the_modules():
    """The table's names, order and one-line help are what the stage modules register."""
    full = next(a for a in build_parser()._actions if a.dest == "command")
    lazy = next(a for a in build_parser(commands=())._actions if a.dest == "command")
    registered = [(a.dest, a.help) for a in full._choices_actions]
    assert registered == [(name, text) for name, _, text in COMMANDS]
    assert [a.dest for a in lazy._choices_actions] == [name for name, _, _ in COMMANDS]


@pytest.mark.parametrize("name", [name for name, _, _ in COMMANDS])
def test_command_help_works_alone(name, capsys):
    """Each command's options come from the module the table names (a wrong one leaves the
    command without options: ``--help`` would be refused)."""
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    assert capsys.readouterr().out.startswith(f"usage: torchseam {name}")


def test_version(tmp_path):
    r = _torchseam("--version", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"torchseam {version('torchseam')}"
    assert torchseam.__version__ == version("torchseam")


def test_config_dir_must_be_a_folder(tmp_path, capsys):
    (tmp_path / "file.yaml").write_text("x: 1\n")
    for bad in (tmp_path / "absent", tmp_path / "file.yaml"):
        with pytest.raises(SystemExit) as e:
            main(["--config-dir", str(bad), "demo"])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "--config-dir" in err and str(bad) in err


# --------------------------------------------------------------------------- --config-dir

JOINTS = "30,0,0,0,30,0"  # axis 1 at 30 degrees: reachable with the shipped limits (170)


@pytest.fixture(scope="module")
def narrow_configs(tmp_path_factory):
    """A copy of the shipped configs with one changed value: axis 1 limited to +20 degrees."""
    d = tmp_path_factory.mktemp("my_configs")
    shutil.copytree(torchseam.shipped("configs"), d, dirs_exist_ok=True)
    robot = d / "robot.yaml"
    old = "max_deg: [170.0,"
    assert robot.read_text().count(old) == 1
    robot.write_text(robot.read_text().replace(old, "max_deg: [20.0,"))
    return d


@pytest.fixture(scope="module")
def pose_at_joints():
    r = _torchseam("robot", "fk", "--joints", JOINTS)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.split()


def test_config_dir_is_used(narrow_configs, pose_at_joints, tmp_path):
    """As a user runs it: a fresh process, the changed value decides."""
    r = _torchseam("--config-dir", str(narrow_configs), "robot", "ik", *pose_at_joints,
                   cwd=tmp_path)
    assert r.returncode == 1 and "axis 1 out of range" in r.stdout, (r.stdout, r.stderr)


def test_config_dir_in_process_then_restored(narrow_configs, pose_at_joints, capsys):
    """Twice in one process (stage modules imported already): the copy is used for that call
    only; a bad value in it is an error naming the copy's file."""
    import torchseam.core.config as cfg

    before, env = cfg.CONFIG_DIR, os.environ.get(torchseam.CONFIGS_ENV)
    assert main(["robot", "ik", *pose_at_joints]) == 0
    assert capsys.readouterr().out.split()[0] == "30.000"
    assert main(["--config-dir", str(narrow_configs), "robot", "ik", *pose_at_joints]) == 1
    assert "axis 1 out of range" in capsys.readouterr().out
    assert cfg.CONFIG_DIR == before and os.environ.get(torchseam.CONFIGS_ENV) == env
    assert main(["robot", "ik", *pose_at_joints]) == 0


def test_config_dir_bad_value_names_the_copy(tmp_path, capsys):
    d = tmp_path / "cfg"
    shutil.copytree(torchseam.shipped("configs"), d)
    robot = d / "robot.yaml"
    robot.write_text(robot.read_text().replace("ik_method: analytic", "ik_method: guess"))
    assert main(["--config-dir", str(d), "robot", "fk", "--joints", JOINTS]) == 2
    err = capsys.readouterr().err
    assert str(robot) in err and "ik_method" in err
