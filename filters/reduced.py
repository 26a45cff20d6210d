"""The solve with failed channels excluded: the rest, rate-aided where they must be.

With channels left out the array may no longer solve every rate product beside the
angular acceleration and force (on the nine-cube, A6 or A9 alone carries ``wdot_x``
once the other is gone, and ``w_y w_z`` with it). :class:`ngnav.frontend.ArraySolver`
on the remaining channels says which terms it still solves; the rest are *aided*:
computed from the filter's rate and taken out of the remaining channels before the
solve. So the features a block propagates and measures with are

    ``phi = S_m a - A_m q(w)``

with ``S_m`` the reduced solve in the filter's feature order (zero columns for the
excluded channels, zero rows for the aided features) and ``A_m = S_m G_q`` what the
aided quadratic terms ``q(w)`` leave in the solved ones. A rate error ``dw`` then
reaches the angular acceleration and force as ``-A_m J(w) dw`` (the filter's
transition carries it), and the aided products are no measurement of the rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.frontend import ArraySolver
from ngnav.layout import N_FEATURES, ArrayLayout


@dataclass(frozen=True)
class ReducedSolve:
    """The solve of an array with some channels excluded (see the module docstring).

    Attributes
    ----------
    excluded : int
        Bitmask of the channels left out (bit ``i``: channel ``i + 1``).
    solve_matrix : array (k, N)
        ``S_m``: the filter's k features from all N channels (zero columns excluded).
    aided_quadratics : array (k, 6)
        ``A_m``: the solved features' dependence on the aided quadratic terms
        ``(wx^2, wy^2, wz^2, wy wz, wx wz, wx wy)`` (zero columns for those solved).
    solved : array (k,) of bool
        Which of the filter's features are still solved (False: aided).
    """

    excluded: int
    solve_matrix: np.ndarray
    aided_quadratics: np.ndarray
    solved: np.ndarray


def reduced_solve(
    layout: ArrayLayout, noise_sigma_mps2: np.ndarray, columns: np.ndarray, excluded: int
) -> ReducedSolve:
    """The solve without the channels in ``excluded`` (bitmask), in the filter's features.

    ``columns`` (k,) are the feature indices (:data:`ngnav.layout.FEATURE_NAMES`) the
    filter carries, those the full layout solves. Raises ValueError, naming what is
    lost, when the remaining channels cannot solve angular acceleration and force.
    """
    n = layout.n_sensors
    keep = np.array([not (excluded >> i) & 1 for i in range(n)])
    if not keep.any():
        raise ValueError("every channel is excluded")
    sub = ArrayLayout(layout.positions_b_m[keep], layout.axes_b[keep], name="remaining")
    sigma = np.broadcast_to(np.asarray(noise_sigma_mps2, dtype=float), (n,))
    solver = ArraySolver(sub, sigma[keep])  # raises when wdot or f is lost
    cols = np.asarray(columns, dtype=int)
    k = cols.shape[0]
    s = np.zeros((k, n))
    a = np.zeros((k, 6))
    solved = np.isin(cols, solver.solved_columns)
    rows = {int(c): r for r, c in enumerate(solver.solved_columns)}
    sm = solver.solve_matrix
    # what the aided quadratic terms leave in the solved features: S_m G_aided
    g_quad = np.zeros((sub.n_sensors, N_FEATURES - 6))
    aided = solver.aided_columns
    g_quad[:, aided - 6] = sub.design[:, aided]
    # the full layout's features the reduced one cannot solve and is not told about
    # (the quadratic terms it neither solves nor excites) are zero in both
    for j, c in enumerate(cols.tolist()):
        if c in rows:
            s[j, keep] = sm[rows[c]]
            a[j] = sm[rows[c]] @ g_quad
    return ReducedSolve(int(excluded), s, a, solved)
