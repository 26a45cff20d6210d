"""A lost track, recovered: the filter started again from what it has.

The filter loses its track when its covariance stops being positive definite, when the
GPS velocities it rejects say its tilt or rate is gone for good (a second attitude reopen
within ``REOPEN_MIN_INTERVAL_S``: :class:`ngnav.errors.LostTrackError`), or when a fix
leaves its tilt 1-sigma above ``LOST_TILT_SIGMA_DEG`` (a long coast at a poor grade), or
its heading's where the fix's course can give the heading back (a vehicle flying along its
course). It then stops
estimating, skips the blocks up to the next GPS fix that has one before it, and starts
again there:

- position and velocity from the fix (its antenna lever arm removed);
- the tilt from the array's specific force over the last block against the GPS
  acceleration between the two fixes (``C f_b = a_n - g_n``, a TRIAD with the heading);
- the heading from the GPS course for a fixed-wing (no sideslip: the course is the
  heading) and for a vehicle whose heading is its course (``initial.heading_source =
  "gps"``), otherwise the configured heading with :data:`RESTART_HEADING_SIGMA_DEG` (for the
  latter until the next course);
- the rate zero with :data:`RESTART_RATE_SIGMA_DPS`;
- the biases as they were, with their covariance (the array's errors do not change when
  the track is lost; at their priors only if the loss left them not finite or not positive
  definite): started at their priors, the tilt and a horizontal bias read alike in level
  flight and were learned again apart under sigmas that did not follow (``uav-survey`` at
  ``mems-consumer``: the pitch and the zero-lift angle drifted together, design notes);
- the other states (lift law, sensor positions) at their priors.

Estimates are not recorded while the track is lost, and those after the start again are
marked not valid (:attr:`ngnav.records.NavEstimate.valid`) until the tilt and heading
1-sigma are back under :data:`VALID_TILT_SIGMA_DEG` and :data:`VALID_HEADING_SIGMA_DEG`.
Each loss is counted and reported (:class:`ngnav.records.TrackLoss`). A loss again within
:data:`RESTART_MIN_INTERVAL_S` of a start again ends the run as before: the estimates are
not coming back (a broken configuration), and carrying on would report garbage.
"""

from __future__ import annotations

import numpy as np

from filters.alignment import _gps_course
from filters.stream import whole_fix
from filters.supervision import tilt_sigma_rad
from filters.vehicle_model import ZERO_LIFT_AOA_DEG
from ngnav.conventions import gravity_n_mps2
from ngnav.errors import CovarianceError
from ngnav.records import TrackLoss
from ngnav.rotation import quat_from_euler

#: The tilt's 1-sigma at a start again, deg: the force is the last block's mean, the GPS
#: acceleration the mean over a fix interval; a survey aircraft's 1-3 m/s^2 changes of
#: load within one interval tilt the pair by up to about 10 deg, 5 deg typical.
RESTART_TILT_SIGMA_DEG = 5.0
#: The heading's 1-sigma at a start again without a GPS course (a free vehicle, or too
#: slow), deg: the configured heading says little after minutes of flight.
RESTART_HEADING_SIGMA_DEG = 60.0
#: The rate's 1-sigma per axis at a start again, deg/s: a survey aircraft's turns are
#: 13 deg/s (25 deg of bank at 20 m/s).
RESTART_RATE_SIGMA_DPS = 15.0
#: Estimates after a start again count as valid from when the tilt's 1-sigma (each
#: horizontal axis) is under this, deg...
VALID_TILT_SIGMA_DEG = 2.0
#: ...and the heading's under this, deg.
VALID_HEADING_SIGMA_DEG = 10.0
#: A loss within this long of a start again ends the run (:class:`CovarianceError`), s.
RESTART_MIN_INTERVAL_S = 30.0
#: Fixes further apart than this give no acceleration for the tilt, s.
RESTART_MAX_FIX_GAP_S = 1.0


def triad(f_b: np.ndarray, f_n: np.ndarray, heading_rad: float) -> np.ndarray:
    """Attitude ``C_nb`` (3, 3) that takes ``f_b`` onto ``f_n``'s direction exactly and turns
    the body x axis about it toward the heading (TRIAD with the force as the primary)."""
    h_n = np.array([np.cos(heading_rad), np.sin(heading_rad), 0.0])
    x_b = np.array([1.0, 0.0, 0.0])

    def frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        t1 = a / np.linalg.norm(a)
        t2 = np.cross(t1, b)
        t2 = t2 / np.linalg.norm(t2)
        return np.column_stack([t1, t2, np.cross(t1, t2)])

    return frame(f_n, h_n) @ frame(f_b, x_b).T


