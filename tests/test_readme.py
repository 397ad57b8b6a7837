"""The README's code: every Python block compiles; the Python API examples run as written."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_every_python_block_compiles():
    blocks = _blocks(README.read_text())
    assert len(blocks) >= 5
    for i, code in enumerate(blocks):
        compile(code, f"README.md python block {i}", "exec")


def test_the_two_commands_are_there_verbatim():
    ci = (README.parent / ".ci" / "run").read_text()
    test_cmd = next(line for line in ci.splitlines() if line.startswith("python3 -m venv .venv"))
    text = README.read_text()
    assert test_cmd in text
    install = test_cmd.split(" && .venv/bin/python -m pytest", 1)[0]
    assert install + " && .venv/bin/torchseam demo\n" in text


@pytest.mark.filterwarnings("ignore")
def test_python_api_examples_run(tmp_path, monkeypatch, capsys):
    section = README.read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    monkeypatch.chdir(tmp_path)  # the demo example writes out/
    ns: dict = {}
    for code in _blocks(section):
        exec(compile(code, "README.md Python API", "exec"), ns)
    assert ns["res"].summary["unsafe_poses_sent"] == 0
    assert (tmp_path / "out" / "summary.json").exists()
    assert bool(ns["ok"][0])


def test_the_configuration_section_names_every_shipped_config():
    """A config file the README's list leaves out is a setting a user never hears of."""
    text = README.read_text()
    section = text[text.index("## Configuration"):text.index("## Further reading")]
    shipped = sorted(p.name for p in (README.parent / "configs").glob("*.yaml"))
    assert shipped, "no configs found next to the README"
    missing = [name for name in shipped if f"`{name}`" not in section]
    assert not missing, f"README's Configuration section does not name {missing}"
