"""pyproject.toml lists drivectl's packages by hand: every folder with an __init__.py must be listed."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_every_subpackage_is_listed_for_a_non_editable_install():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    on_disk = {"drivectl"}
    for init in ROOT.rglob("__init__.py"):
        rel = init.parent.relative_to(ROOT)
        if rel.parts and rel.parts[0] in {".venv", "tests", "bench", "build", "docs"}:
            continue
        on_disk.add(".".join(("drivectl",) + rel.parts))
    assert on_disk == listed
