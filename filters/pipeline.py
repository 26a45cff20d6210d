"""One run through the whole chain: array solve, compensation, EKF, GPS updates.

``run_filter`` takes what a user has (array samples, GPS fixes, the run's
configuration) and returns estimates with their covariance, the GPS
innovations, and counts of everything skipped, held or rejected. The same
function serves simulated and recorded runs.

Compensation (paper eq. 22) works at the filter rate: the motion of the next
block (rate, angular acceleration, specific force: the block means) is
forecast from the last ``window`` blocks by the chosen predictor, and the
mounting-error term ``S E phi_hat`` is removed from every sample of the block.
At the paper's 100 Hz this is exactly its one-step-ahead forecast; at a 1 kHz
array each block's samples share the forecast of their mean. The rate history
is the filter's own rate estimate, so the compensation does not drift.

- ``gm11``, ``line``, ``last``: nominal solve, calibrated ``E``, that predictor;
- ``none``: nominal solve, no correction;
- ``oracle``: the solve of the *true* geometry (simulation only): no
  mounting error at all, the best any compensation could do.
"""

from __future__ import annotations

import numpy as np

from filters import kernels
from filters.algebra import BODY_FRAME_MAX_CURVATURE_MPS
from filters.alignment import AlignmentMixin
from filters.ekf import NavFilter
from filters.epochs import EpochStore
from filters.exclusion import ExclusionMixin, SuspectsMixin
from filters.faults import ChannelMonitor
from filters.noise import filter_noise
from filters.recovery import RecoveryMixin
from filters.reduced import ReducedSolve
from filters.smoother import RESTARTS, SmootherLog
from filters.state import ATT, POS, RATE, VEL
from filters.step import StepMixin
from filters.stream import StreamMixin
from filters.supervision import (
    GATE_PROBABILITY,
    GPS_GAP_RESET_S,
)
from filters.vehicle_model import (
    BodyVelocityRecord,
)
from ngnav.compensation import _QUAD_I, _QUAD_J
from ngnav.errors import CovarianceError
from ngnav.frontend import ArraySolver
from ngnav.geodesy import LocalTangentPlane
from ngnav.layout import FEATURE_NAMES, ArrayLayout
from ngnav.records import (
    ArraySamples,
    Estimates,
    FlightTruth,
    GpsFixes,
    GpsInnovations,
    NavEstimate,
    RunResult,
    TrackLoss,
)
from ngnav.runconfig import RunConfig

#: Where a fix pushed into the pipeline ends (its counters): the one that set position and
#: velocity at the start, those fused (through the gates, passed or not), those ignored
#: (``use_gps`` off), and the three kinds that cannot be fused.
FIX_OUTCOMES = (
    "gps fix that started the filter",
    "gps fixes through the gates",
    "gps fixes ignored (no GPS)",
    "gps fixes outside the array's time span",
    "gps fixes before the filter start",
    "gps fixes after the last array sample",
    "gps fixes while the track was lost",
)


#: kernels.epoch_record's angle-of-attack arguments without the state (it returns 0).
_V, _M = kernels.NO_VECTOR, kernels.ABSENT
_NO_AOA = (0, 0, 0, 0.0, 0.0, _V, 0.0, 0.0, 0.0, _V, _M, 0, _M, 0)


