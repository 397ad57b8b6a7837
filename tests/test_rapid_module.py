"""The shipped RAPID module (rapid/TorchseamWeld.mod): its data channel's indices and values are
rapid_data.py's, its blocks balance, it ships in the package, and ``torchseam robot rapid``
prints or writes it unchanged.

The module cannot run here: these tests read its text. What they do not show (that ABB's
compiler accepts it, that a controller runs it) its header says."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import torchseam
from torchseam.cli import main
from torchseam.robot.cli import RAPID_MODULE, rapid_module_path
from torchseam.robot.egm import rapid_data as rd

ROOT = Path(__file__).resolve().parents[1]
MOD = ROOT / "rapid" / RAPID_MODULE
TEXT = MOD.read_text(encoding="ascii")

#: the layout's names by kind: the dnum indices each array may be read / written with
SENSOR_INDICES = {"SENSOR_SEGMENT", "SENSOR_STATE", "SENSOR_HEARTBEAT"}
RAPID_INDICES = {"RAPID_SEGMENT", "RAPID_PHASE", "RAPID_N_SEGMENTS"}
#: the ABB instructions (statements) the module relies on, besides its own routines: an
#: integrator checks these against the controller's RAPID reference
ABB_INSTRUCTIONS = {"SetDO", "MoveJ", "MoveL", "EGMReset", "EGMGetId", "EGMSetupUC",
                    "EGMActPose", "EGMRunPose", "EGMStop", "WaitTime", "ErrWrite", "TPWrite",
                    "ClkStop", "ClkReset", "ClkStart"}
BLOCK_WORDS = {"MODULE", "ENDMODULE", "PROC", "ENDPROC", "FUNC", "ENDFUNC", "IF", "ELSEIF",
               "ELSE", "ENDIF", "WHILE", "ENDWHILE", "FOR", "ENDFOR", "TEST", "CASE", "DEFAULT",
               "ENDTEST", "ERROR"}


def _code_lines(text: str) -> list[str]:
    """The module's lines without comments (``!`` outside a string), stripped, non-empty."""
    out = []
    for line in text.splitlines():
        code, in_str = [], False
        for ch in line:
            if ch == '"':
                in_str = not in_str
            if ch == "!" and not in_str:
                break
            code.append(ch)
        s = "".join(code).strip()
        if s:
            out.append(s)
    return out


def _consts(text: str) -> dict[str, float]:
    found = re.findall(r"^\s*CONST\s+num\s+(\w+)\s*:=\s*([-+0-9.eE]+)\s*;", text, re.M)
    names = [n for n, _ in found]
    assert len(names) == len(set(names)), "a CONST declared twice"
    return {n: float(v) for n, v in found}


def test_every_layout_constant_is_declared_with_its_value():
    consts = _consts(TEXT)
    for name, value in rd.RAPID_CONSTANTS.items():
        assert name in consts, f"{RAPID_MODULE} lacks CONST num {name}"
        assert consts[name] == value, f"{name}: {consts[name]} in the module, {value} in " \
                                      "rapid_data.py"
    # and nothing in the layout's style that rapid_data.py does not know
    stray = {n for n in consts if re.match(r"(SENSOR|RAPID|STATE|PHASE|HEARTBEAT)_", n)
             and n not in rd.RAPID_CONSTANTS}
    assert not stray, f"CONSTs in the layout's style unknown to rapid_data.py: {stray}"


def test_the_arrays_are_indexed_with_the_layout_names_only():
    code = "\n".join(_code_lines(TEXT))
    # the sensor's values are read through SensorVal(NAME) only (and cleared all at the start)
    assert re.findall(r"dnFromSensor\{([^}]*)\}", code) == ["40", "k", "idx + 1"]
    read = set(re.findall(r"SensorVal\((\w+)\)", code))
    assert read == SENSOR_INDICES
    # RAPID's values are written as dnToSensor{NAME + 1}, each of them
    written = re.findall(r"dnToSensor\{([^}]*)\}", code)
    assert written[0] == "40"
    names = [re.fullmatch(r"(\w+) \+ 1", w) for w in written[1:]]
    assert all(names), written
    assert {m.group(1) for m in names if m} == RAPID_INDICES
    # the states and phases it names are declared (with the layout's values, above)
    used = set(re.findall(r"\b((?:STATE|PHASE)_\w+)\b", code))
    assert used <= set(rd.RAPID_CONSTANTS)
    assert {"STATE_TRACKING", "STATE_DONE", "STATE_ABORT"} <= used
    assert {f"PHASE_{p.name}" for p in rd.RapidPhase} <= used


def test_the_egm_calls_link_the_channel():
    code = " ".join(_code_lines(TEXT))
    act = re.search(r"EGMActPose [^;]*;", code)
    assert act, "no EGMActPose"
    for arg in (r"\DataToSensor:=dnToSensor", r"\DataFromSensor:=dnFromSensor",
                r"\DIFromSensor:=diTsArcReq", r"\DOToSensor:=doTsArcEst", r"\StreamStart"):
        assert arg in act.group(0)
    assert re.search(r"EGMSetupUC [^;]*\\Pose [^;]*\\CommTimeout:=COMM_TIMEOUT_S;", code)
    assert re.search(r"EGMRunPose egmId, EGM_STOP_HOLD \\NoWaitCond", code)
    assert "ERRNO = ERR_UDPUC_COMM" in code
    consts = _consts(TEXT)
    assert consts["HB_GIVEUP_S"] < consts["COMM_TIMEOUT_S"]  # the loop's own timeout first
    assert consts["HB_STALE_S"] < consts["HB_GIVEUP_S"]


