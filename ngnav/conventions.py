"""Frames, units and constants, stated once for the whole project.

- Navigation frame ``n``: local NED (north, east, down) tangent plane.
- Body frame ``b``: FRD (x forward, y right, z down), as MAVLink.
- Attitude: unit quaternion ``q_nb = [w, x, y, z]`` (Hamilton, scalar first)
  rotating body vectors into NED: ``v_n = q_nb * v_b * conj(q_nb)``.
- Units: SI inside (m, s, rad, m/s^2). Degrees, millivolts and g appear only at
  the edges and say so in their names (``angle_deg``, ``noise_mv``).
- Accelerometers measure specific force ``f = a - g``: a level body at rest
  reads ``f_b = [0, 0, -g]``.
"""

from __future__ import annotations

import numpy as np

#: Standard gravity, m/s^2 (CGPM 1901; also the MAVLink/ISO value).
G0_MPS2: float = 9.80665


def gravity_n_mps2() -> np.ndarray:
    """Gravity vector in NED, shape (3,), m/s^2: ``[0, 0, +g0]`` (down)."""
    return np.array([0.0, 0.0, G0_MPS2])
