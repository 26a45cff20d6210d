"""The compensation inside the filter: the forecast's predictor, its window, and the noise
its errors add (the block's own forecast error, and held samples').
"""

from __future__ import annotations

import numpy as np

from ngnav.predictors import GreyPredictor, LastValuePredictor, LinePredictor

#: The GM(1,1) forecast's window, blocks (the paper's).
GM_WINDOW = 5
#: The body-rate range the forecasts are held to, rad/s.
RATE_RANGE_RPS = float(np.deg2rad(200.0))
#: Held samples (invalid or saturated): the forecast that replaces them drifts from the
#: motion as a random walk of this angular acceleration, rad/s^2 per sqrt(s), and force,
#: m/s^2 per sqrt(s).
HOLD_WDOT_SIGMA_RPS2 = 2.0
HOLD_FORCE_SIGMA_MPS2 = 3.0
#: Time constant of the angular acceleration the position states' Jacobian uses, s.
WDOT_SMOOTHING_S = 0.05
#: Blocks the running mean of the forecast's squared error spans (``Pipeline._forecast_noise``):
#: a manoeuvre's onset lasts a few tenths of a second, so a few blocks at 100 Hz.
FORECAST_ERROR_BLOCKS = 5
#: The forecast's error counts only where its running mean square exceeds the noise floor
#: this many times: below, what it would add is at most ``E_6^2`` times the floor, about
#: 1 % of a block's feature noise (``E_6`` about 0.07), and skipping it saves the block's
#: covariance arithmetic (at rest a 5-block mean of squares passes 2 with chance 0.075).
FORECAST_ERROR_GATE = 2.0
#: Blocks' worth of the forecast's measured error variance one block counts in the rate
#: and velocity noise without the forecast correction (``1 + 2 sum_k rho_k`` of the error's
#: autocorrelation): over ``tactical``'s roll-ins the angular acceleration's reads 0.72,
#: 0.3 and 0.1 at lags of 1, 2 and 5 blocks. With the correction, which takes the error
#: out of the state, no noise is added: counted once, it moved no NEES block of runs 0-49
#: by more than 1.0 point on ``tactical`` or ``uav-survey`` (docs/design.md).
FORECAST_ERROR_PERSISTENCE = 2.0


def make_predictor(name: str, window: int, shift: np.ndarray):
    if name == "gm11":
        return GreyPredictor(window=window, shift=shift)
    if name == "line":
        return LinePredictor(window=window)
    if name == "last":
        return LastValuePredictor()
    return None
