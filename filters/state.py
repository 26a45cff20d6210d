"""The filter's one declared state layout (error state and nominal state).

Error state ``dx`` (the Kalman state; zero after every reset), in this order:

=========  =====  ==============================================================
block      size   meaning
=========  =====  ==============================================================
POS        3      position error, NED, m (true - estimate)
VEL        3      velocity error, NED, m/s
ATT        3      attitude error, NED, rad: ``q_true = exp(dtheta) * q_est``
RATE       3      body-rate error, FRD, rad/s
B_WDOT     3      bias of the solved angular acceleration, FRD, rad/s^2
B_F        3      bias of the solved specific force, FRD, m/s^2
B_QUAD     nq     bias of the solved rate-quadratic terms, rad^2/s^2
DR         3N     residual sensor-position errors ``dr_i``, FRD, m (optional)
CAL        3N     residual sensing-axis errors ``dg_i`` (scale along the axis,
                  angles across it), FRD, dimensionless (optional)
AOA        1-2    angle-of-attack error, rad; with a lift law the law's offset
                  error (rad) and its ``K`` error (m) (optional)
=========  =====  ==============================================================

Why these biases: each channel's bias ``beta_i`` enters the solved features as
``S beta`` (S the solve operator), one-to-one for the nine-cube (nine outputs,
nine solved features). Six of those nine directions (``B_WDOT``, ``B_F``) drive
the navigation drift and are observable from GPS through attitude and
velocity; the other ``nq`` (three rate products for the nine-cube) enter only
the rate measurement, where they would read as a false rate of up to
``sqrt(bias / l)`` (0.3 rad/s for 1 mg on a 0.1 m arm) if left out; they are
observable whenever the rate is held by the integrated angular acceleration
and the GPS-held attitude. So all nine are carried, as the 9-D image of the
channel biases, with a prior and random walk mapped through ``S`` (so the
three blocks start correlated exactly as the channel biases make them). With a
forecast compensation the features are compensated with a forecast made from
their own history less the bias *estimates*, so a bias error ``S beta - b_hat``
shows in them as ``T (S beta - b_hat)`` (``FilterNoise.bias_effect``): the
states stay ``S beta`` and the transition, the rate measurement, the static
alignment and the lift law read them through ``T``.

Why ``DR``: the calibration (multi-position, at rest) finds the sensing axes
but cannot see where each sensitive element sits; what is left after the
drawings (``dr_i``, 0.5 mm per axis is typical) makes channel errors
``theta_i . (wdot x dr_i + w x (w x dr_i))``. They are constant but enter
through the motion, so they act as a bias that changes with every manoeuvre;
as white noise they leave the filter overconfident. Carried as states they are
exact (linear in ``dr``) and estimated in flight: the in-flight part of the
position calibration. With a forecast compensation the forecast's history holds
their effect ``S G dr`` in full, so its loop returns it as it returns a bias and the
features carry ``T S G dr`` (:meth:`filters.ekf.NavFilter.geometry_jacobian`). The
block is present whenever the configuration declares a position uncertainty
(``position_sigma_m`` > 0): a declared uncertainty is never dropped. Where the
motion keeps the scatter's channel error far below the noise (``ngnav simulate``
prints both; ``uav-survey``) the states learn little and stay near their prior.

Why ``CAL``: the bench calibration fits each channel's scale and axis angles from
static poses; what its fit leaves (a few ppm and microradians after 20 000 samples a
pose) makes the channel read ``dg_i . a_i`` more, ``a_i`` the specific force at the
sensor. That follows the load: at a projectile's 24 g boost about 100 ug per channel,
fifty times the bias walk over the boost, and back as the load falls, which no bias
walk describes (over-sure attitude after the boost; docs/notes/filter-notes.md, "a
spinning projectile"). Carried as states they are exact, read like ``DR`` through
the features' sensitivity ``T S diag(a_i^T)``. Present when the calibration declares
``scale_sigma`` or ``axis_error_sigma_rad``.

Why ``AOA``: an aircraft's velocity leaves its body x axis by the angle of
attack, which its lift needs: it grows with load factor and falls with speed.
The fixed-wing vehicle model (``vehicle.kind``) measures the velocity
along the wind-normal axis ``[-sin alpha, 0, cos alpha]`` (FRD) as zero, which
ties the pitch to the flight path plus ``alpha``. With the airframe's lift law
(``aoa_lift_k_m``) ``alpha = w(V) (alpha_b + K n_w / V^2)`` follows every change
of load and speed the array measures, and the block holds the law's offset
``alpha_b`` (a constant of the airframe, or a slow random walk with
``aoa_rw_deg_rts`` > 0) and, with
``aoa_lift_k_sigma_m``, the error of ``K`` (constant: mass, density and lift
slope are never known exactly, and its effect grows with the load factor,
which a random walk cannot describe). Without a law the state is ``alpha``
itself. Without the block the model assumes zero angle of attack, which only a
vehicle flying along its body axis keeps. Present when ``aoa_prior_sigma_deg`` > 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

from ngnav.records import NAV_BLOCKS


def block_slices(blocks: tuple[tuple[str, int], ...]) -> dict[str, slice]:
    """Slices of consecutive ``(name, dof)`` blocks, in their declared order."""
    out, start = {}, 0
    for name, dof in blocks:
        out[name] = slice(start, start + dof)
        start += dof
    return out


#: The blocks every filter carries, in order: navigation (position, velocity, attitude,
#: rate) and the biases of the solved angular acceleration and specific force.
FIXED_BLOCKS: tuple[tuple[str, int], ...] = (
    *NAV_BLOCKS,
    ("b_wdot", 3),
    ("b_f", 3),
)
_FIXED = block_slices(FIXED_BLOCKS)
POS, VEL, ATT, RATE = _FIXED["pos"], _FIXED["vel"], _FIXED["att"], _FIXED["rate"]
B_WDOT, B_F = _FIXED["b_wdot"], _FIXED["b_f"]
#: Number of navigation error states (position, velocity, attitude, rate).
N_NAV = RATE.stop
#: Error states before the rate-quadratic biases.
N_BASE = B_F.stop


def b_quad(nq: int) -> slice:
    """Slice of the rate-quadratic bias block for ``nq`` solved quadratic terms."""
    return slice(N_BASE, N_BASE + nq)


@dataclass(frozen=True)
class StateLayout:
    """The error state of one filter: the fixed blocks, then ``nq`` rate-quadratic
    biases, ``n_dr`` sensor-position states, ``n_cal`` sensing-axis states and ``n_aoa``
    (0-2) angle-of-attack states.

    Every slice comes from :attr:`blocks`, the one ordered declaration (each computed once).
    """

    nq: int
    n_dr: int = 0
    n_aoa: int = 0
    n_cal: int = 0
    _slices: dict[str, slice] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.n_aoa not in (0, 1, 2):
            raise ValueError(f"n_aoa must be 0, 1 or 2, got {self.n_aoa}")
        object.__setattr__(self, "_slices", block_slices(self.blocks))

    @property
    def blocks(self) -> tuple[tuple[str, int], ...]:
        """The ordered ``(name, dof)`` blocks of this layout."""
        return (
            *FIXED_BLOCKS,
            ("b_quad", self.nq),
            ("dr", self.n_dr),
            ("cal", self.n_cal),
            ("aoa", self.n_aoa),
        )

    @cached_property
    def n(self) -> int:
        """Total error-state size."""
        return self._slices["aoa"].stop

    @cached_property
    def dr(self) -> slice:
        """The sensor-position error block (3N or empty)."""
        return self._slices["dr"]

    @cached_property
    def cal(self) -> slice:
        """The calibration's residual sensing-axis errors ``dg_i`` (3N or empty)."""
        return self._slices["cal"]

    @cached_property
    def geometry(self) -> slice:
        """``DR`` and ``CAL`` together: the states the features read through ``sg``."""
        return slice(self._slices["dr"].start, self._slices["cal"].stop)

    @cached_property
    def aoa(self) -> slice:
        """The angle-of-attack block (0, 1 or 2 states)."""
        return self._slices["aoa"]

    @cached_property
    def bias(self) -> slice:
        """All bias states (angular acceleration, force, quadratic), in solve-column order."""
        return slice(B_WDOT.start, self._slices["b_quad"].stop)


#: Names of the error-state blocks used for NEES, with their slices.
NEES_BLOCKS: dict[str, slice] = {"pos": POS, "vel": VEL, "att": ATT, "rate": RATE}
