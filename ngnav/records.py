"""Immutable records that carry data between modules, each with its time.

Arrays inside records are copied and made read-only, so a record can be shared
without defensive copies downstream.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def frozen_array(a: np.ndarray | None, name: str, shape_tail: tuple[int, ...] = ()) -> np.ndarray:
    """Copy ``a`` to a read-only float array and check its trailing shape."""
    if a is None:
        raise ValueError(f"{name} is required")
    out = np.array(a, dtype=float)
    if shape_tail and out.shape[out.ndim - len(shape_tail) :] != shape_tail:
        raise ValueError(f"{name} must have trailing shape {shape_tail}, got {out.shape}")
    out.setflags(write=False)
    return out


def freeze_fields(record: object, shapes: dict[str, tuple[int, ...]]) -> None:
    """Replace the named array fields of a frozen dataclass by read-only copies.

    ``shapes`` maps field name to the required trailing shape (``()`` for any).
    """
    for name, tail in shapes.items():
        object.__setattr__(record, name, frozen_array(getattr(record, name), name, tail))


def check_time_axis(t_s: np.ndarray, name: str = "t_s") -> None:
    """Raise ValueError naming the first sample where ``t_s`` is not finite or not increasing."""
    if t_s.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {t_s.shape}")
    bad = np.flatnonzero(~np.isfinite(t_s))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] is not finite ({t_s[bad[0]]})")
    step = np.diff(t_s)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        i = bad[0] + 1
        raise ValueError(
            f"time stamps must increase strictly: {name}[{i}] = {t_s[i]!r} "
            f"follows {name}[{i - 1}] = {t_s[i - 1]!r}"
        )


@dataclass(frozen=True)
class ArraySamples:
    """Raw accelerometer-array outputs.

    Parameters
    ----------
    t_s : array (T,)
        Sample times, s; finite and strictly increasing.
    accel_mps2 : array (T, N)
        Sensor outputs along each sensing axis, m/s^2 (specific force). Rows
        that are not finite mark invalid samples; see :attr:`invalid`.
    """

    t_s: np.ndarray
    accel_mps2: np.ndarray

    def __post_init__(self) -> None:
        t = frozen_array(self.t_s, "t_s")
        a = frozen_array(self.accel_mps2, "accel_mps2")
        check_time_axis(t)
        if a.ndim != 2 or a.shape[0] != t.shape[0]:
            raise ValueError(
                f"accel_mps2 must have shape (T, N) with T = {t.shape[0]} samples, got {a.shape}"
            )
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "accel_mps2", a)

    @property
    def n_channels(self) -> int:
        return self.accel_mps2.shape[1]

    @property
    def invalid(self) -> np.ndarray:
        """Boolean mask (T,) of samples with a non-finite channel."""
        return ~np.all(np.isfinite(self.accel_mps2), axis=1)


@dataclass(frozen=True)
class ArrayKinematics:
    """Body kinematics solved from an accelerometer array, at the sample times.

    Parameters
    ----------
    t_s : array (T,)
        Times, s.
    omega_dot_b_rps2 : array (T, 3)
        Angular acceleration, body frame, rad/s^2.
    f_b_mps2 : array (T, 3)
        Specific force at the body origin, body frame, m/s^2.
    rate_products_rps2 : array (T, 3)
        ``[w_y w_z, w_x w_z, w_x w_y]``, rad^2/s^2; NaN where the layout
        cannot solve them.
    rate_squares_rps2 : array (T, 3)
        ``[w_x^2, w_y^2, w_z^2]``, rad^2/s^2; NaN where the layout cannot
        solve them (the nine-cube never excites them).
    """

    t_s: np.ndarray
    omega_dot_b_rps2: np.ndarray
    f_b_mps2: np.ndarray
    rate_products_rps2: np.ndarray
    rate_squares_rps2: np.ndarray

    def __post_init__(self) -> None:
        freeze_fields(
            self,
            {
                "t_s": (),
                "omega_dot_b_rps2": (3,),
                "f_b_mps2": (3,),
                "rate_products_rps2": (3,),
                "rate_squares_rps2": (3,),
            },
        )
