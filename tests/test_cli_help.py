"""Help texts: every option explained, its default said, nothing argparse left unformatted."""

import argparse

import pytest

from torchseam.cli import build_parser

#: commands whose options must each say their default (the others are owned elsewhere and
#: checked for a help text only)
DEFAULTS_SAID = {"simulate", "detect", "calibrate", "plan", "robot", "console", "demo", "replay",
                 "train-live", "train", "track", "eval", "ring"}


def _parsers(parser, path=()):
    """(command path, parser) for every (sub-)command."""
    yield path, parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield from _parsers(sp, (*path, name))


PARSERS = list(_parsers(build_parser()))


@pytest.mark.parametrize("path,parser", PARSERS, ids=[" ".join(p) or "torchseam"
                                                      for p, _ in PARSERS])
def test_help_is_complete(path, parser):
    text = parser.format_help()
    assert "%%" not in text and "%(" not in text
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction | argparse._SubParsersAction):
            continue
        name = "/".join(a.option_strings) or a.dest
        assert a.help and a.help is not argparse.SUPPRESS, f"{' '.join(path)} {name}: no help"
        flag = a.nargs == 0  # store_true and the like: off unless given
        if path[:1] and path[0] in DEFAULTS_SAID and a.option_strings and not flag \
                and not a.required:
            assert "default" in a.help, f"{' '.join(path)} {name}: the default is unsaid"


def test_robot_ik_and_check_say_which_point_the_pose_is_of():
    cmds = dict(PARSERS)
    ik = cmds[("robot", "ik")].format_help()
    check = cmds[("robot", "check")].format_help()
    assert "flange" in ik and "torch tip" in ik
    assert "torch tip" in check and "not of the flange" in " ".join(check.split())


def test_help_says_what_the_code_does():
    """Help texts that once said otherwise: replay's --pose default (the flange at the base
    origin: 3D points are located), ring's --model (the live tracker's file, as the other
    commands say)."""
    cmds = dict(PARSERS)
    replay = " ".join(cmds[("replay",)].format_help().split())
    assert "flange at the base origin" in replay and "pixels only" not in replay
    ring = " ".join(cmds[("ring",)].format_help().split())
    assert "EAKF-STC model file" not in ring
    assert "tracker model file for the anchored and eakf-stc trackers" in ring
    assert "models/live_tracker.safetensors" in ring


def test_calibrate_help_gives_the_pose_csv_header_simulate_writes(tmp_path):
    """The hand-eye and TCP poses.csv header in the help is the one format
    (torchseam/core/poses_csv.py) that ``calibrate simulate`` writes; the old spelling is
    named only as still read."""
    from torchseam.cli import main

    text = " ".join(dict(PARSERS)[("calibrate",)].format_help().split())
    assert "header image,x,y,z,q1,q2,q3,q4" in text and "header pose,x,y,z,q1,q2,q3,q4" in text
    assert "x_mm,y_mm,z_mm,qw,qx,qy,qz is still read" in text
    assert main(["calibrate", "simulate", "tcp", str(tmp_path / "t")]) == 0
    header = next(ln for ln in (tmp_path / "t" / "poses.csv").read_text().splitlines()
                  if ln and not ln.startswith("#"))
    assert header == "pose,x,y,z,q1,q2,q3,q4"


#: what a command's parser must not import: the command imports them when it runs
HEAVY = ("torch", "pytorch_kinematics", "matplotlib", "scipy", "cv2")


def test_command_help_imports_nothing_heavy():
    """``torchseam COMMAND --help`` (and ``calibrate camera --help``, ``robot ik --help``, ...)
    builds the command's parser without torch, pytorch_kinematics, matplotlib, scipy or
    OpenCV (seconds of imports): one fresh interpreter goes through every command path,
    checking after each which heavy modules it has imported."""
    import json
    import subprocess
    import sys

    paths = [list(p) for p, _ in PARSERS if p]
    code = """if True:
        import contextlib, io, json, sys
        from torchseam.cli import main
        heavy, paths = json.loads(sys.argv[1])
        found = {}
        for path in paths:
            with contextlib.redirect_stdout(io.StringIO()) as out, \\
                    contextlib.suppress(SystemExit):
                main([*path, "--help"])
            assert "usage: torchseam " + " ".join(path) in out.getvalue(), path
            loaded = [m for m in heavy if m in sys.modules]
            if loaded:
                found[" ".join(path)] = loaded
                break
        print(json.dumps(found))
    """
    r = subprocess.run([sys.executable, "-c", code, json.dumps([HEAVY, paths])],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == {}, "a command's --help imported " + r.stdout
