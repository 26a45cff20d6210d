"""Figures of a run and of a campaign, as PNG files and one self-contained HTML page.

matplotlib's object API on the Agg canvas (``matplotlib.figure.Figure``, no pyplot):
files only, no display and no global backend state, so it runs the same in CI, over SSH
and inside a notebook. Each function takes records and arrays, not files: the CLI
(``ngnav plot``) reads a run and hands them over.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ngnav.records import Estimates, GpsInnovations
from ngnav.rotation import euler_from_quat

#: Figure size (inches) and resolution of every PNG: legible in the HTML page at 100 %.
FIG_SIZE_IN = (10.0, 7.0)
DPI = 100
#: The NED and FRD axis names of the three components of each navigation block.
#: The files :func:`plot_run` and :func:`write_report` may write into a run's ``plots/``.
RUN_PLOT_FILES = (
    "trajectory.png",
    "position.png",
    "velocity.png",
    "attitude.png",
    "rate.png",
    "errors.png",
    "nis.png",
    "report.html",
)
AXES = {"pos": ("N", "E", "D"), "vel": ("N", "E", "D"), "att": ("N", "E", "D"), "rate": "xyz"}


@dataclass(frozen=True)
class RunPlotData:
    """What the run's figures show.

    Attributes
    ----------
    estimates : Estimates
        The filter's epochs; ``cov_nav``'s diagonal gives the bands.
    fix_t_s : array (M,)
        GPS fix times, s.
    fix_ned_m : array (M, 3)
        GPS antenna positions in the run's NED frame, m.
    nis : GpsInnovations or None
        Each fix's NIS and gate decisions (``estimates.nis.csv``).
    nis_gate : float
        The gate the NIS were tested against (chi-square, 3 dof).
    outages : sequence of (float, float)
        Spans without GPS (start, end), s: shaded.
    errors : array (E, 12) or None
        Truth minus estimate (position, velocity, NED attitude in rad, rate), state order.
    """

    estimates: Estimates
    fix_t_s: np.ndarray
    fix_ned_m: np.ndarray
    nis: GpsInnovations | None = None
    nis_gate: float = float("nan")
    outages: Sequence[tuple[float, float]] = ()
    errors: np.ndarray | None = None


def outage_spans(fix_t_s: np.ndarray, min_gap_s: float) -> list[tuple[float, float]]:
    """Gaps between consecutive fixes longer than ``min_gap_s``, as (start, end) in s."""
    t = np.asarray(fix_t_s, dtype=float)
    if t.size < 2:
        return []
    gaps = np.flatnonzero(np.diff(t) > min_gap_s)
    return [(float(t[i]), float(t[i + 1])) for i in gaps]


def _shade(ax, outages: Sequence[tuple[float, float]]) -> None:
    for k, (t0, t1) in enumerate(outages):
        ax.axvspan(t0, t1, color="0.85", zorder=0, label="GPS outage" if k == 0 else None)


def _new(rows: int, cols: int = 1) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=FIG_SIZE_IN, dpi=DPI, layout="constrained")
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False)
    return fig, axes


def _save(fig: Figure, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path


def plot_trajectory(data: RunPlotData, path: Path) -> Path:
    """The horizontal path (east right, north up) with the GPS fixes, rejected fixes marked."""
    fig = Figure(figsize=FIG_SIZE_IN, dpi=DPI, layout="constrained")
    ax = fig.subplots()
    est = data.estimates
    ax.plot(est.pos_ned_m[:, 1], est.pos_ned_m[:, 0], lw=1.2, label="estimate")
    ax.plot(data.fix_ned_m[:, 1], data.fix_ned_m[:, 0], ".", ms=2, color="0.5", label="GPS fix")
    if data.nis is not None and data.nis.t_s.size:
        bad = ~data.nis.pos_accepted
        if np.any(bad):
            i = np.searchsorted(data.fix_t_s, data.nis.t_s[bad]).clip(0, data.fix_t_s.size - 1)
            ax.plot(
                data.fix_ned_m[i, 1], data.fix_ned_m[i, 0], "x", color="red", ms=8,
                label=f"rejected fix ({int(bad.sum())})",
            )  # fmt: skip
    for k, (t0, t1) in enumerate(data.outages):
        m = (est.t_s >= t0) & (est.t_s <= t1)
        ax.plot(
            est.pos_ned_m[m, 1], est.pos_ned_m[m, 0], lw=3, color="orange",
            label="during GPS outage" if k == 0 else None,
        )  # fmt: skip
    ax.set_xlabel("east, m")
    ax.set_ylabel("north, m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best")
    ax.set_title("trajectory")
    return _save(fig, path)


def _block_with_band(
    data: RunPlotData, path: Path, title: str, values: np.ndarray, sig: np.ndarray, labels, unit
) -> Path:
    fig, axes = _new(3)
    t = data.estimates.t_s
    for j in range(3):
        ax = axes[j, 0]
        _shade(ax, data.outages)
        ax.fill_between(
            t, values[:, j] - 3 * sig[:, j], values[:, j] + 3 * sig[:, j],
            color="C0", alpha=0.25, lw=0, label="+-3 sigma",
        )  # fmt: skip
        ax.plot(t, values[:, j], lw=0.8, color="C0", label="estimate")
        ax.set_ylabel(f"{labels[j]}, {unit}")
        ax.grid(True, lw=0.3)
    axes[0, 0].legend(loc="upper right")
    axes[0, 0].set_title(title)
    axes[-1, 0].set_xlabel("time, s")
    return _save(fig, path)


def _sigmas(est: Estimates) -> np.ndarray:
    return np.sqrt(np.maximum(np.einsum("eii->ei", est.cov_nav), 0.0))


def plot_states(data: RunPlotData, out_dir: Path) -> list[Path]:
    """Position, velocity, attitude and rate against time with +-3-sigma bands.

    The attitude is roll, pitch and yaw (yaw unwrapped) with the NED small-angle
    sigmas as their bands: the same to first order while the tilt is small.
    """
    est = data.estimates
    sig = _sigmas(est)
    rpy = np.rad2deg(euler_from_quat(est.q_nb))
    rpy[:, 2] = np.rad2deg(np.unwrap(np.deg2rad(rpy[:, 2])))
    blocks = [
        ("position.png", "position (NED)", est.pos_ned_m, sig[:, 0:3], AXES["pos"], "m"),
        ("velocity.png", "velocity (NED)", est.vel_ned_mps, sig[:, 3:6], AXES["vel"], "m/s"),
        (
            "attitude.png",
            "attitude",
            rpy,
            np.rad2deg(sig[:, 6:9]),
            ("roll", "pitch", "yaw (unwrapped)"),
            "deg",
        ),
        (
            "rate.png",
            "body rate (FRD)",
            np.rad2deg(est.omega_b_rps),
            np.rad2deg(sig[:, 9:12]),
            AXES["rate"],
            "deg/s",
        ),
    ]
    return [
        _block_with_band(data, out_dir / name, title, v, s, lab, unit)
        for name, title, v, s, lab, unit in blocks
    ]


def plot_errors(data: RunPlotData, path: Path) -> Path:
    """Truth minus estimate for the 12 navigation errors, against +-3 sigma."""
    if data.errors is None:
        raise ValueError("no truth: the errors figure needs truth.csv")
    est = data.estimates
    sig = _sigmas(est)
    err = np.array(data.errors, dtype=float)
    scale = np.ones(12)
    scale[6:12] = np.rad2deg(1.0)
    fig, axes = _new(4, 3)
    names = [("position", "m", "pos"), ("velocity", "m/s", "vel"), ("attitude", "deg", "att")]
    names.append(("rate", "deg/s", "rate"))
    for b, (name, unit, key) in enumerate(names):
        for j in range(3):
            ax = axes[b, j]
            c = 3 * b + j
            _shade(ax, data.outages)
            band = 3 * sig[:, c] * scale[c]
            ax.fill_between(est.t_s, -band, band, color="C0", alpha=0.25, lw=0)
            ax.plot(est.t_s, err[:, c] * scale[c], lw=0.6, color="C3")
            ax.set_title(f"{name} {AXES[key][j]}, {unit}", fontsize=9)
            ax.grid(True, lw=0.3)
    for j in range(3):
        axes[-1, j].set_xlabel("time, s")
    fig.suptitle("errors (truth - estimate, red) against +-3 sigma (blue)")
    return _save(fig, path)


def plot_nis(data: RunPlotData, path: Path) -> Path:
    """Each fix's position and velocity NIS (3 dof) with the gate; rejected fixes marked."""
    if data.nis is None:
        raise ValueError("no NIS: the figure needs estimates.nis.csv (ngnav run writes it)")
    nis = data.nis
    fig, axes = _new(2)
    for ax, (name, v, ok) in zip(
        axes[:, 0],
        (
            ("position", nis.nis_pos, nis.pos_accepted),
            ("velocity", nis.nis_vel, nis.vel_accepted),
        ),
        strict=True,
    ):
        _shade(ax, data.outages)
        ax.semilogy(nis.t_s[ok], v[ok], ".", ms=2, color="C0", label="fused")
        if np.any(~ok):
            ax.semilogy(nis.t_s[~ok], v[~ok], "x", color="red", label=f"rejected ({(~ok).sum()})")
        if np.isfinite(data.nis_gate):
            ax.axhline(data.nis_gate, color="red", lw=0.8, ls="--", label="gate")
        ax.axhline(3.0, color="0.3", lw=0.8, label="mean for 3 dof")
        ax.set_ylabel(f"GPS {name} NIS")
        ax.grid(True, lw=0.3, which="both")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("time, s")
    return _save(fig, path)


