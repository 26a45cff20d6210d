"""The filter's model of the solved features: their noise, the biases' effect, the solve.

What the noise model (:class:`filters.noise.FilterNoise`), the solve matrix and the forecast's
feedback fix in :class:`filters.ekf.NavFilter` (the noise blocks, the transition's and the rate
measurement's bias columns, the caches), and the switch to a reduced solve when channels are
excluded (:mod:`filters.exclusion`).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from filters import kernels
from filters.algebra import _product_derivatives
from filters.noise import FilterNoise
from filters.state import N_NAV, POS, RATE, VEL
from ngnav.compensation import QUAD_PAIRS


class FeatureModelMixin:
    """Derive the feature model's members; switch the solve; widen the biases' walk."""

    def set_extra_bias_walk(self, cov_per_s: np.ndarray) -> None:
        """Add ``cov_per_s`` (k, k) to the biases' random walk from now on (zeros: none).

        While the parity names a group of channels without saying which of them fails,
        the offset of the failing one is carried by the bias states (their raw ``S b``
        holds every channel's offset), given room to move along the group's directions.
        """
        self.extra_bias_walk = np.asarray(cov_per_s, dtype=float).copy()
        self._q_walk_cache = {}

    def set_solve(
        self,
        noise: FilterNoise,
        solve_matrix: np.ndarray,
        quad_feedback: np.ndarray | None,
        feature_quad_feedback: np.ndarray | None,
        rate_rows: np.ndarray,
        aided_quadratics: np.ndarray,
        bias_map: np.ndarray,
    ) -> None:
        """Switch to a reduced solve of the array: channels excluded (:mod:`filters.reduced`).

        The bias states are the raw feature biases ``S b`` of the solve; the new solve's
        are ``bias_map`` (k, k) times the old (``S_m S^-1``, exact for a square solve),
        and the estimate and covariance are mapped so. ``rate_rows`` (nq,) says which
        products still measure the rate (its gate takes their number of dof);
        ``aided_quadratics`` ``A_m`` (k, 6) is what the aided quadratic terms, computed
        from the rate, leave in the solved features: a rate error reaches the angular
        acceleration and force through it (:meth:`propagation_matrices`).
        """
        n = self.layout.n
        bs = self.layout.bias
        j = np.eye(n)
        j[bs, bs] = bias_map
        self.bias = bias_map @ self.bias
        self.P = j @ self.P @ j.T
        self._symmetrise()
        self.noise = noise
        self.solve_matrix = solve_matrix
        self.quad_feedback = quad_feedback
        self.feature_quad_feedback = feature_quad_feedback
        self.rate_rows = np.asarray(rate_rows, dtype=bool).copy()
        aided = np.asarray(aided_quadratics, dtype=float)
        self._aided_quadratics = aided[0:6].copy()
        self._aided_in_quad = aided[6:].copy()
        self.gate_q = float(chi2.ppf(self.gate_probability, max(int(self.rate_rows.sum()), 1)))
        self._derive_feature_model()

    def _derive_feature_model(self) -> None:
        """What the noise model, the solve and the forecast's feedback fix: the noise
        blocks, the transition's and the rate measurement's bias columns, the caches."""
        n = self.layout.n
        k = 6 + self.layout.nq
        #: The rate products that still measure the rate (the rate update's dof).
        self.rate_dof = int(self.rate_rows.sum())
        self._sww = self.noise.feature_cov[0:3, 0:3]
        # the rate's noise over one block (FilterNoise.block_wdot_cov): the loop's mapped
        # noise plus the positive part of what the mapping took off
        self._sww_block = self._sww
        if self.noise.block_wdot_cov is not None:
            ev, vec = np.linalg.eigh(np.asarray(self.noise.block_wdot_cov) - self._sww)
            self._sww_block = self._sww + (vec * np.maximum(ev, 0.0)) @ vec.T
        self._sff = self.noise.feature_cov[3:6, 3:6]
        self._sfw = self.noise.feature_cov[3:6, 0:3]
        self._sqq = self.noise.feature_cov[6:, 6:]
        # what a bias error leaves in the compensated [wdot, f, quad] (FilterNoise.bias_effect)
        te = self.noise.bias_effect
        te = np.eye(k) if te is None else np.array(te, dtype=float)
        self._bias_effect_f = te[3:6].copy()  # into the force (FRD), per block rotated to NED
        # what a rate error leaves in the propagated [wdot, f] (6, 3 per unit J6(w)): the
        # forecast's products and any aided ones, through the loop's map A
        into = [m for m in (self.feature_quad_feedback, self._aided_quadratics) if m is not None]
        self._quad_into_features = te[0:6, 0:6] @ sum(into) if into else None
        # the constant part of the error dynamics, copied and filled per block: only
        # the navigation rows (position, velocity, attitude, rate) of F are non-zero
        # (biases and the angle-of-attack offset walk, DR and K are constants)
        fc = np.zeros((N_NAV, n))
        fc[POS, VEL] = np.eye(3)
        fc[RATE, self.layout.bias] = -te[0:3]
        self._fc_base = fc
        # the rate measurement's Jacobian without its rate columns (filled per block)
        h_rate = np.zeros((self.layout.nq, n))
        h_rate[:, self.layout.bias] = te[6:]
        self._h_rate_base = h_rate
        self._q12_cache: dict[tuple[int, float], np.ndarray] = {}
        self._q_walk_cache: dict[float, np.ndarray] = {}
        self._weights_cache: dict[tuple[int, float], tuple[np.ndarray, ...]] = {}
        if self.solve_matrix is not None:
            # T S with each column repeated 3 times: the compensated features carry the
            # sensor positions' effect through the forecast's loop as they carry a bias's
            # (geometry_jacobian)
            ts = te @ np.asarray(self.solve_matrix, dtype=float)
            self._solve_rep = np.repeat(ts, 3, axis=1)
            self._solve_t = ts
        d = _product_derivatives(self.quad_pairs.tolist())
        if self.quad_feedback is not None:
            fb = np.asarray(self.quad_feedback, dtype=float)
            if fb.shape != (self.layout.nq, 6):
                raise ValueError(
                    f"quad_feedback must have shape ({self.layout.nq}, 6), got {fb.shape}"
                )
            d = d + np.einsum("rs,scm->rcm", fb, _product_derivatives(QUAD_PAIRS))
        self._quad_d = d
        self._quad6_d = _product_derivatives(QUAD_PAIRS)  # (6, 3, 3): d q6 / dw = D @ w
        # the aided products' map into the solved ones (nq, 6); (nq, 0) without
        aq = self._aided_in_quad
        self._aided_rate_cols = np.zeros((self.layout.nq, 0)) if aq is None else aq
        # the kernels' arguments these fix (ProcessMixin._geometry_args,
        # MeasurementsMixin._rate_jacobian_parts)
        lay = self.layout
        with_dr = bool(lay.n_dr)
        self._geo_fixed = (
            bool(lay.n_dr or lay.n_cal),
            lay.geometry.start,
            self.sensor_axes_b if with_dr else kernels.ABSENT,
            self._solve_t if with_dr else kernels.ABSENT,
        )
        self._rate_fixed = (self._h_rate_base, self._quad_d, self._aided_rate_cols, self._quad6_d)
