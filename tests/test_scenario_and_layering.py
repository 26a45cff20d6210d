import ast
import re
from pathlib import Path

import numpy as np
import pytest

from ngnav.paper import load_paper_table
from ngnav.scenario import load_tilt_table, shipped_scenarios

ROOT = Path(__file__).resolve().parents[1]


def test_every_scenario_parameter_has_a_reason():
    for name in shipped_scenarios():
        lines = (ROOT / "ngnav" / "scenarios" / f"{name}.toml").read_text().splitlines()
        for i, line in enumerate(lines):
            if re.match(r"^[a-z_]+\s*=", line):
                assert lines[i - 1].startswith("# "), (
                    f"{name}.toml line {i + 1} has no reason: {line}"
                )


def test_scenario_errors_name_key_and_file(tmp_path):
    with pytest.raises(ValueError, match=r"tilt-table.toml: unknown key sensor.nois"):
        load_tilt_table(overrides=["sensor.nois=1"])
    with pytest.raises(ValueError, match=r"sensor.noise_mv: expected a number"):
        load_tilt_table(overrides=["sensor.noise_mv=fast"])
    p = tmp_path / "s.toml"
    p.write_text("[run]\nseed = 1\n")
    with pytest.raises(ValueError, match=r"s.toml: missing key run.rate_hz"):
        load_tilt_table(str(p))
    with pytest.raises(ValueError, match="unknown scenario"):
        load_tilt_table("no-such-thing")
    assert load_tilt_table(overrides=["sensor.noise_mv=0.5"]).sensor.noise_mv == 0.5


def test_shipped_table_matches_shared_data():
    shared = ROOT.parent / "shared" / "data" / "paper_table1.csv"
    if not shared.exists():
        pytest.skip("shared/ is not beside this checkout")
    rows = np.loadtxt(shared, delimiter=",", skiprows=1)
    t = load_paper_table()
    np.testing.assert_array_equal(
        np.column_stack([t.platform_deg, t.measured_deg, t.compensated_deg]), rows
    )


def _imported_packages(path: Path) -> set[str]:
    """Top-level names a module imports (anywhere in it, functions included)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out


#: The composition roots: the only core modules that wire filters and telemetry together.
COMPOSITION_ROOTS = ("ngnav/cli", "ngnav/api.py")


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [("ngnav", {"filters", "telemetry"}), ("telemetry", {"filters"})],
)
def test_layers_import_in_one_direction(package, forbidden):
    """core <- filters, telemetry; telemetry never imports filters; only the roots wire."""
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith(COMPOSITION_ROOTS):
            continue
        hit = _imported_packages(path) & forbidden
        if hit:
            bad.append(f"{rel} imports {sorted(hit)}")
    assert not bad, "; ".join(bad)


def test_layer_check_sees_a_violation(tmp_path):
    """The check itself catches a function-level import (what a move tends to add)."""
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from filters.pipeline import Pipeline\n    return Pipeline\n")
    assert _imported_packages(f) == {"filters"}


def test_a_retired_setting_reads_at_its_fixed_value_and_is_refused_otherwise(tmp_path):
    """Run directories written before a setting was retired still read."""
    from ngnav.flight_scenario import load_flight
    from ngnav.runconfig import (
        FilterSettings,
        read_run_config_text,
        write_run_config,
    )
    from ngnav.simulate import simulate_flight

    cfg = simulate_flight(load_flight("static"), 0).config
    write_run_config(cfg, tmp_path / "config.toml")
    text = (tmp_path / "config.toml").read_text()
    assert "[filter]" in text
    for key, fixed in FilterSettings.RETIRED.items():
        value = str(fixed).lower()
        old = text.replace("[filter]\n", f"[filter]\n{key} = {value}\n")
        assert read_run_config_text(old, "old.toml").filter == cfg.filter
        flipped = str(not fixed).lower()
        bad = text.replace("[filter]\n", f"[filter]\n{key} = {flipped}\n")
        with pytest.raises(ValueError, match=f"filter.{key} was retired; it is always"):
            read_run_config_text(bad, "old.toml")
