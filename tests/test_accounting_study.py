"""The step accounting study (``python -m studies.accounting``)."""

import json

import numpy as np
import pytest

from filters.ekf import NavFilter
from filters.nominal import NominalMixin
from filters.updates import Measurement
from ngnav.sim.flight_scenario import load_flight
from studies.accounting import KINDS, StepLog, account_run, step_kind, window_excess
from tests.helpers import SHORT_TACTICAL_ARGS, level_filter, run_study


def test_each_update_is_sorted_by_the_columns_it_reads():
    nf, _, _ = level_filter()
    bias = nf.layout.bias
    gps_pos = nf.measure_gps_position(np.zeros(3), 1.0)
    gps_vel = nf.measure_gps_velocity(np.zeros(3), 0.1)
    _, h_rate = nf.rate_model(np.array([[0.1, 0.2, 0.3]]))
    _, h_rate_at_rest = nf.rate_model(np.zeros((1, 3)))  # no rate column at zero rate
    _, h_slip = nf.sideslip_model(nf.q, np.array([10.0, 0.0, 0.0]))
    h_static = np.zeros((6, nf.layout.n))
    h_static[:, bias.start : bias.start + 6] = np.eye(6)

    def kind(h):
        return KINDS[step_kind(Measurement(np.zeros(h.shape[0]), h, np.eye(h.shape[0])), bias)]

    assert kind(gps_pos.H) == "GPS position"
    assert kind(gps_vel.H) == "GPS velocity"
    assert kind(gps_vel.H[0:2]) == "GPS velocity"  # a fix without the vertical velocity
    assert kind(h_rate) == "rate products"
    assert kind(h_rate_at_rest) == "rate products"
    assert kind(h_slip) == "vehicle model"
    assert kind(nf.rate_at_rest_model()) == "zero rate"
    assert kind(h_static) == "static biases"


def _log(t, kind, e0, e1, p0, p1):
    col = [np.asarray(v, dtype=float)[:, None] for v in (e0, e1, p0, p1)]
    return StepLog(np.asarray(t, dtype=float), np.asarray(kind), *col)


def test_window_excess_is_each_kinds_step_sum_averaged_over_runs():
    # run A: a propagation that grows e^2 by 3 where P grows by 1 (excess 2 over P 2: 1.0),
    # and a GPS velocity update that does as it says (0); run B: a propagation with excess
    # -0.5 (e^2 0 -> 0.5 where P 1 -> 2) and one outside the window
    a = _log([1.0, 2.0], [0, 3], [1.0, 2.0], [2.0, 1.0], [2.0, 3.0], [3.0, 0.0])
    b = _log([1.5, 7.0], [0, 0], [0.0, 0.0], [np.sqrt(0.5), 5.0], [1.0, 1.0], [2.0, 1.0])
    (w, w2) = window_excess([a, b], 5.0)
    prop, vel = w["kinds"]["propagation"], w["kinds"]["GPS velocity"]
    assert (w["t0_s"], w["t1_s"]) == (0.0, 5.0)
    assert prop["excess"] == pytest.approx((1.0 - 0.5) / 2)
    assert prop["se"] == pytest.approx(np.std([1.0, -0.5], ddof=1) / np.sqrt(2))
    assert (prop["steps"], vel["steps"]) == (2, 1)
    # run A's update: e^2 4 -> 1 (-3), P 3 -> 0 (-3): no excess; run B had none (0)
    assert vel["excess"] == pytest.approx(0.0)
    assert w["kinds"]["rate products"]["steps"] == 0
    assert w2["kinds"]["propagation"]["steps"] == 1


def test_a_run_is_observed_step_by_step_and_the_filter_is_left_as_it_was():
    apply = NavFilter._apply
    scn = load_flight("tactical", ["run.rate_hz=200"])
    log = account_run(scn, 0, ("heading", "yaw_rate", "vel_n"))
    assert NavFilter.propagate is NominalMixin.propagate
    assert NavFilter._apply is apply
    assert log.err_before.shape == log.err_after.shape == (log.t_s.shape[0], 3)
    kinds = {KINDS[k] for k in np.unique(log.kind)}
    assert {"propagation", "rate products", "GPS position", "GPS velocity"} <= kinds
    assert "vehicle model" in kinds  # tactical flies the fixed-wing models
    assert np.all(np.diff(log.t_s) >= 0.0)
    assert np.all(log.var_before > 0.0) and np.all(log.var_after > 0.0)
    # every change of the state is a logged step: one step's after is the next one's before
    # (a heading set from the course or a reset onto a fix would not be; tactical has none)
    np.testing.assert_array_equal(log.err_after[:-1], log.err_before[1:])
    np.testing.assert_array_equal(log.var_after[:-1], log.var_before[1:])


def test_the_bias_states_are_followed_against_the_solves_image_of_the_channel_biases():
    # a wrong map (the channel biases unsolved, or in g) reads tens of sigmas: the filter
    # learns the biases in flight
    scn = load_flight("tactical", ["run.rate_hz=200"])
    comps = ("wdot_bias_x", "wdot_bias_y", "wdot_bias_z", "f_bias_x", "f_bias_y", "f_bias_z")
    log = account_run(scn, 0, comps)
    z = log.err_after / np.sqrt(log.var_after)
    assert np.abs(z).max() < 5.0
    assert 0.05 < float(np.mean(z**2)) < 3.0
    np.testing.assert_array_equal(log.err_after[:-1], log.err_before[1:])


def test_an_unknown_component_is_named():
    scn = load_flight("tactical", ["run.rate_hz=200"])
    with pytest.raises(ValueError, match="unknown component 'heading_rate'"):
        account_run(scn, 0, ("heading_rate",))


def test_command_line():
    proc = run_study(
        "accounting",
        *SHORT_TACTICAL_ARGS,
        "--runs",
        "2",
        "--workers",
        "1",
        "--window",
        "30",
        "--component",
        "heading",
        "--json",
    )
    out = json.loads(proc.stdout)
    assert out["runs"] == 2 and out["window_s"] == 30.0
    (windows,) = out["components"].values()
    assert [w["t0_s"] for w in windows][:2] == [0.0, 30.0]
    assert set(windows[0]["kinds"]) == set(KINDS)
    bad = run_study("accounting", "--runs", "1", check=False)
    assert bad.returncode == 2 and "at least 2 runs" in bad.stderr
