"""The README is a user's guide that works as written.

- its ```python blocks run as they stand, in a fresh directory, and print what they say;
- it stays short and free of lab-notebook history (commit hashes, "issue N" headings);
- every ``ngnav COMMAND`` in its validation table is a real sub-command.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES = 300

#: The Python quickstart's printed line.
QUICKSTART_LINE = re.compile(
    r"^(?P<epochs>\d+) epochs, horizontal RMS (?P<rms>\d+\.\d+) m, "
    r"(?P<inside>\d+\.\d) % of errors inside 3 sigma$"
)
#: A word that looks like an abbreviated or full git commit hash.
HASH_LIKE = re.compile(r"\b[0-9a-f]{7,40}\b")


def _readme() -> str:
    return README.read_text(encoding="utf-8")


def python_blocks(text: str) -> list[str]:
    """The bodies of the ```python fenced blocks, in order."""
    return re.findall(r"^```python[ \t]*\n(.*?)^```[ \t]*$", text, flags=re.MULTILINE | re.DOTALL)


def section(text: str, heading: str) -> str:
    """The text of the ``## heading`` section, up to the next ``##`` heading."""
    m = re.search(rf"^## {re.escape(heading)}[ \t]*\n(.*?)(?=^## |\Z)", text, re.M | re.S)
    assert m, f"README has no '## {heading}' section"
    return m.group(1)


def hash_like_words(text: str) -> list[str]:
    """Words of 7-40 hex digits holding both a digit and a letter a-f."""
    return [w for w in HASH_LIKE.findall(text) if re.search(r"[0-9]", w) and re.search(r"[a-f]", w)]


def test_python_blocks_are_found():
    assert python_blocks(_readme()), "README has no ```python block"


@pytest.mark.parametrize("index", range(len(python_blocks(_readme()))))
def test_python_block_runs_as_written(index, tmp_path):
    code = python_blocks(_readme())[index]
    script = tmp_path / f"readme_block_{index}.py"
    script.write_text(code, encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, str(script)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines, "the block printed nothing"
    if "horizontal RMS" in code:
        m = QUICKSTART_LINE.match(lines[-1])
        assert m, f"unexpected output: {lines[-1]!r}"
        assert int(m["epochs"]) > 1000
        assert float(m["rms"]) < 2.0
        assert 0.0 <= float(m["inside"]) <= 100.0


def test_the_quickstart_prints_its_summary_line():
    assert any("horizontal RMS" in b for b in python_blocks(_readme()))


def test_readme_is_short():
    n = len(_readme().splitlines())
    assert n <= MAX_LINES, f"README has {n} lines, at most {MAX_LINES}"


def test_readme_has_no_commit_hashes():
    assert hash_like_words(_readme()) == []


def test_hash_check_sees_a_hash():
    assert hash_like_words("measured at 7d71300, 2.03 deg, facade 1234567") == ["7d71300"]


def test_readme_has_no_issue_headings():
    bad = [
        line
        for line in _readme().splitlines()
        if line.startswith("#") and re.search(r"\bissues?\s*#?\d+", line, re.I)
    ]
    assert bad == []


def _subcommands() -> set[str]:
    proc = subprocess.run(
        [sys.executable, "-m", "ngnav", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    # argparse lists each sub-command at a 4-space indent under COMMAND
    return set(re.findall(r"^ {4}([a-z][a-z0-9-]*)(?:\s|$)", proc.stdout, re.M))


def test_validation_table_names_real_commands():
    table = [line for line in section(_readme(), "Validation").splitlines() if line.startswith("|")]
    named = {m for line in table for m in re.findall(r"\bngnav ([a-z][a-z0-9-]*)", line)}
    assert len(named) >= 5, f"the validation table names too few commands: {sorted(named)}"
    known = _subcommands()
    assert {"paper", "run", "evaluate", "consistency"} <= known, sorted(known)
    assert named <= known, f"not ngnav sub-commands: {sorted(named - known)}"


def test_the_design_page_names_where_each_constant_lives():
    """Every UPPER_CASE constant the heuristics table names is defined in the module its
    row names (a move that leaves the page behind fails here)."""
    rows = [
        ln.split("|")
        for ln in (ROOT / "docs" / "design.md").read_text().splitlines()
        if ln.startswith("| `") and "`filters/" in ln
    ]
    checked = 0
    for cells in rows:
        modules = re.findall(r"`(filters/[a-z_]+\.py)`", cells[3])
        for name in re.findall(r"`([A-Z][A-Z0-9_]+)`", cells[1]):
            text = "".join((ROOT / m).read_text() for m in modules)
            assert re.search(rf"^{name}\b[^=\n]*=", text, re.M), (name, modules)
            checked += 1
    assert checked >= 25
