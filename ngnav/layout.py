"""Accelerometer-array geometry and the linear output model (SPEC section 2).

A rigid body carries N single-axis accelerometers; sensor i sits at ``r_i``
(body frame, m) and senses along the unit vector ``theta_i``. Its output

    A_i = theta_i . (f_0 + wdot x r_i + w x (w x r_i))

is *exactly linear* in the 12 kinematic features

    phi = [wdot_x, wdot_y, wdot_z, f_x, f_y, f_z,
           w_x^2, w_y^2, w_z^2, w_y w_z, w_x w_z, w_x w_y]

so ``A = G @ phi`` with a design matrix ``G`` (N, 12) that depends on the
geometry only. Rows of G: ``[(r_i x theta_i)^T, theta_i^T, q_i^T]`` where
``theta^T W^2 r = (theta.w)(r.w) - (theta.r)|w|^2`` gives the quadratic
coefficients ``q``. Everything else (forward model, least squares inverse,
mounting-error term) is built on this matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Names of the 12 kinematic features, in column order of the design matrix.
FEATURE_NAMES: tuple[str, ...] = (
    "omega_dot_x",
    "omega_dot_y",
    "omega_dot_z",
    "f_x",
    "f_y",
    "f_z",
    "wx*wx",
    "wy*wy",
    "wz*wz",
    "wy*wz",
    "wx*wz",
    "wx*wy",
)
#: Column slices of the feature vector, derived from FEATURE_NAMES.
OMEGA_DOT = slice(0, 3)
SPECIFIC_FORCE = slice(3, 6)
RATE_SQUARES = slice(6, 9)
RATE_PRODUCTS = slice(9, 12)
N_FEATURES = len(FEATURE_NAMES)


def kinematic_features(
    omega_dot_b_rps2: np.ndarray, f_b_mps2: np.ndarray, omega_b_rps: np.ndarray
) -> np.ndarray:
    """Feature vectors phi (..., 12) from body kinematics (..., 3) each.

    Parameters
    ----------
    omega_dot_b_rps2 : array (..., 3)
        Angular acceleration, body frame, rad/s^2.
    f_b_mps2 : array (..., 3)
        Specific force at the body origin, body frame, m/s^2.
    omega_b_rps : array (..., 3)
        Angular rate, body frame, rad/s.
    """
    wd, f, w = np.broadcast_arrays(
        np.asarray(omega_dot_b_rps2, dtype=float),
        np.asarray(f_b_mps2, dtype=float),
        np.asarray(omega_b_rps, dtype=float),
    )
    return np.concatenate([wd, f, rate_quadratics(w)], axis=-1)


def rate_quadratics(omega_b_rps: np.ndarray) -> np.ndarray:
    """Quadratic rate terms (..., 6): ``[wx^2, wy^2, wz^2, wy wz, wx wz, wx wy]``, rad^2/s^2."""
    w = np.asarray(omega_b_rps, dtype=float)
    wx, wy, wz = w[..., 0], w[..., 1], w[..., 2]
    return np.stack([wx * wx, wy * wy, wz * wz, wy * wz, wx * wz, wx * wy], axis=-1)


def design_matrix(positions_b_m: np.ndarray, axes_b: np.ndarray) -> np.ndarray:
    """Design matrix G (N, 12) of the linear output model ``A = G @ phi``.

    Parameters
    ----------
    positions_b_m : array (N, 3)
        Sensor positions from the body origin, body frame, m.
    axes_b : array (N, 3)
        Sensing directions (unit vectors), body frame.
    """
    r = np.asarray(positions_b_m, dtype=float)
    t = np.asarray(axes_b, dtype=float)
    r_dot_t = np.sum(r * t, axis=1)
    squares = t * r - r_dot_t[:, None]
    products = np.stack(
        [
            t[:, 1] * r[:, 2] + t[:, 2] * r[:, 1],
            t[:, 0] * r[:, 2] + t[:, 2] * r[:, 0],
            t[:, 0] * r[:, 1] + t[:, 1] * r[:, 0],
        ],
        axis=1,
    )
    return np.hstack([np.cross(r, t), t, squares, products])


def _readonly(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class ArrayLayout:
    """Geometry of an accelerometer array.

    Parameters
    ----------
    positions_b_m : array (N, 3)
        Sensor positions from the body origin, body frame (FRD), m.
    axes_b : array (N, 3)
        Sensing directions, body frame. Must be unit vectors (within 1e-9).
    name : str
        Human-readable name.
    lever_arm_m : float or None
        The characteristic lever arm (cube edge) when the layout has one.
    """

    positions_b_m: np.ndarray
    axes_b: np.ndarray
    name: str = "custom"
    lever_arm_m: float | None = None
    _g: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        r = np.asarray(self.positions_b_m, dtype=float)
        t = np.asarray(self.axes_b, dtype=float)
        if r.ndim != 2 or r.shape[1] != 3:
            raise ValueError(f"positions_b_m must have shape (N, 3), got {r.shape}")
        if t.shape != r.shape:
            raise ValueError(f"axes_b must have shape {r.shape} like positions_b_m, got {t.shape}")
        if r.shape[0] == 0:
            raise ValueError("an array layout needs at least one sensor")
        if not (np.all(np.isfinite(r)) and np.all(np.isfinite(t))):
            raise ValueError("layout positions and axes must be finite")
        norms = np.linalg.norm(t, axis=1)
        bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-9)
        if bad.size:
            raise ValueError(
                f"sensing axis of sensor {bad[0] + 1} has norm {norms[bad[0]]:.6g}, "
                "expected a unit vector"
            )
        object.__setattr__(self, "positions_b_m", _readonly(r))
        object.__setattr__(self, "axes_b", _readonly(t))
        object.__setattr__(self, "_g", _readonly(design_matrix(r, t)))

    @property
    def n_sensors(self) -> int:
        """Number of single-axis accelerometers N."""
        return self.positions_b_m.shape[0]

    @property
    def design(self) -> np.ndarray:
        """Design matrix G (N, 12), read-only; see :func:`design_matrix`."""
        return self._g

    def outputs(
        self, omega_dot_b_rps2: np.ndarray, f_b_mps2: np.ndarray, omega_b_rps: np.ndarray
    ) -> np.ndarray:
        """Exact sensor outputs (..., N), m/s^2, for rigid-body kinematics (..., 3) each."""
        return kinematic_features(omega_dot_b_rps2, f_b_mps2, omega_b_rps) @ self._g.T


def nine_accelerometer_cube(lever_arm_m: float = 0.1) -> ArrayLayout:
    """The paper's nine-accelerometer layout (paper eqs. 23-24, SPEC section 2).

    Three sensors per body axis; positions in units of the cube edge ``l``:
    x-sensors at (0,0,0), (0,1,0), (0,0,1); y-sensors at (0,0,0), (1,0,0),
    (0,0,1); z-sensors at (0,0,0), (1,0,0), (0,1,0). Every ``r_i`` is
    perpendicular to its ``theta_i``, so no squared rate appears and the nine
    outputs determine omega_dot, f_0 and the three rate products exactly.

    Parameters
    ----------
    lever_arm_m : float
        Cube edge l, m (the paper's cube: 0.1 m).
    """
    if not np.isfinite(lever_arm_m) or lever_arm_m <= 0:
        raise ValueError(f"lever_arm_m must be positive, got {lever_arm_m}")
    unit = np.array(
        [
            [0, 0, 0],
            [0, 1, 0],
            [0, 0, 1],
            [0, 0, 0],
            [1, 0, 0],
            [0, 0, 1],
            [0, 0, 0],
            [1, 0, 0],
            [0, 1, 0],
        ],
        dtype=float,
    )
    axes = np.repeat(np.eye(3), 3, axis=0)
    return ArrayLayout(unit * lever_arm_m, axes, name="nine-cube", lever_arm_m=lever_arm_m)


def six_accelerometer_cube(lever_arm_m: float = 0.1) -> ArrayLayout:
    """The six-accelerometer cube of Chen, Lee & DeBra (1994).

    J.-H. Chen, S.-C. Lee, D. B. DeBra, "Gyroscope free strapdown inertial
    measurement unit by six linear accelerometers", J. Guidance, Control and
    Dynamics 17(2), 1994. One sensor at the centre of each face of a cube whose
    centre is the body origin (face centres at distance ``l`` along +-x, +-y,
    +-z), sensing along a face diagonal. The 6x6 block for omega_dot and f_0 is
    full rank, but the rate products it excites cannot be solved as well: this
    layout needs the rate from elsewhere (integration), which is exactly the
    information the nine-sensor layout adds.

    Parameters
    ----------
    lever_arm_m : float
        Distance l from the cube centre to each face centre, m.
    """
    if not np.isfinite(lever_arm_m) or lever_arm_m <= 0:
        raise ValueError(f"lever_arm_m must be positive, got {lever_arm_m}")
    s = 1.0 / np.sqrt(2.0)
    pos = np.array(
        [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=float
    )
    axes = s * np.array(
        [[0, 1, 1], [1, 0, 1], [1, 1, 0], [0, 1, -1], [-1, 0, 1], [1, -1, 0]], dtype=float
    )
    return ArrayLayout(pos * lever_arm_m, axes, name="six-cube", lever_arm_m=lever_arm_m)


LAYOUTS = {"nine-cube": nine_accelerometer_cube, "six-cube": six_accelerometer_cube}


def layout_by_name(name: str, lever_arm_m: float = 0.1) -> ArrayLayout:
    """Look up a built-in layout by name (``nine-cube`` or ``six-cube``)."""
    try:
        return LAYOUTS[name](lever_arm_m)
    except KeyError:
        raise ValueError(f"unknown layout {name!r}; choose one of {sorted(LAYOUTS)}") from None