class RecoveryMixin:
    """Lose the track on a covariance failure; start again at the next usable fix."""

    def lose_track(self, reason: str) -> None:
        """Declare the track lost now (a covariance failure does so by itself).

        The filter starts again at the next GPS fix with one before it (see the module
        docstring). Raises :class:`CovarianceError` if the last start again was less
        than :data:`RESTART_MIN_INTERVAL_S` ago.
        """
        nf = self.nf
        t = float(nf.t_s)
        if self.track_losses and t - self.track_losses[-1].restarted_s < RESTART_MIN_INTERVAL_S:
            raise CovarianceError(
                f"{reason}; lost again {t - self.track_losses[-1].restarted_s:.1f} s after "
                "starting again"
            )
        self.counts["track losses (filter started again)"] += 1
        self._lost = (t, reason)
        self._prev_fix = None
        if self.smoother is not None:
            # the pass needs every block's transition: none while the track is lost
            self.smoother.close()
            self.smoother = None
            nf.lag = None
            self.counts["smoothing dropped (track lost)"] = 1

    def _converged(self, p: np.ndarray) -> bool:
        """The attitude's 1-sigma (covariance ``p``) back under the validity limits."""
        tilt = tilt_sigma_rad(p)
        return bool(
            tilt < np.deg2rad(VALID_TILT_SIGMA_DEG)
            and np.sqrt(p[8, 8]) < np.deg2rad(VALID_HEADING_SIGMA_DEG)
        )

    @property
    def lost(self) -> bool:
        """True while the track is lost (no estimates until the next start again)."""
        return self._lost is not None

    def _lost_block(self, i1: int) -> None:
        """A block while the track is lost: its samples skipped, its fixes looked at."""
        fixes = []
        while self._pending and self._pending[0][0] == i1:
            fixes.append(self._pending.pop(0)[2])
        fixes.extend(self._late)
        self._late = []
        self.counts["samples skipped (track lost)"] += i1 - self._i0
        self._i0 = i1
        if i1 >= self._next_grid:
            self._next_grid += self._k_reg
        for fix in fixes:
            if self._lost is None:  # started again on an earlier fix of this block
                self._fuse_fix(fix, i1, self._p_bound)
                continue
            self.counts["gps fixes while the track was lost"] += 1
            if self.keep_estimates:  # no innovation: the series keep one entry per fix
                self._inn.append((fix[0], np.nan, np.nan, False, False))
            if not whole_fix(fix):
                continue  # a start needs the whole position and velocity
            prev = self._prev_fix
            self._prev_fix = fix
            if (
                self.use_gps
                and prev is not None
                and 0.0 < fix[0] - prev[0] <= RESTART_MAX_FIX_GAP_S
            ):
                self._start_again(fix, prev, i1)
        if self.keep_estimates and self._nq:  # nor a rate update: the same for blocks
            self._rate_nis.append(np.nan)
            self._rate_nis_t.append(float(self._t[i1 - self._base]))
            self._rate_nis_dof.append(self.nf.rate_dof)
        if self._lost is None:
            self._record()
        elif self.keep_estimates and self._epochs:
            # the epoch is kept, empty: a lost track's estimates are not valid
            self._epochs.add_lost(float(self._t[i1 - self._base]))

    def _start_again(self, fix: tuple, prev: tuple, i1: int) -> None:
        cfg = self.cfg
        nf = self.nf
        t_fix, ned, vel, sig, vacc, _ = fix
        a_n = (vel - prev[2]) / (t_fix - prev[0])
        f_n = a_n - gravity_n_mps2()
        # the last block's features (the force's bias and mounting term are within the
        # tilt's sigma: 1 mg and an axis error times g are a few mrad)
        g0 = max(i1 + 1 - self._k_reg, self._base + 1)
        seed = self._features(g0, i1 + 1, self._filter_mask, np.zeros(3))
        b = self._base
        seed_ok = (self._chmask[g0 - b : i1 + 1 - b] & ~self._filter_mask) == 0
        if not np.any(seed_ok):
            return  # no valid sample to tilt by: the next fix will do
        f_b = seed[seed_ok, 3:6].mean(axis=0)
        course = _gps_course(vel, vacc) if self._flies_on_course else None
        if course is not None:
            heading, heading_sigma = course
            if cfg.vehicle.fixed_wing:
                heading_sigma = max(heading_sigma, np.deg2rad(2.0))
        else:
            heading = float(np.deg2rad(cfg.initial.yaw_deg))
            heading_sigma = float(np.deg2rad(RESTART_HEADING_SIGMA_DEG))
            self._heading_pending = self._heading_is_course  # the next course sets it
        c = triad(f_b, f_n, heading)
        q = quat_from_euler(
            np.arctan2(c[2, 1], c[2, 2]),
            -np.arcsin(np.clip(c[2, 0], -1, 1)),
            np.arctan2(c[1, 0], c[0, 0]),
        )
        tilt = float(np.deg2rad(RESTART_TILT_SIGMA_DEG))
        bs = nf.layout.bias
        kept = _usable_biases(nf.bias, nf.P[bs, bs])
        nf.initialise(
            t_fix,
            ned - c @ cfg.antenna_b_m,
            vel,
            q,
            np.zeros(3),
            sig,
            vacc,
            np.array([tilt, tilt, heading_sigma]),
            float(np.deg2rad(RESTART_RATE_SIGMA_DPS)),
            aoa_rad=float(np.deg2rad(ZERO_LIFT_AOA_DEG if cfg.vehicle.fixed_wing else 0.0)),
            bias=kept,
        )
        nf.t_s = float(self._t[i1 - b])
        self._seed_compensation(seed, seed_ok)
        self._f_load_prev = self._sg_load_prev = None
        self._k_load_prev = self._kk_load_prev = 1
        self._wd_smooth = np.zeros(3)
        self._fe_d2 = np.zeros(6)
        self._t_hold = 0.0
        if self.rest is not None:
            self.rest.interrupt(nf.t_s)
        if self._p_bound is not None:
            self._p_bound = nf.P.copy()
        lost_s, reason = self._lost
        self.track_losses.append(TrackLoss(lost_s, nf.t_s, reason))
        self._lost = None
        self._converging = True
        self._t_last_reopen = -np.inf
        self.last_gps_t = t_fix


def _usable_biases(bias: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The bias states' estimate (k,) and covariance (k, k) for a start again to keep, or
    None (start from the prior) when the loss left them not finite or not positive definite."""
    if not (np.all(np.isfinite(bias)) and np.all(np.isfinite(cov))):
        return None
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    return bias.copy(), cov.copy()
