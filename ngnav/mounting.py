"""Mounting errors of an accelerometer array (paper section 3.1, SPEC section 2).

Real sensors sit at ``r_i + dr_i`` and sense along ``normalise(theta_i + dtheta_i)``.
Because the output model is linear in the kinematic features phi (see
:mod:`ngnav.layout`), the exact error term of paper eq. 10,

    A_e = A_r - A = (G_real - G_nominal) @ phi,

is a fixed matrix ``E`` times phi: no approximation and none of the OCR'd
eq. 10's dropped terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.layout import ArrayLayout


def perpendicular_basis(axes_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to each sensing axis, shapes (N, 3) each.

    ``e1`` is the body axis least aligned with ``theta`` (first of ties: x, y,
    z), made perpendicular to ``theta``; ``e2 = theta x e1``. For the nine-cube
    layout this gives, for an x-axis sensor, e1 = y and e2 = z; for a y-axis
    sensor e1 = x and e2 = -z; for a z-axis sensor e1 = x and e2 = y.
    """
    t = np.asarray(axes_b, dtype=float)
    ref = np.eye(3)[np.argmin(np.abs(t), axis=1)]
    e1 = ref - np.sum(ref * t, axis=1, keepdims=True) * t
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(t, e1)
    return e1, e2


@dataclass(frozen=True)
class MountingErrors:
    """Per-sensor position and sensing-axis errors.

    Parameters
    ----------
    position_error_b_m : array (N, 3)
        ``dr_i``: where the sensitive element really is minus its nominal
        position, body frame, m.
    axis_error_rad : array (N, 2)
        Two small angles per sensor (rad): the real axis is
        ``normalise(theta + tan(a1) e1 + tan(a2) e2)`` with ``e1, e2`` from
        :func:`perpendicular_basis`.
    """

    position_error_b_m: np.ndarray
    axis_error_rad: np.ndarray

    def __post_init__(self) -> None:
        dr = np.array(self.position_error_b_m, dtype=float)
        da = np.array(self.axis_error_rad, dtype=float)
        if dr.ndim != 2 or dr.shape[1] != 3:
            raise ValueError(f"position_error_b_m must have shape (N, 3), got {dr.shape}")
        if da.shape != (dr.shape[0], 2):
            raise ValueError(f"axis_error_rad must have shape ({dr.shape[0]}, 2), got {da.shape}")
        if not (np.all(np.isfinite(dr)) and np.all(np.isfinite(da))):
            raise ValueError("mounting errors must be finite")
        if np.any(np.abs(da) >= np.pi / 4):
            raise ValueError("axis errors must be below 45 deg; larger is a different layout")
        dr.setflags(write=False)
        da.setflags(write=False)
        object.__setattr__(self, "position_error_b_m", dr)
        object.__setattr__(self, "axis_error_rad", da)

    @classmethod
    def zeros(cls, n_sensors: int) -> MountingErrors:
        """No mounting error for ``n_sensors`` sensors."""
        return cls(np.zeros((n_sensors, 3)), np.zeros((n_sensors, 2)))

    @property
    def n_sensors(self) -> int:
        return self.position_error_b_m.shape[0]

    def _check(self, nominal: ArrayLayout) -> None:
        if nominal.n_sensors != self.n_sensors:
            raise ValueError(
                f"mounting errors are for {self.n_sensors} sensors, layout has {nominal.n_sensors}"
            )

    def real_axes(self, nominal: ArrayLayout) -> np.ndarray:
        """Real sensing directions (N, 3), unit vectors, body frame."""
        self._check(nominal)
        e1, e2 = perpendicular_basis(nominal.axes_b)
        a = self.axis_error_rad
        u = nominal.axes_b + np.tan(a[:, :1]) * e1 + np.tan(a[:, 1:]) * e2
        return u / np.linalg.norm(u, axis=1, keepdims=True)

    def real_layout(self, nominal: ArrayLayout) -> ArrayLayout:
        """The layout as really built: nominal geometry plus these errors."""
        self._check(nominal)
        return ArrayLayout(
            nominal.positions_b_m + self.position_error_b_m,
            self.real_axes(nominal),
            name=f"{nominal.name}+errors",
            lever_arm_m=nominal.lever_arm_m,
        )

    def error_matrix(self, nominal: ArrayLayout) -> np.ndarray:
        """``E = G_real - G_nominal`` (N, 12): exact ``A_e = E @ phi`` (paper eq. 10)."""
        return self.real_layout(nominal).design - nominal.design
