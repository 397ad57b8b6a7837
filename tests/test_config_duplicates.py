"""A key given twice in a config is refused with the file, the line and the key (issue 36):
PyYAML keeps the last one silently, so a typo'd second ``fx:`` would win unseen.

Every YAML read of the package goes through :func:`torchseam.core.config.read_yaml` /
:func:`~torchseam.core.config.load_yaml` (:class:`~torchseam.core.config.UniqueKeyLoader`);
the property tests render random nested configs in block style, with their line numbers
known, and add a duplicate anywhere.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchseam.cli import main
from torchseam.core.config import CONFIG_DIR, ConfigError, load_cell, load_yaml, read_yaml


def _run(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def _with_duplicate(text: str, section: str, key: str) -> tuple[str, int, int]:
    """``text`` with the first ``KEY:`` line under top-level ``SECTION:`` given again right
    after it (same indentation, another value); (text, line of the copy, line of the first)."""
    lines = text.splitlines(keepends=True)
    top = next(i for i, s in enumerate(lines) if s.startswith(f"{section}:"))
    k = next(i for i in range(top + 1, len(lines))
             if re.match(rf"\s+{key}:", lines[i]))
    indent = lines[k][:len(lines[k]) - len(lines[k].lstrip())]
    lines.insert(k + 1, f"{indent}{key}: 1234.5\n")
    return "".join(lines), k + 2, k + 1


def test_every_shipped_config_has_each_key_once():
    files = sorted(Path(CONFIG_DIR).rglob("*.yaml"))
    assert len(files) >= 10
    for p in files:
        read_yaml(p)  # raises on a duplicate


def test_a_cell_key_given_twice_names_file_line_and_key(tmp_path):
    text, line, first = _with_duplicate((CONFIG_DIR / "cell.yaml").read_text(), "camera", "fx")
    p = tmp_path / "cell.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as e:
        load_cell(p)
    assert str(e.value) == f"{p}:{line}: camera.fx given twice (first on line {first})"
    # the same keys once each load as before
    assert load_cell(CONFIG_DIR / "cell.yaml").camera.fx > 0


def test_the_cli_says_it_in_one_line_with_exit_2(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    text, line, first = _with_duplicate((CONFIG_DIR / "cell.yaml").read_text(), "camera", "fx")
    p = tmp_path / "cell.yaml"
    p.write_text(text)
    rc, out, err = _run(["simulate", str(tmp_path / "o"), "--frames", "1", "--cell", str(p)],
                        capsys)
    assert rc == 2 and out == ""
    lines = err.strip().splitlines()
    assert lines == [f"torchseam simulate: error: {p}:{line}: camera.fx given twice "
                     f"(first on line {first})"], err
    assert not (tmp_path / "o").exists()


def test_a_config_dir_with_a_duplicate_is_refused(tmp_path, capsys):
    d = tmp_path / "cfgs"
    d.mkdir()
    for p in Path(CONFIG_DIR).glob("*.yaml"):
        (d / p.name).write_text(p.read_text())
    text, line, first = _with_duplicate((d / "console.yaml").read_text(), "server", "port")
    (d / "console.yaml").write_text(text)
    from torchseam.console.config import load_console_config

    with pytest.raises(ConfigError, match=rf"console\.yaml:{line}: server\.port given twice "
                                          rf"\(first on line {first}\)$"):
        load_console_config(d / "console.yaml")


@pytest.mark.parametrize(("text", "message"), [
    ("a: 1\nb: 2\na: 3\n", "f.yaml:3: a given twice (first on line 1)"),
    ("s:\n  t:\n    u: 1\n    u: 2\n", "f.yaml:4: s.t.u given twice (first on line 3)"),
    ("l:\n  - x: 1\n  - {y: 1, y: 2}\n", "f.yaml:3: l[1].y given twice (first on line 3)"),
    ("1: a\n1.0: b\n", "f.yaml:2: 1.0 given twice (first on line 1)"),   # the same dict key
    ("yes: 1\ntrue: 2\n", "f.yaml:2: true given twice (first on line 1)"),
    ("m: {<<: {a: 1, a: 2}}\n", "f.yaml:1: m.a given twice (first on line 1)"),  # inline merge
])
def test_duplicates_of_every_shape(text, message):
    with pytest.raises(ConfigError) as e:
        load_yaml(text, "f.yaml")
    assert str(e.value) == message


@pytest.mark.parametrize("text", [
    "base: &b {a: 1, b: 2}\ntop:\n  <<: *b\n  a: 3\n",          # a merge, then an override
    "base: &b {a: 1}\nmid: &m\n  <<: *b\n  a: 2\ntop:\n  <<: *m\n  a: 3\n",
    "x: &a [*a]\n",                                               # a cycle through an alias
    "a: &x {k: 1}\nb: *x\nc: *x\n",                               # one mapping, three places
    "a: 1\nA: 2\n'a ': 3\n",                                      # different keys
    "",
])
def test_what_is_not_a_duplicate_loads_as_safe_load_does(text):
    assert repr(load_yaml(text)) == repr(yaml.safe_load(text))


# --------------------------------------------------------------------------- properties

KEYS = st.sampled_from(["a", "b", "c", "fx", "fy", "port", "x_mm", "rate_hz", "1", "2.5",
                        "yes", "off", "null_", "k-1"])
LEAF = st.one_of(st.integers(-10**6, 10**6), st.floats(-1e6, 1e6, allow_nan=False),
                 st.sampled_from(["text", "'quoted'", "[1, 2]", "{p: 1, q: 2}", "null"]))
TREE = st.recursive(LEAF, lambda sub: st.one_of(
    st.dictionaries(KEYS, sub, min_size=1, max_size=4),
    st.lists(st.dictionaries(KEYS, sub, min_size=1, max_size=3), min_size=1, max_size=3)),
    max_leaves=25)


def _render(tree: dict, indent: int = 0, path: str = "") -> list[tuple]:
    """Block-style lines of a mapping: (key column, text, key as written, the mapping the key
    belongs to, the key's dotted path); a list item's first line opens with ``- ``."""
    out: list = []
    for k, v in tree.items():
        where = f"{path}.{k}" if path else k
        pad = " " * indent
        if isinstance(v, dict):
            out.append((indent, f"{pad}{k}:", k, tree, where))
            out.extend(_render(v, indent + 2, where))
        elif isinstance(v, list):
            out.append((indent, f"{pad}{k}:", k, tree, where))
            for j, item in enumerate(v):
                sub = _render(item, indent + 4, f"{where}[{j}]")
                col, text, key, owner, at = sub[0]
                sub[0] = (col, " " * (indent + 2) + "- " + text.lstrip(), key, owner, at)
                out.extend(sub)
        else:
            out.append((indent, f"{pad}{k}: {v}", k, tree, where))
    return out


def _distinct_keys(text_keys: list[str]) -> bool:
    """True when the written keys load as distinct dict keys (``yes`` and ``1`` both load as
    1: such a generated mapping is a real duplicate, not a test of one)."""
    keys = [next(iter(yaml.safe_load(f"{k}: 0"))) for k in text_keys]
    return len(set(keys)) == len(keys)


def _mappings(tree: dict) -> list[dict]:
    out = [tree]
    for v in tree.values():
        if isinstance(v, dict):
            out.extend(_mappings(v))
        elif isinstance(v, list):
            for item in v:
                out.extend(_mappings(item))
    return out


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tree=st.dictionaries(KEYS, TREE, min_size=1, max_size=5), data=st.data())
def test_random_configs_load_as_safe_load_and_any_added_duplicate_is_named(tree, data):
    if not all(_distinct_keys(list(m)) for m in _mappings(tree)):
        return
    lines = _render(tree)
    text = "\n".join(line[1] for line in lines) + "\n"
    assert repr(load_yaml(text)) == repr(yaml.safe_load(text))   # no false alarm
    # give one key of one mapping again, as the last line of that mapping's block
    i = data.draw(st.integers(0, len(lines) - 1), label="line")
    col, _, key, owner, where = lines[i]
    end = i + 1
    while end < len(lines) and (lines[end][0] > col
                                or (lines[end][0] == col and lines[end][3] is owner)):
        end += 1
    new = [line[1] for line in lines]
    new.insert(end, " " * col + f"{key}: 0")
    with pytest.raises(ConfigError) as e:
        load_yaml("\n".join(new) + "\n", "r.yaml")
    assert str(e.value) == f"r.yaml:{end + 1}: {where} given twice (first on line {i + 1})"


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=st.sampled_from(list("ab:- {}[],&*<1\n '\"")), max_size=60))
def test_any_text_loads_as_safe_load_or_is_one_config_error(text):
    try:
        want = repr(yaml.safe_load(text))
    except yaml.YAMLError:
        want = None
    except RecursionError:  # pragma: no cover - PyYAML's own limit
        return
    try:
        got = repr(load_yaml(text, "t.yaml"))
    except ConfigError as e:
        assert "\n" not in str(e)
        assert want is None or " given twice (first on line " in str(e), (text, e)
        return
    assert got == want, text
