import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ngnav.grey import GreyModel11, auto_shift, one_step_forecast
from ngnav.predictors import GreyPredictor

X0 = [27260, 29547, 32411, 35388]


def test_published_reference_values():
    m = GreyModel11().fit(X0)
    assert m.a_ == pytest.approx(-0.0899951724, abs=1e-10)
    assert m.b_ == pytest.approx(25790.28384, abs=1e-5)
    np.testing.assert_allclose(m.fitted_, [27260, 29553.442, 32336.460, 35381.552], atol=1e-3)
    assert m.forecast()[0] == pytest.approx(38713.398, abs=1e-3)
    q = m.quality()
    assert q.ratio_admissible and q.grade == "good"


@given(c=st.floats(0.1, 1e4), r=st.floats(0.5, 1.5), n=st.integers(4, 12))
def test_geometric_sequence_identity(c, r, n):
    m = GreyModel11(shift=None).fit(c * r ** np.arange(n))
    assert m.a_ == pytest.approx(2 * (1 - r) / (1 + r), rel=1e-8, abs=1e-12)
    assert m.b_ == pytest.approx(2 * c / (1 + r), rel=1e-8)


def test_restore_equals_difference_of_time_response():
    m = GreyModel11().fit(X0)
    a, b = m.a_, m.b_
    k = np.arange(0, 6)
    x1 = (X0[0] - b / a) * np.exp(-a * k) + b / a
    np.testing.assert_allclose(m._restore(k[1:]), np.diff(x1), rtol=1e-12)


def test_nearly_constant_window_keeps_precision():
    x = 5.0 + 1e-9 * np.arange(8)
    assert GreyModel11().fit(x).forecast()[0] - 5.0 == pytest.approx(8e-9, rel=1e-3)
    assert one_step_forecast(x)[0] - 5.0 == pytest.approx(8e-9, rel=1e-3)


def test_constant_and_signed_input():
    assert GreyModel11().fit([3.0] * 5).forecast()[0] == pytest.approx(3.0, abs=1e-12)
    m = GreyModel11().fit([-1.0, -0.5, 0.2, 0.6, 1.1])
    assert m.shift_ == pytest.approx(1.0 + 2.1)
    assert np.isfinite(m.forecast(3)).all()
    assert m.fitted_[0] == -1.0


def test_bad_input_errors():
    with pytest.raises(ValueError, match="at least 4"):
        GreyModel11().fit([1, 2, 3])
    with pytest.raises(ValueError, match="not finite"):
        GreyModel11().fit([1, 2, np.nan, 4])
    with pytest.raises(ValueError, match="positive"):
        GreyModel11(shift=None).fit([1, 2, 0, 4])
    with pytest.raises(RuntimeError, match="not fitted"):
        GreyModel11().forecast()
    with pytest.raises(ValueError, match="steps"):
        GreyModel11().fit(X0).forecast(0)
    with pytest.raises(ValueError, match="at least 4"):
        GreyPredictor(window=3)


@given(seed=st.integers(0, 2**32 - 1), n=st.integers(4, 10))
def test_vectorised_forecast_equals_model(seed, n):
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(6, n)) * rng.uniform(0.1, 10, (6, 1)) + rng.normal(0, 5, (6, 1))
    vec, fell = one_step_forecast(w)
    for i in range(6):
        m = GreyModel11().fit(w[i])
        if fell[i]:
            assert vec[i] == w[i, -1]
        else:
            assert vec[i] == pytest.approx(m.forecast()[0], rel=1e-9, abs=1e-9 * np.abs(w[i]).max())


@given(seed=st.integers(0, 2**32 - 1))
def test_loop_predictor_fast_path_equals_general(seed):
    rng = np.random.default_rng(seed)
    shift = np.repeat([2.1, 245.0, 24.5], 3)
    hist = rng.normal(size=(5, 9)) * np.repeat([0.5, 3.0, 5.0], 3)
    fast, _ = GreyPredictor(5, shift=shift).forecast(hist, 0)
    ref, _ = one_step_forecast(hist.T, shift)
    np.testing.assert_allclose(fast, ref, rtol=1e-10, atol=1e-10)


def test_auto_shift_rule():
    assert auto_shift(np.array([1.0, 2.0])) == 0.0
    assert auto_shift(np.array([-1.0, 2.0])) == pytest.approx(4.0)
    assert auto_shift(np.array([0.0, 0.0])) == pytest.approx(1.0)
