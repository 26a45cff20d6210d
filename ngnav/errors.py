"""The estimation failures any estimator raises, so that callers need not import one."""

from __future__ import annotations


class CovarianceError(RuntimeError):
    """The covariance stopped being symmetric positive definite.

    Attributes
    ----------
    partial : ngnav.records.RunResult or None
        What the run estimated before the failure, when the failure came out of
        a whole-run call after the filter had started (None otherwise): the
        estimates up to the failure, for the report and for a comparison.
    """

    partial = None


class LostTrackError(CovarianceError):
    """The filter lost its tilt or rate again soon after it was reopened.

    Reopening the attitude is a recovery for a one-off loss (the end of a long
    coast); needing it again soon after means the track is lost: the pipeline then
    starts the filter again from GPS (:mod:`filters.recovery`), and only a loss soon
    after that start ends the run. It subclasses :class:`CovarianceError`, so whatever
    handles a divergence handles this one (``partial`` included).
    """
