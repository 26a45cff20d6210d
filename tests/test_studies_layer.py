"""Research stays out of the installed packages: none of them imports ``studies``."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _imports_studies(path: Path) -> bool:
    """Whether a module imports ``studies`` anywhere (functions included)."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            if any(a.name.split(".")[0] == "studies" for a in node.names):
                return True
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.split(".")[0] == "studies":
                return True
    return False


def test_installed_packages_never_import_studies():
    bad = [
        path.relative_to(ROOT).as_posix()
        for package in ("ngnav", "filters", "telemetry")
        for path in sorted((ROOT / package).rglob("*.py"))
        if _imports_studies(path)
    ]
    assert not bad, bad


def test_the_check_sees_a_function_level_import(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from studies.control import fix_noise\n    return fix_noise\n")
    assert _imports_studies(f)
    f.write_text("import numpy\nfrom filters.consistency import consistency\n")
    assert not _imports_studies(f)