class Pipeline(
    StreamMixin, AlignmentMixin, StepMixin, ExclusionMixin, SuspectsMixin, RecoveryMixin
):
    """The whole chain run as a stream: push samples and fixes, get estimates.

    One block at a time: the compensation's forecast, the nominal propagation,
    the covariance prediction, the rate-product update, the GPS fixes that fall
    in the block (at their time of validity), the sideslip model, the checks.
    Estimates are recorded at every block end as a :class:`ngnav.records.NavEstimate`
    (:attr:`latest`); ``on_epoch(record)`` is called with each.

    Inputs may arrive in any interleaving (a live link delivers a fix
    ``latency`` after its time of validity): the filter's fusion horizon runs
    ``cfg.filter.fusion_lag_s`` behind the newest sample (PX4 EKF2's delayed
    horizon), so a fix that arrives within that lag is fused exactly where an
    offline run fuses it. A later fix is fused at the next block end with a
    ``v dt`` time shift and counted. The result therefore depends only on the
    samples, the fixes and the order of their arrival, not on how they were
    chunked or how fast they came: a tlog replay and the live link of the same
    run give the same estimates.

    Before the filter starts (a fix after the static alignment period, and the
    samples up to it plus the lag) everything is buffered.

    Parameters
    ----------
    cfg : RunConfig
        What the filter knows (see :mod:`ngnav.runconfig`).
    dt_s : float, optional
        The array's sample interval. Default: the median interval of the
        samples received before the filter starts.
    compensation, use_gps, true_layout, truth, bound
        As for :func:`run_filter`.
    on_epoch : callable, optional
        Called with the :class:`ngnav.records.NavEstimate` of every recorded epoch.
    keep_estimates : bool
        Keep every epoch for :meth:`result` (False for an endless live link:
        :meth:`result` then holds the latest epoch only).
    body_velocity_log : list, optional
        As for :func:`run_filter`.
    smooth : bool
        Store what a Rauch-Tung-Striebel pass needs (:mod:`filters.smoother`) and
        give :meth:`result` the smoothed estimates after :meth:`finish`.
    lose_track_at_s : tuple of float
        Declare the track lost at these times (s, run clock): the recovery's
        validation (:mod:`filters.recovery`). A covariance failure loses it by itself.

    Raises
    ------
    ValueError
        Bad configuration or a rate-aided layout (at construction); no valid
        sample in the alignment period (at the start); no usable GPS fix (at
        :meth:`finish`).
    filters.ekf.CovarianceError
        If the covariance stops being symmetric positive definite.
    """

    #: The innovation gate's probability, for outputs that report test ratios.
    gate_probability = GATE_PROBABILITY
    #: How long after an accepted GPS position an estimate counts as GPS aided, s.
    gps_gap_s = GPS_GAP_RESET_S

    def __init__(
        self,
        cfg: RunConfig,
        *,
        dt_s: float | None = None,
        compensation: str | None = None,
        use_gps: bool = True,
        true_layout: ArrayLayout | None = None,
        truth: FlightTruth | None = None,
        bound: bool = False,
        on_epoch=None,
        keep_estimates: bool = True,
        body_velocity_log: list[BodyVelocityRecord] | None = None,
        smooth: bool = False,
        lose_track_at_s: tuple[float, ...] = (),
    ) -> None:
        method = compensation or cfg.compensation.method
        if smooth and not keep_estimates:
            raise ValueError("smoothing needs the whole run's estimates (keep_estimates)")
        if method == "oracle" and (true_layout is None or truth is None):
            raise ValueError(
                "compensation 'oracle' needs the true geometry and motion (simulations)"
            )
        if bound and truth is None:
            raise ValueError("the bound needs the truth")
        solver = ArraySolver(cfg.layout, cfg.noise_sigma_mps2)
        unsolved = [FEATURE_NAMES[c] for c in range(9, 12) if c not in solver.solved_columns]
        if unsolved:
            # the rate products are the filter's rate measurement: without one, its rate
            # about some axis is never measured
            raise ValueError(
                f"layout {cfg.layout.name!r} cannot solve the rate product "
                f"{', '.join(unsolved)} beside angular acceleration and force; the filter "
                "measures the rate with the three products (e.g. a nine-sensor cube)"
            )
        if dt_s is not None and not (np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be a positive number, got {dt_s}")
        self.cfg = cfg
        self.method = method
        self.use_gps = use_gps
        self.true_layout = true_layout
        self.truth = truth
        self.bound = bound
        self.on_epoch = on_epoch
        self.keep_estimates = keep_estimates
        self.body_velocity_log = body_velocity_log
        self.n_epochs = 0
        self.n_channels = cfg.layout.n_sensors
        self.solver = solver
        cols = solver.solved_columns
        self._cols = cols
        quad_cols = cols[cols >= 6] - 6
        self._pairs = np.column_stack([_QUAD_I[quad_cols], _QUAD_J[quad_cols]])
        self._smat = solver.solve_matrix
        self._se = None
        # terms the layout excites but cannot solve (an as-built cube's faint rate squares)
        # go with the mounting errors: the compensation takes them out with the rate
        aided = np.zeros_like(cfg.layout.design)
        aided[:, solver.aided_columns] = cfg.layout.design[:, solver.aided_columns]
        #: The known mounting errors' effect on the channels (N, 12), with a forecast.
        self._e_chan = None
        if method in ("gm11", "line", "last"):
            e = cfg.known_errors.error_matrix(cfg.layout)  # (N, 12)
            self._e_chan = e + aided if solver.rate_aided else e
            self._se = self._smat @ self._e_chan  # (k, 12)
        self._d_true = None
        if method == "oracle":
            # the exact mounting-error term on the channels: true geometry, true motion
            self._d_true = true_layout.design - cfg.layout.design + aided
        self.dt = dt_s
        self._k = cols.shape[0]
        # sample store: global index g lives at row g - base
        self._t = np.empty(0)
        self._raw = np.empty((0, self.n_channels))  # the channels as they came, m/s^2
        self._ach = np.empty((0, self.n_channels))  # calibrated channels, m/s^2
        self._mon_n = 0  # samples the health tests have seen (global count)
        self._nfmask = np.empty(0, dtype=np.int64)  # bit i: channel i non-finite
        self._chmask = np.empty(0, dtype=np.int64)  # bit i: channel i non-finite or saturated
        self._last_bad = -1  # the last stored row (global) with a bit in _chmask; -1: none
        self._excl = np.empty(0, dtype=np.int64)  # bit i: channel i excluded at the sample
        #: Channels excluded from the samples arriving now (bitmask), and those the
        #: filter's model is set for (:meth:`_switch_solve`).
        self._excluded = 0
        self._filter_mask = 0
        self._reduced: dict[int, ReducedSolve] = {}
        self._solved = np.ones(self._k, dtype=bool)
        self._suspects = None  # a parity group being told apart (SuspectsMixin)
        self._bits = 1 << np.arange(self.n_channels, dtype=np.int64)
        #: The channels' health tests (flat line, noise level, parity; :mod:`filters.faults`).
        #: Without compensation the known mounting errors alone move the parity: no parity
        #: test then (the sample tests still run).
        self._parity_on = method != "none"
        self.monitor = ChannelMonitor(
            cfg.noise_sigma_mps2, cfg.range_mps2, self._smat[cols >= 6] * self._parity_on
        )
        self._base = 0
        self._n = 0  # samples received (global count)
        self._fixes: list[tuple] = []  # (t, ned(3), vel(3), sig(3), vel_acc, arrival order)
        self._pending: list[tuple[int, int, tuple]] = []  # (idx, order, fix) after the start
        self._late: list[tuple] = []
        self._n_fix = 0
        #: Every fix pushed ends in exactly one of ``FIX_OUTCOMES`` once the run finishes
        #: (``gps fixes later than the fusion lag`` says how some of the fused came).
        self.counts: dict[str, int] = {
            "samples held (non-finite)": 0,
            "samples held (saturated)": 0,
            **dict.fromkeys(FIX_OUTCOMES, 0),
            "gps fixes later than the fusion lag": 0,
            "track losses (filter started again)": 0,
            "samples skipped (track lost)": 0,
        }
        self._ltp = LocalTangentPlane(cfg.lat0_deg, cfg.lon0_deg, cfg.alt0_m)
        self.started = False
        self.finished = False
        self.nf: NavFilter | None = None
        self.last_gps = None
        self.last_gps_t = -np.inf
        self.last_rate_nis = float("nan")
        self.block_faulty = 0
        self.block_fallbacks = 0
        #: The last block's compensated ``[wdot, f]`` mean (FRD; rad/s^2, m/s^2) less the
        #: bias estimates less its forecast, (6,): the forecast's error plus noise (NaN
        #: without a forecast compensation or before the first block).
        self.last_forecast_error = np.full(6, np.nan)
        # the latest epoch's NavEstimate (:attr:`latest`) and what builds it
        self._latest: NavEstimate | None = None
        self._latest_args: tuple | None = None
        self._blocks_for = None
        self._blocks: tuple = ()
        #: The run's history for :class:`Estimates` (the 12 x 12 navigation covariance
        #: only; the full P goes to ``on_epoch`` and ``latest``), made at the first epoch.
        self._epochs: EpochStore | None = None
        self._inn: list[tuple] = []
        self._rate_nis: list[float] = []
        self._rate_nis_t: list[float] = []
        self._rate_nis_dof: list[int] = []
        self.n_fallbacks = 0
        self.smooth = smooth
        self.smoother: SmootherLog | None = None  # made at the start (the state's size)
        self._smoothed: tuple[Estimates, int] | None = None
        #: A lost track (time, reason) until the filter starts again (RecoveryMixin).
        self._lost: tuple[float, str] | None = None
        self._prev_fix: tuple | None = None
        #: After a start again: estimates not valid until the attitude's sigmas are back.
        self._converging = False
        #: Every loss of the track and start again, in order.
        self.track_losses: list[TrackLoss] = []
        #: Times at which to declare the track lost (a recovery's validation), s.
        self._forced_losses = sorted(lose_track_at_s)

    def _record(self) -> None:
        nf = self.nf
        pb = self._p_bound[:12, :12] if self._p_bound is not None else None
        self.n_epochs += 1
        store = self._epochs
        if store is None:
            store = self._epochs = EpochStore(nf.bias.shape[0], nf.layout.n)
        elif not self.keep_estimates:
            store.clear()
        lay = nf.layout
        bound = None if pb is None else pb.copy()
        e = store.next_row()
        # with the body-frame velocity error, the NED velocity a user reads: its
        # second-order part's mean and covariance; and the angle of attack's variance
        p = store.p
        aoa_var = kernels.epoch_record(
            nf.P,
            nf.vel,
            nf._body_frame_allowed(),
            BODY_FRAME_MAX_CURVATURE_MPS,
            nf.pos,
            nf.q,
            nf.w,
            nf.bias,
            store.nav,
            store.cov,
            e,
            p,
            nf._aoa_jacobian_args(nf.vel) if lay.n_aoa else _NO_AOA,
        )
        aoa = (nf.aoa, nf.aoa_sigma_from(aoa_var)) if lay.n_aoa else (None, None)
        c = nf.counters
        if self._converging and self._converged(p):
            self._converging = False
        valid = not self._converging
        store.rest.append((nf.t_s, bound, *aoa, self.block_faulty, valid))
        # what the epoch's NavEstimate is built from when it is read (:attr:`latest`); the
        # filter replaces its state arrays (never writes into them), so they need no copy
        self._latest = None
        self._latest_args = (
            (store.nav, e),
            (nf.t_s, nf.pos, nf.q, nf.w, nf.bias, bound, *aoa),
            (
                self.last_gps,
                nf.t_last_position_fix,
                c.gps_resets + c.gps_gap_resets,
                nf.last_rate_innovation,
                self.last_rate_nis,
                nf.gate_q,
                self.block_fallbacks,
                self.n_fallbacks,
                self.counts["samples held (non-finite)"] + self.counts["samples held (saturated)"],
                c.rate_rejected,
                self.block_faulty,
                lay,
                (nf.dr if lay.n_dr else None, nf.dg if lay.n_cal else None),
                (nf.aoa_b, nf.aoa_k)[: lay.n_aoa],
                valid,
            ),
        )

    @property
    def latest(self) -> NavEstimate | None:
        """The latest epoch's record (None before the first); built when first asked for
        (a run without an ``on_epoch`` reader builds only the last one)."""
        if self._latest is None and self._latest_args is not None:
            (nav, e), (t_s, pos, q, w, bias, *rest), extra = self._latest_args
            gps, t_fix, resets, y, nis, gate, fb, fbs, held, rej, faulty, lay, geo, aoa, ok = extra
            self._latest = NavEstimate(
                t_s,
                pos,
                nav[e, 3:6].copy(),
                q,
                w,
                bias,
                self._epochs.p.copy(),
                *rest,  # the bound, the angle of attack and its sigma
                last_gps=gps,
                t_last_position_fix_s=t_fix,
                resets=resets,
                rate_innovation=y,
                rate_nis=nis,
                rate_rejected=bool(nis > gate),
                forecast_fallback=bool(fb),
                forecast_fallbacks=fbs,
                held_samples=held,
                rate_updates_rejected=rej,
                faulty_channels=faulty,
                state_blocks=self._state_blocks(lay),
                dr_m=geo[0],
                axis_error_b=geo[1],
                aoa_states=np.array(aoa) if aoa else None,
                valid=ok,
            )
        return self._latest

    def _state_blocks(self, lay) -> tuple[tuple[str, int], ...]:
        """The layout's blocks with states, as :class:`NavEstimate` names them (cached)."""
        if self._blocks_for is not lay:
            self._blocks_for = lay
            self._blocks = tuple((name, dof) for name, dof in lay.blocks if dof)
        return self._blocks

    # --------------------------------------------------------------- output
    def result(self) -> RunResult:
        """Everything recorded so far (call after :meth:`finish` for the whole run)."""
        if not self.started:
            raise ValueError("the filter has not started: no estimates")
        nf = self.nf
        if self._epochs is None:
            raise ValueError("no estimates to stack")
        estimates = self._epochs.estimates()
        inn = np.array([r[0:3] for r in self._inn], dtype=float).reshape(-1, 3)
        acc = np.array([r[3:5] for r in self._inn], dtype=bool).reshape(-1, 2)
        innovations = GpsInnovations(inn[:, 0], inn[:, 1], inn[:, 2], acc[:, 0], acc[:, 1])
        counts = dict(self.counts)
        smoothed = None
        if self.smoother is not None and self.finished:
            if self._smoothed is None:
                self._smoothed = self._smooth()
            smoothed, counts[RESTARTS] = self._smoothed
        counts.update(
            {
                "blocks": nf.counters.blocks,
                "samples used": nf.counters.samples,
                "samples before the filter start": self._i_start,
                "gps fixes used": nf.counters.gps_used,
                "gps positions rejected (gate)": nf.counters.gps_rejected_pos,
                "gps velocities rejected (gate)": nf.counters.gps_rejected_vel,
                "gps resets after rejections": nf.counters.gps_resets,
                "gps resets after an outage": nf.counters.gps_gap_resets,
                "channel faults found": len(self.monitor.events),
                "rate updates": nf.counters.rate_updates,
                "rate updates rejected (gate)": nf.counters.rate_rejected,
                "zero-rate updates at rest": nf.counters.zero_rate_used,
                "zero-rate updates rejected (gate)": nf.counters.zero_rate_rejected,
                "sideslip updates": nf.counters.sideslip_used,
                "sideslip updates rejected (gate)": nf.counters.sideslip_rejected,
                "angle-of-attack updates": nf.counters.aoa_used,
                "angle-of-attack updates rejected (gate)": nf.counters.aoa_rejected,
                "heading resets to the GPS course": nf.counters.heading_resets,
                "heading updates from the GPS course": nf.counters.course_updates,
                "attitude reopened after rejected velocities": nf.counters.attitude_reopens,
                "vehicle-model updates counted as coasting": nf.counters.coast_model_updates,
                "vehicle-model updates counted as the hand-over": (
                    nf.counters.handover_model_updates
                ),
                "grey forecasts fallen back": self.n_fallbacks,
            }
        )
        return RunResult(
            estimates,
            innovations,
            np.array(self._rate_nis),
            counts,
            self.method,
            self._nq,
            nf.layout.n,
            np.array(self._rate_nis_t),
            self.latest,
            smoothed,
            tuple(self.monitor.events),
            np.array(self._rate_nis_dof, dtype=int),
            tuple(self.track_losses),
        )

    def _smooth(self) -> tuple[Estimates, int]:
        """The backward pass over the finished run: smoothed epochs, restarts."""
        log = self.smoother
        rows, restarts = log.smooth(self.nf.layout)
        if len(rows) != len(self._epochs):
            raise RuntimeError(f"smoother: {len(rows)} epochs for {len(self._epochs)} estimates")
        kept = [r[-2:] for r in self._epochs.rest]  # faulty channels, valid
        rows = [(*r, None, None, None, *k) for r, k in zip(rows, kept, strict=True)]
        return Estimates.from_rows(rows), restarts


def run_filter(
    samples: ArraySamples,
    fixes: GpsFixes,
    cfg: RunConfig,
    *,
    compensation: str | None = None,
    use_gps: bool = True,
    true_layout: ArrayLayout | None = None,
    truth: FlightTruth | None = None,
    bound: bool = False,
    progress=None,
    body_velocity_log: list[BodyVelocityRecord] | None = None,
    smooth: bool = False,
    lose_track_at_s: tuple[float, ...] = (),
) -> RunResult:
    """Run the GPS/array filter over a whole run (a :class:`Pipeline` fed in arrival order).

    Fixes are pushed when they arrive (time of validity plus ``latency_s``),
    between the samples, as a live link would deliver them.

    Parameters
    ----------
    samples : ArraySamples
        Channel outputs (T, N), m/s^2, uniformly sampled; non-finite rows are held.
    fixes : GpsFixes
        GPS fixes; the first one at or after the alignment sets position and velocity.
    cfg : RunConfig
        What the filter knows (see :mod:`ngnav.runconfig`).
    compensation : str, optional
        Override ``cfg.compensation.method``.
    use_gps : bool
        False runs the array alone after initialisation (the drift).
    true_layout : ArrayLayout, optional
        The true geometry; required by ``compensation="oracle"``.
    truth : FlightTruth, optional
        Exact truth on the samples' times; required by ``compensation="oracle"``.
    bound : bool
        Also run the covariance recursion linearised at ``truth`` (the bound).
    progress : callable, optional
        Called with the fraction done (0..1) now and then.
    body_velocity_log : list, optional
        Every sideslip and angle-of-attack update is appended to it as a
        :class:`filters.vehicle_model.BodyVelocityRecord` (what
        ``python -m studies.remainder`` measures).
    smooth : bool
        Also smooth the run (:mod:`filters.smoother`): the result's ``smoothed``.
    lose_track_at_s : tuple of float
        As for :class:`Pipeline`.

    Raises
    ------
    ValueError
        Bad configuration, a rate-aided layout, no usable GPS fix, no valid sample.
    filters.ekf.CovarianceError
        If the covariance stops being symmetric positive definite, or (its
        subclass ``LostTrackError``) the tilt or rate is lost twice within
        ``REOPEN_MIN_INTERVAL_S``; its ``partial`` holds the estimates up to the
        failure.
    """
    n = cfg.layout.n_sensors
    if samples.n_channels != n:
        raise ValueError(f"config layout has {n} channels, the array data has {samples.n_channels}")
    t = samples.t_s
    if t.shape[0] < 2:
        raise ValueError(f"the run holds {t.shape[0]} array samples; at least 2 are needed")
    if truth is not None and (truth.t_s.shape != t.shape or not np.allclose(truth.t_s, t)):
        raise ValueError("truth must be sampled at the array's sample times")
    pipe = Pipeline(
        cfg,
        dt_s=float(np.median(np.diff(t))),
        compensation=compensation,
        use_gps=use_gps,
        true_layout=true_layout,
        truth=truth,
        bound=bound,
        body_velocity_log=body_velocity_log,
        smooth=smooth,
        lose_track_at_s=lose_track_at_s,
    )
    try:
        pipe.replay(samples, fixes, progress)
        return pipe.result()
    except CovarianceError as exc:
        if pipe.started and pipe.n_epochs:
            exc.partial = pipe.result()
        raise
    finally:
        if pipe.smoother is not None and pipe._smoothed is None:
            pipe.smoother.close()  # not smoothed: the run stopped


__all__ = [
    "ATT",
    "POS",
    "RATE",
    "VEL",
    "Estimates",
    "GpsInnovations",
    "RunResult",
    "filter_noise",
    "run_filter",
]
