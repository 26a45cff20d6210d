import numpy as np


def rigid_body_outputs_direct(positions, axes, omega_dot, f, omega):
    """Paper eq. 3 evaluated directly with cross products (independent of the design matrix)."""
    acc = f + np.cross(omega_dot, positions) + np.cross(omega, np.cross(omega, positions))
    return np.sum(axes * acc, axis=-1)
