"""The wheel's package list is complete: every folder of the package and of recipes/ ships."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setuptools() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed():
    listed = set(_setuptools()["packages"])
    mapped = _setuptools()["package-dir"]
    found = set()
    for init in (ROOT / "torchrl_silp").rglob("__init__.py"):
        found.add(".".join(init.parent.relative_to(ROOT).parts))
    for package, folder in mapped.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            found.add(".".join((package, *init.parent.relative_to(ROOT / folder).parts)))
    missing = sorted(found - listed)
    assert not missing, f"pyproject.toml's packages lacks {missing}"
    # and nothing listed is a folder that no longer exists
    for package in listed:
        folder = mapped.get(package) or package.replace(".", "/")
        assert (ROOT / folder).is_dir(), package


def test_package_data_covers_the_recipe_configs_and_urdfs():
    data = _setuptools()["package-data"]
    mapped = _setuptools()["package-dir"]
    for package, patterns in data.items():
        folder = ROOT / mapped.get(package, package.replace(".", "/"))
        covered = {p for pattern in patterns for p in folder.glob(pattern)}
        wanted = {p for p in folder.rglob("*") if p.suffix in (".yaml", ".urdf")}
        assert wanted <= covered, sorted(str(p) for p in wanted - covered)
        assert covered, package