def test_blocks_balance_and_statements_end():
    """A structural check (not ABB's compiler): every block closes in order, ERROR and CASE
    sit where they may, every statement ends with ';' before the next block word."""
    stack: list[str] = []
    pending = ""          # a statement spread over lines, not yet ended
    routines: set[str] = set()
    calls: set[str] = set()
    for line in _code_lines(TEXT):
        word = re.match(r"[A-Za-z_]\w*", line)
        first = word.group(0) if word else ""
        if first in BLOCK_WORDS or first in {"LOCAL"}:
            assert not pending, f"statement not ended before {line!r}: {pending!r}"
        if first == "MODULE":
            stack.append("MODULE")
        elif first in {"PROC", "FUNC"}:
            assert stack == ["MODULE"], line
            routines.add(re.match(r"(?:PROC|FUNC\s+\w+)\s+(\w+)", line).group(1))
            stack.append("ROUTINE")
        elif first == "ERROR":
            assert stack[-1] == "ROUTINE", "ERROR outside a routine's top level"
        elif first == "IF" and line.endswith("THEN"):
            stack.append("IF")
        elif first in {"ELSEIF", "ELSE"}:
            assert stack[-1] == "IF", line
        elif first in {"WHILE", "FOR"}:
            assert line.endswith("DO"), line
            stack.append(first)
        elif first == "TEST":
            stack.append("TEST")
        elif first in {"CASE", "DEFAULT"}:
            assert stack[-1] == "TEST" and line.endswith(":"), line
        elif first.startswith("END"):
            want = {"ENDMODULE": "MODULE", "ENDPROC": "ROUTINE", "ENDFUNC": "ROUTINE",
                    "ENDIF": "IF", "ENDWHILE": "WHILE", "ENDFOR": "FOR", "ENDTEST": "TEST"}
            assert stack and stack.pop() == want[first], line
        else:
            if not pending and stack and stack[-1] != "MODULE" and first:
                calls.add(first)
            pending = "" if line.endswith(";") else f"{pending} {line}"
    assert not stack and not pending
    keywords = {"VAR", "PERS", "CONST", "RETURN", "RAISE"}
    assigned = {c for c in calls if re.search(rf"^\s*{c}\s*(\{{[^}}]*\}})?\s*:=", TEXT, re.M)}
    unknown = calls - routines - ABB_INSTRUCTIONS - keywords - assigned
    assert not unknown, f"statements that are neither the module's routines nor the ABB " \
                        f"instructions listed here: {unknown}"
    assert {"main", "RunSegment", "SetPhase", "SensorVal", "ClearSensorData"} <= routines


def test_module_is_plain_ascii_and_named_as_its_file():
    assert TEXT.isascii()  # RAPID files and strings: ISO 8859-1; ASCII is safe everywhere
    assert _code_lines(TEXT)[0] == f"MODULE {MOD.stem}" and _code_lines(TEXT)[-1] == "ENDMODULE"
    assert TEXT.endswith("\n")
    for header in ("What was verified", "What was NOT verified", "has not run on a controller"):
        assert header in TEXT


# --------------------------------------------------------------------------- shipping

def test_module_ships_in_the_package():
    """torchseam/rapid links to rapid/ (one copy) and pyproject's package-data takes *.mod."""
    assert torchseam.shipped("rapid") == ROOT / "rapid"
    assert rapid_module_path() == MOD
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())[
        "tool"]["setuptools"]["package-data"]["torchseam"]
    pkg = ROOT / "torchseam"
    assert any(MOD.resolve() in {p.resolve() for p in pkg.glob(g)} for g in globs)


# --------------------------------------------------------------------------- the command

def test_command_prints_the_shipped_module(capsys):
    assert main(["robot", "rapid"]) == 0
    out = capsys.readouterr()
    assert out.out == TEXT and out.err == ""


def test_command_writes_the_module(tmp_path, capsys):
    path = tmp_path / "new" / "TorchseamWeld.mod"
    assert main(["robot", "rapid", "--out", str(path)]) == 0
    assert path.read_text(encoding="ascii") == TEXT
    assert str(path) in capsys.readouterr().out


@pytest.mark.parametrize("bad", ["folder", "under_a_file"])
def test_command_refuses_an_unusable_out(tmp_path, capsys, bad):
    (tmp_path / "a_file").write_text("x")
    path = tmp_path if bad == "folder" else tmp_path / "a_file" / "x.mod"
    with pytest.raises(SystemExit) as e:
        main(["robot", "rapid", "--out", str(path)])
    assert e.value.code == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and str(path) in out.err


def test_command_reports_a_failed_write(tmp_path, capsys, monkeypatch):
    """A write the system refuses (a read-only place; as root, a path the kernel refuses):
    one line naming the file, exit code 2, nothing on stdout."""
    path = tmp_path / "x.mod"

    def refuse(self, *a, **k):
        raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(Path, "write_text", refuse)
    assert main(["robot", "rapid", "--out", str(path)]) == 2
    out = capsys.readouterr()
    assert out.out == "" and out.err.count("\n") == 1 and str(path) in out.err
