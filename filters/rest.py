"""Rest detection for the zero-rate update: is the vehicle standing still?

A gyro-free array senses angular acceleration and specific force, not the rate, and GPS
senses the velocity. :class:`RestDetector` says "at rest" when both agree that nothing
moves:

- *entering* rest takes :data:`CONFIRM_S` of GPS fixes whose velocity is consistent with
  zero (chi-square, 3 dof, false-alarm :data:`FIX_STILL_FALSE_ALARM`) and of steady array
  blocks (below), the last fix no older than :data:`FIX_MAX_AGE_S`;
- rest *holds* while the array stays steady and no fix reads motion, GPS outages
  included: a vehicle cannot start to move or turn without an angular acceleration or a
  change of specific force that the array sees.

A block is steady when its mean angular acceleration and specific force are consistent
with the rest's reference, by chi-square tests on the blocks' noise: one block alone
(false alarm :data:`FAST_FALSE_ALARM`, 6 dof) and an exponential mean over
:data:`SLOW_TAU_S` (the slow onsets one block's noise hides). The features are taken
with their biases in, and the reference is the mean of the steady blocks, forgetting
over :data:`REF_TAU_S`: at rest it is the biases (and gravity), so neither the sensors'
bias walk nor the filter's corrections of its bias estimates read as motion. A failed
test ends the rest at once and restarts the confirmation.

What it cannot see: a steady spin with no angular acceleration and no change of force
(a hovering multirotor yawing in place at constant rate, a turntable). The zero-rate
update's own gate (:meth:`filters.ekf.NavFilter.update_zero_rate`) rejects the update
when the filter's rate contradicts zero, which ends the rest (:meth:`RestDetector.interrupt`);
a spin that starts before the filter does is not caught, which is why the update is off
by default (``rest.rate_sigma_dps``).

This is the stance-phase idea of zero-velocity detectors for inertial navigation
(Skog, Handel, Nilsson and Rantakokko, "Zero-velocity detection: an algorithm
evaluation", IEEE Trans. Biomed. Eng. 57(11), 2010: a chi-square test of the specific
force against gravity's direction and of the rate against zero), with the angular
acceleration in the rate's place and GPS velocity to tell rest from steady flight, whose
array output is the same.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

#: False-alarm probability of one block's steadiness test (6 dof).
FAST_FALSE_ALARM = 1e-6
#: Time constant of the exponential mean the slow test reads, s.
SLOW_TAU_S = 0.5
#: False-alarm probability of the slow test, per block (6 dof).
SLOW_FALSE_ALARM = 1e-6
#: Forgetting time of the rest's reference specific force, s.
REF_TAU_S = 10.0
#: Steady array and still fixes needed to enter rest, s.
CONFIRM_S = 1.0
#: False-alarm probability of a fix's "velocity is zero" test (3 dof).
FIX_STILL_FALSE_ALARM = 1e-3
#: The newest still fix may be this old when rest is entered, s.
FIX_MAX_AGE_S = 1.0


@dataclass
class RestDetector:
    """Decides from array blocks and GPS fixes whether the vehicle is at rest.

    Parameters
    ----------
    feature_cov : ndarray, shape (6, 6)
        Per-sample covariance of the solved ``[wdot (rad/s^2), f (m/s^2)]`` features,
        body frame (FRD): a block mean of ``k`` samples has ``feature_cov / k``.
    block_s : float
        Duration of one block (the filter step), s.
    block_samples : int
        Samples in a full block (the nominal ``k`` for the exponential means).
    """

    feature_cov: np.ndarray
    block_s: float
    block_samples: int
    at_rest: bool = False
    #: blocks that failed a steadiness test (each one ended or delayed a rest)
    unsteady_blocks: int = 0
    #: fixes whose velocity read motion
    moving_fixes: int = 0
    _info: np.ndarray = field(init=False, repr=False)
    _ref: np.ndarray | None = field(default=None, init=False, repr=False)
    _v_ref: float = field(default=0.0, init=False, repr=False)
    _slow: np.ndarray = field(init=False, repr=False)
    _v_slow: float = field(default=0.0, init=False, repr=False)
    _t_steady: float = field(default=np.inf, init=False, repr=False)
    _t_still: float = field(default=np.inf, init=False, repr=False)
    _t_last_still: float = field(default=-np.inf, init=False, repr=False)

    def __post_init__(self) -> None:
        cov = np.asarray(self.feature_cov, dtype=float)
        if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
            raise ValueError(f"feature_cov must be a finite (6, 6) matrix, got shape {cov.shape}")
        if not (np.isfinite(self.block_s) and self.block_s > 0.0):
            raise ValueError(f"block_s must be finite and > 0, got {self.block_s}")
        if int(self.block_samples) < 1:
            raise ValueError(f"block_samples must be >= 1, got {self.block_samples}")
        try:
            np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            raise ValueError("feature_cov must be positive definite") from None
        self.feature_cov = cov
        self._info = np.linalg.inv(cov)
        self._slow = np.zeros(6)
        self._fast_limit = float(chi2.isf(FAST_FALSE_ALARM, 6))
        self._slow_limit = float(chi2.isf(SLOW_FALSE_ALARM, 6))
        self._still_limit = float(chi2.isf(FIX_STILL_FALSE_ALARM, 3))
        self._a_slow = min(1.0, self.block_s / SLOW_TAU_S)
        self._a_ref = min(1.0, self.block_s / REF_TAU_S)

    # ------------------------------------------------------------------ inputs
    def start_at_rest(self, t_s: float, ref_features: np.ndarray, ref_blocks: float) -> None:
        """Start at rest (a static alignment) with its mean ``[wdot, f]`` (6,), biases in.

        ``ref_blocks`` is how many blocks' worth of samples that mean holds (its
        variance is a block's over ``ref_blocks``).
        """
        x = np.asarray(ref_features, dtype=float)
        if x.shape != (6,) or not np.all(np.isfinite(x)):
            raise ValueError(f"ref_features must be a finite (6,) vector, got {x!r}")
        self._restart(t_s - CONFIRM_S, x, 1.0 / max(float(ref_blocks), 1.0))
        self._t_still = self._t_last_still = t_s
        self.at_rest = True

    def observe_fix(self, t_s: float, vel_ned_mps: np.ndarray, vel_acc_mps: float) -> None:
        """A GPS fix: its NED velocity (3,) and that velocity's 1-sigma per axis, m/s.

        A fix without a usable velocity (not finite, or no accuracy) says nothing.
        """
        v = np.asarray(vel_ned_mps, dtype=float)
        if not (np.all(np.isfinite(v)) and np.isfinite(vel_acc_mps) and vel_acc_mps > 0.0):
            return
        if float(v @ v) / (vel_acc_mps * vel_acc_mps) <= self._still_limit:
            if not np.isfinite(self._t_still):
                self._t_still = t_s
            self._t_last_still = t_s
        else:
            self.moving_fixes += 1
            self._t_still = np.inf
            self.at_rest = False

    def observe_block(self, t_s: float, features: np.ndarray, n_samples: int) -> bool:
        """One block's mean features at its end time; returns ``at_rest``.

        Parameters
        ----------
        t_s : float
            The block's end, s.
        features : ndarray, shape (6,)
            Mean angular acceleration (rad/s^2) and specific force (m/s^2) over the
            block, FRD, biases in (compensated for the mounting errors).
        n_samples : int
            Samples in the mean (its noise is ``feature_cov / n_samples``).
        """
        x = np.asarray(features, dtype=float)
        if x.shape != (6,):
            raise ValueError(f"features must be a (6,) vector, got shape {x.shape}")
        if not np.all(np.isfinite(x)) or n_samples < 1:
            return self.at_rest  # nothing to judge this block by
        if self._ref is None:
            self._restart(t_s, x, float(self.block_samples) / n_samples)
            return self.at_rest
        d = x - self._ref
        unit = 1.0 / float(self.block_samples)  # one nominal block's variance factor
        a = self._a_slow
        slow = self._slow + a * (d - self._slow)
        v_slow = (1.0 - a) ** 2 * self._v_slow + a * a
        if (
            float(d @ self._info @ d) / (1.0 / n_samples + unit * self._v_ref) > self._fast_limit
            or float(slow @ self._info @ slow) / (unit * (v_slow + self._v_ref)) > self._slow_limit
        ):
            self.unsteady_blocks += 1
            self.at_rest = False
            self._restart(t_s, x, float(self.block_samples) / n_samples)
            return False
        self._slow, self._v_slow = slow, v_slow
        # the reference: the steady blocks' mean, forgetting over REF_TAU_S
        w = max(self._a_ref, self._v_ref / (self._v_ref + 1.0))
        self._ref = self._ref + w * (x - self._ref)
        self._v_ref = (1.0 - w) ** 2 * self._v_ref + w * w
        if not self.at_rest:
            self.at_rest = (
                t_s - self._t_steady >= CONFIRM_S - 1e-9
                and t_s - self._t_still >= CONFIRM_S - 1e-9
                and t_s - self._t_last_still <= FIX_MAX_AGE_S
            )
        return self.at_rest

    def interrupt(self, t_s: float) -> None:
        """End the rest now (the zero-rate update was rejected: the vehicle turns)."""
        self.at_rest = False
        if self._ref is not None:
            self._restart(t_s, self._ref, self._v_ref)

    # ------------------------------------------------------------------ internals
    def _restart(self, t_s: float, x: np.ndarray, v_ref: float) -> None:
        self._ref = x.copy()
        self._v_ref = v_ref
        self._slow = np.zeros(6)
        self._v_slow = 0.0
        self._t_steady = t_s
