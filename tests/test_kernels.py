"""The one loader of the packages' compiled kernels (torchseam.core.kernels)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from torchseam.core.errors import TorchseamError
from torchseam.core.kernels import KernelError, load_kernels


def _package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str, kernels: str) -> str:
    (tmp_path / name).mkdir()
    (tmp_path / name / "__init__.py").write_text("")
    (tmp_path / name / "_kernels.py").write_text(kernels)
    monkeypatch.syspath_prepend(str(tmp_path))
    return name


def test_loads_each_package_own_kernels_once() -> None:
    k = load_kernels("torchseam.track")
    assert k.__name__ == "torchseam.track._kernels" and hasattr(k, "peak_quality")
    assert load_kernels("torchseam.track") is k
    assert load_kernels("torchseam.vision").__name__ == "torchseam.vision._kernels"
    assert load_kernels("torchseam.geometry").__name__ == "torchseam.geometry._kernels"
    with pytest.raises(ValueError, match="__package__"):
        load_kernels(None)


def test_missing_numba_is_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = _package(tmp_path, monkeypatch, "kpkg_nonumba", "import numba\n")
    monkeypatch.setitem(sys.modules, "numba", None)  # as if not installed
    with pytest.raises(KernelError, match=r"kpkg_nonumba\._kernels: .*need numba") as e:
        load_kernels(pkg)
    assert isinstance(e.value, TorchseamError)


def test_failed_compilation_is_a_clear_error(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = _package(tmp_path, monkeypatch, "kpkg_broken",
                   "raise TypeError('cannot type x')\n")
    with pytest.raises(KernelError, match=r"kpkg_broken\._kernels: compiling the kernels "
                                          r"failed \(TypeError: cannot type x\)"):
        load_kernels(pkg)


def test_other_import_errors_pass_through(tmp_path: Path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    pkg = _package(tmp_path, monkeypatch, "kpkg_other", "import not_a_module_xyz\n")
    with pytest.raises(ModuleNotFoundError, match="not_a_module_xyz"):
        load_kernels(pkg)
