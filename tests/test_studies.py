"""The studies (research kept out of the installed packages) still run from a checkout."""

from tests.helpers import run_study


def test_calibration_study_runs_and_compares_the_two_methods():
    """Eq. 27 against multi-position least squares on a few simulated cubes."""
    out = run_study("calibration", "--runs", "3").stdout
    assert "eq. 27 cone-angle error, RMS" in out and "multi-position" in out
    assert out.strip().splitlines()[-1].startswith("use: ")


def test_a_study_reports_bad_input_in_one_line():
    proc = run_study("calibration", "--runs", "3", "--set", "sensor.noise_mvv=1", check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "did you mean sensor.noise_mv?" in proc.stderr