def plot_run(data: RunPlotData, out_dir: str | Path) -> list[Path]:
    """Every figure of a run into ``out_dir``: the errors only with truth, the NIS only
    with the NIS file. Returns the files written."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = [plot_trajectory(data, out / "trajectory.png"), *plot_states(data, out)]
    if data.errors is not None:
        files.append(plot_errors(data, out / "errors.png"))
    if data.nis is not None:
        files.append(plot_nis(data, out / "nis.png"))
    return files


def plot_nees(
    t_s: np.ndarray,
    averages: dict[str, np.ndarray],
    bounds: dict[str, tuple[float, float]],
    path: str | Path,
    title: str = "",
) -> Path:
    """Each block's run-averaged NEES against time, with its two-sided 95 % band.

    ``averages`` maps a block name to its per-epoch average (E,) at ``t_s``;
    ``bounds`` maps it to the chi-square band ``(lo, hi)`` of that average.
    """
    names = list(averages)
    fig, axes = _new(len(names))
    for ax, name in zip(axes[:, 0], names, strict=True):
        lo, hi = bounds[name]
        ax.axhspan(lo, hi, color="C2", alpha=0.2, lw=0, label="95 % band")
        ax.plot(t_s, averages[name], lw=0.7, color="C0", label="average NEES")
        ax.set_ylabel(name)
        ax.grid(True, lw=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    axes[0, 0].set_title(title or "NEES averaged over the runs")
    axes[-1, 0].set_xlabel("time, s")
    return _save(fig, Path(path))


def plot_paper_table(
    platform_deg: np.ndarray, angles_deg: dict[str, np.ndarray], path: str | Path
) -> Path:
    """The paper's Table 1: each series' angle error at every platform angle, and its mean
    absolute error as bars (``angles_deg``: name to the angles read, (turns,), deg)."""
    fig = Figure(figsize=FIG_SIZE_IN, dpi=DPI, layout="constrained")
    top, bottom = fig.subplots(2, 1)
    plat = np.asarray(platform_deg, dtype=float)
    means = []
    for name, angles in angles_deg.items():
        err = np.asarray(angles, dtype=float) - plat
        top.plot(plat, err, "o-", ms=3, lw=0.8, label=name)
        means.append(float(np.mean(np.abs(err))))
    top.axhline(0.0, color="0.3", lw=0.6)
    top.set_xlabel("platform angle, deg")
    top.set_ylabel("angle error, deg")
    top.grid(True, lw=0.3)
    top.legend(fontsize=8)
    top.set_title("indexing-head test (paper Table 1)")
    x = np.arange(len(means))
    bottom.bar(x, means, color=[f"C{k}" for k in range(len(means))])
    bottom.set_xticks(x, list(angles_deg), rotation=15)
    bottom.set_ylabel("mean absolute error, deg")
    bottom.grid(True, axis="y", lw=0.3)
    return _save(fig, Path(path))


def write_report(
    out_dir: str | Path, figures: Sequence[Path], title: str, summary: Sequence[str]
) -> Path:
    """One self-contained ``report.html`` in ``out_dir``: the summary lines and every
    figure embedded (base64), so the page can be mailed or archived alone."""
    out = Path(out_dir) / "report.html"
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1040px;margin:auto}"
        "img{max-width:100%}pre{background:#f4f4f4;padding:8px}</style>",
        f"</head><body><h1>{html.escape(title)}</h1>",
        "<pre>" + html.escape("\n".join(summary)) + "</pre>",
    ]
    for fig in figures:
        data = base64.b64encode(Path(fig).read_bytes()).decode("ascii")
        name = html.escape(Path(fig).stem)
        parts.append(f'<h2>{name}</h2><img alt="{name}" src="data:image/png;base64,{data}">')
    parts.append("</body></html>")
    out.write_text("\n".join(parts), encoding="utf-8")
    return out
