"""What the import-linter contracts (``pyproject.toml``, run by ``lint-imports`` in CI) cannot
see: a private name (``_x``) imported from another module of the package."""

from __future__ import annotations

import ast
from pathlib import Path

import torchseam

PACKAGE = Path(torchseam.__file__).parent


def _private_imports(path: Path) -> list[str]:
    """``file:line: module._name`` for each private name ``path`` imports from another module
    (a private module of its own package, ``from torchseam.vision import _kernels``, is fine)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not (isinstance(node, ast.ImportFrom) and (node.module or "").startswith("torchseam")):
            continue
        for alias in node.names:
            name = alias.name
            if not name.startswith("_") or name.startswith("__"):
                continue
            own_module = (node.module == ".".join(path.relative_to(PACKAGE.parent)
                                                  .with_suffix("").parts[:-1])
                          and (path.parent / f"{name}.py").exists())
            if not own_module:
                found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: "
                             f"{node.module}.{name}")
    return found


def test_no_private_name_is_imported_across_modules():
    bad = [hit for p in sorted(PACKAGE.rglob("*.py")) for hit in _private_imports(p)]
    assert not bad, "make these public in the module that owns them:\n" + "\n".join(bad)
