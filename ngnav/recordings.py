"""Static poses from bench recordings: one CSV per pose, or still segments of one recording.

A pose's reading is the mean of its samples, with the 1-sigma the configuration's noise
gives it. A pose that is not still, has saturated or invalid samples, or is too short is
reported and skipped, never silently used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ngnav.records import ArraySamples

#: Shortest still stretch taken as a pose, s: a second of samples makes the mean's noise
#: small beside the axis errors a bench calibration looks for.
MIN_POSE_S = 1.0
#: Window of the still detector, s: short beside a pose, long enough for a stable spread.
STILL_WINDOW_S = 0.25
#: A window is still when every channel's spread is at most this many times its noise...
STILL_SPREAD = 1.5
#: ...and its mean within this many sigmas of the previous window's (no slow turning).
STILL_MEAN_SIGMAS = 5.0


@dataclass(frozen=True)
class Poses:
    """The poses found in bench recordings.

    Attributes
    ----------
    means_mps2 : array (K, N)
        Each pose's mean channel outputs, m/s^2.
    sigma_mps2 : array (K, N)
        Their 1-sigma: the sample noise over sqrt(samples), and the bias walk over the
        session (its spread about the session's mean offset).
    labels : tuple of str
        Where each pose came from (a file, or a time span of the recording).
    skipped : tuple of str
        Each stretch or file left out, with the reason.
    """

    means_mps2: np.ndarray
    sigma_mps2: np.ndarray
    labels: tuple[str, ...]
    skipped: tuple[str, ...]


def _walk_var(bias_rw_mps2_rts: np.ndarray, session_s: float) -> np.ndarray:
    # a random walk's spread about its mean over the session, q^2 T / 6 (time-averaged)
    return np.asarray(bias_rw_mps2_rts, dtype=float) ** 2 * session_s / 6.0


def _still_problem(a: np.ndarray, noise: np.ndarray, range_mps2: float) -> str | None:
    """Why the samples (T, N) of one pose cannot be used, or None."""
    sat = np.abs(a) >= range_mps2
    if np.any(sat):
        ch = np.flatnonzero(sat.any(axis=0))
        return f"{int(sat.sum())} saturated samples (channels {', '.join(str(c + 1) for c in ch)})"
    spread = a.std(axis=0)
    moving = np.flatnonzero(spread > STILL_SPREAD * noise)
    if moving.size:
        c = moving[0]
        return (
            f"not still: channel {c + 1} spreads {spread[c]:.3g} m/s^2 against its noise "
            f"{noise[c]:.3g}"
        )
    half = a.shape[0] // 2
    drift = np.abs(a[:half].mean(axis=0) - a[half:].mean(axis=0))
    limit = STILL_MEAN_SIGMAS * noise * np.sqrt(4.0 / a.shape[0])
    if np.any(drift > limit):
        c = int(np.argmax(drift / limit))
        return f"not still: channel {c + 1}'s mean moves {drift[c]:.3g} m/s^2 within the pose"
    return None


def poses_from_files(
    recordings: list[tuple[str, ArraySamples]],
    noise_sigma_mps2: np.ndarray,
    bias_rw_mps2_rts: np.ndarray,
    range_mps2: float,
) -> Poses:
    """One pose per recording (``(label, samples)``): its mean, if it is usable."""
    noise = np.asarray(noise_sigma_mps2, dtype=float)
    means, counts, labels, skipped = [], [], [], []
    t_first, t_last = np.inf, -np.inf
    for label, s in recordings:
        a = s.accel_mps2[~s.invalid]
        n_bad = int(s.invalid.sum())
        duration = float(s.t_s[-1] - s.t_s[0]) if s.t_s.size > 1 else 0.0
        if duration < MIN_POSE_S or a.shape[0] < 2:
            skipped.append(f"{label}: {duration:.2f} s, shorter than {MIN_POSE_S:g} s")
            continue
        problem = _still_problem(a, noise, range_mps2)
        if problem:
            skipped.append(f"{label}: {problem}")
            continue
        means.append(a.mean(axis=0))
        counts.append(a.shape[0])
        labels.append(label + (f" ({n_bad} invalid samples left out)" if n_bad else ""))
        t_first, t_last = min(t_first, s.t_s[0]), max(t_last, s.t_s[-1])
    return _poses(means, counts, labels, skipped, noise, bias_rw_mps2_rts, t_first, t_last)


def _poses(means, counts, labels, skipped, noise, bias_rw, t_first, t_last) -> Poses:
    n_ch = noise.shape[0]
    if not means:
        return Poses(np.zeros((0, n_ch)), np.zeros((0, n_ch)), (), tuple(skipped))
    session = max(float(t_last - t_first), 0.0)
    var = noise**2 / np.asarray(counts, dtype=float)[:, None] + _walk_var(bias_rw, session)
    return Poses(np.array(means), np.sqrt(var), tuple(labels), tuple(skipped))


def poses_from_recording(
    samples: ArraySamples,
    noise_sigma_mps2: np.ndarray,
    bias_rw_mps2_rts: np.ndarray,
    range_mps2: float,
) -> Poses:
    """The still stretches of one long recording, each a pose (the motion between them
    is left out). A window of :data:`STILL_WINDOW_S` is still when every channel spreads
    at most :data:`STILL_SPREAD` times its noise and its mean stays within
    :data:`STILL_MEAN_SIGMAS` sigmas of the previous window's; a stretch of still windows
    shorter than :data:`MIN_POSE_S`, or with saturated samples, is reported and skipped."""
    noise = np.asarray(noise_sigma_mps2, dtype=float)
    t, a = samples.t_s, samples.accel_mps2
    dt = float(np.median(np.diff(t)))
    w = max(2, round(STILL_WINDOW_S / dt))
    n_win = a.shape[0] // w
    if n_win == 0:
        raise ValueError(f"the recording is {a.shape[0]} samples, shorter than one window")
    blocks = a[: n_win * w].reshape(n_win, w, -1)
    ok_rows = np.all(np.isfinite(blocks), axis=(1, 2))
    with np.errstate(invalid="ignore"):
        mean = blocks.mean(axis=1)
        spread = blocks.std(axis=1)
    quiet = ok_rows & np.all(spread <= STILL_SPREAD * noise, axis=1)
    same = np.zeros(n_win, dtype=bool)
    tol = STILL_MEAN_SIGMAS * noise * np.sqrt(2.0 / w)
    same[1:] = np.all(np.abs(mean[1:] - mean[:-1]) <= tol, axis=1)
    means, counts, labels, skipped = [], [], [], []
    t_first, t_last = np.inf, -np.inf
    j = 0
    while j < n_win:
        if not quiet[j]:
            j += 1
            continue
        k = j + 1
        while k < n_win and quiet[k] and same[k]:
            k += 1
        seg = a[j * w : k * w]
        t0, t1 = float(t[j * w]), float(t[k * w - 1])
        label = f"{t0:.2f}-{t1:.2f} s"
        if t1 - t0 < MIN_POSE_S:
            if t1 - t0 >= 2 * STILL_WINDOW_S:  # a pause worth mentioning, not a stray window
                skipped.append(f"{label}: still for {t1 - t0:.2f} s, shorter than {MIN_POSE_S:g} s")
        elif np.any(np.abs(seg) >= range_mps2):
            skipped.append(f"{label}: {int((np.abs(seg) >= range_mps2).sum())} saturated samples")
        else:
            means.append(seg.mean(axis=0))
            counts.append(seg.shape[0])
            labels.append(label)
            t_first, t_last = min(t_first, t0), max(t_last, t1)
        j = k
    return _poses(means, counts, labels, skipped, noise, bias_rw_mps2_rts, t_first, t_last)
