"""The installed package must contain every subpackage and the kernels: pyproject.toml
lists packages explicitly (cl_kernels/ is mapped to clscatter.cl_kernels), so check that
the list keeps up with the tree."""
from __future__ import annotations

import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed():
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())
    listed = set(cfg["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "clscatter").rglob("__init__.py")}
    assert found - listed == set(), f"add to pyproject.toml [tool.setuptools] packages: {sorted(found - listed)}"
    assert "clscatter.cl_kernels" in listed
    data = cfg["tool"]["setuptools"]["package-data"]["clscatter.cl_kernels"]
    assert "*.cl" in data and "*.h" in data


def test_kernel_sources_are_found():
    from clscatter.device import kernel_dir
    kd = kernel_dir()
    assert (kd / "common.h").is_file() and (kd / "view_paths.cl").is_file()
