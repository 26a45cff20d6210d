"""A GPS receiver model for simulated runs, and the antenna's truth.

The fix record itself is :class:`ngnav.records.GpsFixes`.

A fix carries WGS-84 latitude/longitude/ellipsoidal altitude of the antenna,
its NED velocity, and the receiver's accuracy figures, read here as 1-sigma:
``h_acc_m`` per horizontal axis, ``v_acc_m`` vertical, ``vel_acc_mps`` per
velocity axis. ``t_s`` is the time of validity on the array's clock;
``latency_s`` (when known) is how much later it arrived.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.geodesy import LocalTangentPlane
from ngnav.records import FlightTruth, GpsFixes
from ngnav.rotation import dcm_from_quat


def antenna_truth(
    truth: FlightTruth, idx: np.ndarray, antenna_b_m: np.ndarray | tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """The antenna's true position and velocity at the truth's samples ``idx`` (M,).

    ``antenna_b_m`` (3,) is the antenna from the array reference point, FRD, m.
    Returns position (M, 3), NED, m, and velocity (M, 3), NED, m/s: the body
    origin's plus ``C r`` and ``C (w x r)``.
    """
    r = np.asarray(antenna_b_m, dtype=float)
    c = dcm_from_quat(truth.q_nb[idx])
    pos = truth.pos_ned_m[idx] + c @ r
    vel = truth.vel_ned_mps[idx] + np.einsum("tij,tj->ti", c, np.cross(truth.omega_b_rps[idx], r))
    return pos, vel


@dataclass(frozen=True)
class GpsReceiverModel:
    """Simulated receiver: white errors at the stated 1-sigma, outages, glitches.

    Parameters
    ----------
    rate_hz : float
        Fix rate, 1-10 Hz.
    h_acc_m, v_acc_m, vel_acc_mps : float
        1-sigma of horizontal (per axis) and vertical position, and of velocity.
    latency_s : float
        Delay from validity to arrival, recorded with each fix.
    antenna_b_m : array (3,)
        Antenna position from the array reference point, FRD, m.
    outages : tuple of (start_s, duration_s)
        Intervals with no fix.
    glitch_times_s : tuple of float
        Fixes nearest these times get a horizontal position jump of ``glitch_m``.
    glitch_m : float
        Size of a glitch, m (north-east, 45 deg).
    """

    rate_hz: float = 5.0
    h_acc_m: float = 1.5
    v_acc_m: float = 3.0
    vel_acc_mps: float = 0.1
    latency_s: float = 0.0
    antenna_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    outages: tuple[tuple[float, float], ...] = ()
    glitch_times_s: tuple[float, ...] = ()
    glitch_m: float = 50.0

    def __post_init__(self) -> None:
        if not 0.1 <= self.rate_hz <= 50.0:
            raise ValueError(f"gps.rate_hz must be in 0.1..50, got {self.rate_hz}")
        for k in ("h_acc_m", "v_acc_m", "vel_acc_mps"):
            if not getattr(self, k) > 0:
                raise ValueError(f"gps.{k} must be positive, got {getattr(self, k)}")
        if self.latency_s < 0:
            raise ValueError(f"gps.latency_s must not be negative, got {self.latency_s}")

    def simulate(
        self, truth: FlightTruth, ltp: LocalTangentPlane, rng: np.random.Generator
    ) -> tuple[GpsFixes, np.ndarray]:
        """Fixes of the antenna along ``truth``, on the truth's sample times.

        Returns the fixes and a boolean mask (M,) of the glitched ones.
        """
        t = truth.t_s
        step = max(1, round(1.0 / (self.rate_hz * float(np.median(np.diff(t))))))
        idx = np.arange(0, t.shape[0], step)
        keep = np.ones(idx.shape, dtype=bool)
        for start, dur in self.outages:
            keep &= ~((t[idx] >= start) & (t[idx] < start + dur))
        idx = idx[keep]
        m = idx.shape[0]
        pos, vel = antenna_truth(truth, idx, self.antenna_b_m)
        sig = np.array([self.h_acc_m, self.h_acc_m, self.v_acc_m])
        pos = pos + rng.normal(0.0, 1.0, (m, 3)) * sig
        vel = vel + rng.normal(0.0, self.vel_acc_mps, (m, 3))
        glitched = np.zeros(m, dtype=bool)
        for tg in self.glitch_times_s:
            if m:
                j = int(np.argmin(np.abs(t[idx] - tg)))
                glitched[j] = True
                pos[j, :2] += self.glitch_m / np.sqrt(2.0)
        lat, lon, alt = ltp.to_geodetic(pos)
        ones = np.ones(m)
        fixes = GpsFixes(
            t_s=t[idx],
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            vel_ned_mps=vel,
            h_acc_m=self.h_acc_m * ones,
            v_acc_m=self.v_acc_m * ones,
            vel_acc_mps=self.vel_acc_mps * ones,
            latency_s=self.latency_s * ones,
        )
        return fixes, glitched
