"""Fixes without an altitude or a velocity component: the filter fuses what they have.

A GPS_INPUT with its altitude flagged ignored, a GPS_RAW_INT (no vertical velocity) or a
gps.csv with empty cells gives fixes with NaN there. The filter gates and fuses the
components given, starts only on a whole fix, and its covariance says what the missing
component leaves unknown.
"""

from dataclasses import replace

import numpy as np
import pytest

from filters.evaluate import run_errors
from filters.pipeline import run_filter
from ngnav.sim.flight_scenario import load_flight
from ngnav.sim.simulate import simulate_flight


@pytest.fixture(scope="module")
def tactical():
    """The short tactical flight (200 Hz array, 10 Hz fixes, 60 s)."""
    return simulate_flight(load_flight("tactical", ["run.rate_hz=200"]), 0)


@pytest.fixture(scope="module")
def whole(tactical):
    return run_filter(tactical.samples, tactical.fixes, tactical.config)


def _without(fixes, alt: bool = False, vd: bool = False, first_whole: int = 1):
    """The fixes with altitude and/or vertical velocity removed after the first few."""
    a = fixes.alt_m.copy()
    v = fixes.vel_ned_mps.copy()
    if alt:
        a[first_whole:] = np.nan
    if vd:
        v[first_whole:, 2] = np.nan
    return replace(fixes, alt_m=a, vel_ned_mps=v)


def _z(err: np.ndarray, cov: np.ndarray, i: int) -> np.ndarray:
    return np.abs(err[:, i]) / np.sqrt(cov[:, i, i])


def test_fixes_without_altitude_fuse_the_horizontal(tactical, whole):
    """Every fix after the first without altitude: the horizontal is fused as before, the
    vertical position is held by the vertical velocity alone, so its sigma stays near the
    first fix's 3 m where whole fixes average it down; errors stay inside their sigmas."""
    res = run_filter(tactical.samples, _without(tactical.fixes, alt=True), tactical.config)
    assert res.counts["gps fixes used"] == whole.counts["gps fixes used"]
    est = res.estimates
    err = run_errors(est, tactical.truth)
    end = est.t_s > 50.0
    sd_d = np.sqrt(est.cov_nav[end, 2, 2])
    sd_d_whole = np.sqrt(whole.estimates.cov_nav[end, 2, 2])
    assert sd_d.min() > 2.0 and sd_d_whole.max() < 1.0
    for i in range(3):
        assert _z(err.pos_ned_m, est.cov_nav, i).max() < 4.5
    # the horizontal is as good as with whole fixes
    h = np.sqrt(np.mean(np.sum(err.pos_ned_m[:, :2] ** 2, axis=1)))
    err_w = run_errors(whole.estimates, tactical.truth)
    h_w = np.sqrt(np.mean(np.sum(err_w.pos_ned_m[:, :2] ** 2, axis=1)))
    assert h < 1.1 * h_w
    # the 3-dof NIS is not computed for a 2-dof position
    assert np.isnan(res.innovations.nis_pos[1:]).all()
    assert np.isfinite(res.innovations.nis_vel).all()


def test_fixes_without_vertical_velocity(tactical, whole):
    """Every fix after the first without vertical velocity (GPS_RAW_INT): the vertical
    velocity is learnt from the altitudes; consistent, and less sure than with it."""
    res = run_filter(tactical.samples, _without(tactical.fixes, vd=True), tactical.config)
    est = res.estimates
    err = run_errors(est, tactical.truth)
    for i in range(3):
        assert _z(err.vel_ned_mps, est.cov_nav[:, 3:6, 3:6], i).max() < 4.5
    late = est.t_s > 10.0
    assert np.median(est.cov_nav[late, 5, 5]) > 2.0 * np.median(whole.estimates.cov_nav[late, 5, 5])


def test_the_filter_starts_on_the_first_whole_fix(tactical):
    """Fixes without altitude before it cannot start the filter (they are counted as
    before the start); the first whole fix does."""
    fixes = tactical.fixes
    a = fixes.alt_m.copy()
    a[:5] = np.nan
    res = run_filter(tactical.samples, replace(fixes, alt_m=a), tactical.config)
    assert res.counts["gps fix that started the filter"] == 1
    assert res.counts["gps fixes before the filter start"] == 5
    assert res.estimates.t_s[0] == pytest.approx(fixes.t_s[5], abs=3e-3)


def test_no_whole_fix_is_a_clear_error(tactical):
    """A run whose fixes all lack their altitude cannot start: one line naming why."""
    fixes = _without(tactical.fixes, alt=True, first_whole=0)
    with pytest.raises(ValueError, match="altitude"):
        run_filter(tactical.samples, fixes, tactical.config)
