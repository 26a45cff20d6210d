import ast
import re
from pathlib import Path

import numpy as np
import pytest

from ngnav.config import shipped_scenarios
from ngnav.paper import load_paper_table
from ngnav.sim.tilt_table import load_tilt_table

ROOT = Path(__file__).resolve().parents[1]


def test_every_scenario_parameter_has_a_reason():
    for name in shipped_scenarios():
        lines = (ROOT / "ngnav" / "sim" / "scenarios" / f"{name}.toml").read_text().splitlines()
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


#: A tactical run's ``[filter]`` as ngnav wrote it before the settings were grouped.
LEGACY_FILTER = """[filter]
rate_hz = 100.0
compensation = "gm11"
window = 5
gate_probability = 0.9999
rate_range_dps = 200.0
sideslip_sigma_deg = 3e-06
aoa_sigma_deg = 3e-06
aoa_prior_deg = -1.5
aoa_prior_sigma_deg = 1.0
aoa_rw_deg_rts = 0.0
aoa_lift_k_m = 18.0
aoa_lift_k_sigma_m = 0.9
liftoff_speed_mps = 0.0
gps_gap_reset_s = 5.0
fusion_lag_s = 0.1
hold_wdot_sigma_rps2 = 2.0
hold_force_sigma_mps2 = 3.0
position_states = true
remainder_updates = 4.0
attitude_remainder_updates = 7.0
coast_remainder_updates = 10.0
coast_after_s = 1.0
forecast_error_persistence = 1.0
forecast_correction = true
remainder_off_constraint = false
vehicle_model_rate_hz = 5.0
count_by_prior_weight = true
body_velocity_error = true
position_consider = false
remainder_consider = false
rest_rate_sigma_dps = 0.0
"""


def test_a_run_written_before_the_settings_were_grouped_still_reads(tmp_path):
    """The old flat ``[filter]`` maps onto today's groups with the same meaning; a value
    that is no longer settable must be the one now fixed, and is refused otherwise."""
    from ngnav.runconfig import read_run_config_text, run_config_text
    from ngnav.sim.flight_scenario import load_flight
    from ngnav.sim.simulate import simulate_flight

    cfg = simulate_flight(load_flight("tactical"), 0).config
    text = run_config_text(cfg)
    old = text[: text.index("[filter]")] + LEGACY_FILTER
    got = read_run_config_text(old, "old.toml")
    for group in ("filter", "compensation", "vehicle", "rest"):
        assert getattr(got, group) == getattr(cfg, group), group
    free = old.replace("sideslip_sigma_deg = 3e-06", "sideslip_sigma_deg = 0.0")
    with pytest.raises(ValueError, match=r"filter\.sideslip_sigma_deg is no longer a setting"):
        read_run_config_text(free, "old.toml")
    retired = (("gate_probability", "0.99"), ("remainder_consider", "true"))
    for key, value in (*retired, ("position_states", "false")):
        bad = old.replace(f"{key} = ", f"{key} = {value}\n# ")
        with pytest.raises(ValueError, match=rf"old.toml: filter\.{key} is no longer a setting"):
            read_run_config_text(bad, "old.toml")
    both = old + '\n[compensation]\nmethod = "none"\n'
    with pytest.raises(ValueError, match=r"filter\.compensation and compensation\.method both"):
        read_run_config_text(both, "old.toml")


@pytest.mark.parametrize(
    ("override", "says"),
    [
        ("filter.gps_gap_reset_s=3", "filter.gps_gap_reset_s is no longer a setting; it is 5.0"),
        ("filter.compensation=none", "filter.compensation is now compensation.method"),
        ("filter.sideslip_sigma_deg=0", 'vehicle.kind = "fixed-wing" has 3e-06'),
        ("filter.position_states=false", "position_sigma_m is always carried as states"),
    ],
)
def test_an_override_of_an_old_key_says_what_became_of_it(override, says):
    from ngnav.sim.flight_scenario import load_flight

    with pytest.raises(ValueError, match=re.escape(says)):
        load_flight("tactical", [override])
