"""Plain-CSV run files: ``array.csv``, ``gps.csv``, ``truth.csv``, ``estimates.csv``.

Formats (header row first, comma separated, one row per sample or fix):

- ``array.csv``: ``t_s,a1_mps2,...,aN_mps2``. An empty or ``nan`` cell marks
  a bad sample: the run holds the prediction there and counts it. Samples are
  uniform in time; a gap of a whole number of sample intervals is filled with
  held samples (counted as missing); any other gap, or unsorted or duplicate
  times, is an error naming file and line.
- ``gps.csv``: ``t_s,lat_deg,lon_deg,alt_m,vn_mps,ve_mps,vd_mps,h_acc_m,v_acc_m,vel_acc_mps``
  and optionally ``fix_type`` (3 = 3-D fix) and ``latency_s``. A row whose
  ``fix_type`` is below 3, or with an empty/nan latitude, longitude or ``h_acc_m``,
  is skipped and counted ("no fix"). An empty altitude (or ``v_acc_m``), horizontal
  velocity (``vn_mps``/``ve_mps``), vertical velocity or ``vel_acc_mps`` is a field
  the receiver did not give: the fix is used for the rest, counted per field.
- ``truth.csv`` (simulations only): ``t_s,n_m,e_m,d_m,vn_mps,ve_mps,vd_mps,qw,qx,qy,qz,
  wx_radps,wy_radps,wz_radps,wdx_radps2,wdy_radps2,wdz_radps2,fx_mps2,fy_mps2,fz_mps2``.

Extra columns are ignored; a missing column is an error naming it.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ngnav.records import (
    FIX_RANGE_KINDS,
    ArraySamples,
    FlightTruth,
    GpsFixes,
    fix_range_problems,
)

GPS_COLUMNS: tuple[str, ...] = (
    "t_s",
    "lat_deg",
    "lon_deg",
    "alt_m",
    "vn_mps",
    "ve_mps",
    "vd_mps",
    "h_acc_m",
    "v_acc_m",
    "vel_acc_mps",
)
#: Navigation-state columns shared by ``truth.csv`` and ``estimates.csv``:
#: NED position (m), NED velocity (m/s), ``q_nb`` (Hamilton, scalar first), body rate (rad/s).
NAV_COLUMNS: tuple[str, ...] = (
    "n_m",
    "e_m",
    "d_m",
    "vn_mps",
    "ve_mps",
    "vd_mps",
    "qw",
    "qx",
    "qy",
    "qz",
    "wx_radps",
    "wy_radps",
    "wz_radps",
)
TRUTH_COLUMNS: tuple[str, ...] = (
    "t_s",
    *NAV_COLUMNS,
    "wdx_radps2",
    "wdy_radps2",
    "wdz_radps2",
    "fx_mps2",
    "fy_mps2",
    "fz_mps2",
)


@dataclass
class ReadReport:
    """What a reader skipped or filled, by kind, for the run summary."""

    file: str
    rows: int = 0
    counts: dict[str, int] = field(default_factory=dict)

    def add(self, kind: str, n: int = 1) -> None:
        if n:
            self.counts[kind] = self.counts.get(kind, 0) + n


def read_table(path: Path, required: tuple[str, ...]) -> tuple[list[str], np.ndarray]:
    """Header and float data (rows, cols) of a CSV; empty cells become NaN."""
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ValueError(f"{path}: empty file (no header)") from None
        missing = [c for c in required if c not in header]
        if missing:
            raise ValueError(f"{path}: missing column {missing[0]!r} (header: {','.join(header)})")
        rows = []
        width = len(header)
        for line_no, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != width:
                raise ValueError(f"{path}, line {line_no}: {len(row)} cells, header has {width}")
            vals = []
            for col, cell in zip(header, row, strict=True):
                cell = cell.strip()
                if cell == "":
                    vals.append(np.nan)
                    continue
                try:
                    vals.append(float(cell))
                except ValueError:
                    raise ValueError(
                        f"{path}, line {line_no}, column {col!r}: not a number: {cell!r}"
                    ) from None
            rows.append(vals)
    data = np.array(rows, dtype=float).reshape(-1, width)
    return header, data


def _check_times(path: Path, t: np.ndarray) -> None:
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise ValueError(f"{path}, line {bad[0] + 2}, column 't_s': time is not a number")
    d = np.diff(t)
    back = np.flatnonzero(d <= 0)
    if back.size:
        i = back[0] + 1
        kind = "duplicate" if d[back[0]] == 0 else "unsorted"
        raise ValueError(
            f"{path}, line {i + 2}, column 't_s': {kind} time {float(t[i])!r} "
            f"after {float(t[i - 1])!r}"
        )


def fill_sample_gaps(
    t0: float, dt: float, k: np.ndarray, acc: np.ndarray
) -> tuple[np.ndarray, np.ndarray, int]:
    """Put samples on their uniform grid, missing grid points as held (NaN) rows.

    Parameters
    ----------
    t0, dt : float
        Time of grid point 0 and the grid step (same unit as the result).
    k : array (M,) of int
        Strictly increasing grid index of each sample.
    acc : array (M, N)
        The samples.

    Returns
    -------
    t : array (T,), full : array (T, N), filled : int
        Grid times, samples with NaN rows at the gaps, number of rows filled.
    """
    n_total = int(k[-1]) + 1
    full = np.full((n_total, acc.shape[1]), np.nan)
    full[k] = acc
    return t0 + np.arange(n_total) * dt, full, n_total - acc.shape[0]


def read_array_csv(path: str | Path, n_channels: int) -> tuple[ArraySamples, ReadReport]:
    """Read ``array.csv`` for a layout of ``n_channels`` channels (see module docstring)."""
    p = Path(path)
    cols = ("t_s", *(f"a{i + 1}_mps2" for i in range(n_channels)))
    header, data = read_table(p, cols)
    extra = [h for h in header if h.startswith("a") and h.endswith("_mps2") and h not in cols]
    if extra:
        raise ValueError(f"{p}: column {extra[0]!r} beyond the layout's {n_channels} channels")
    idx = [header.index(c) for c in cols]
    data = data[:, idx]
    report = ReadReport(str(p), rows=data.shape[0])
    if data.shape[0] < 2:
        raise ValueError(f"{p}: needs at least two samples, has {data.shape[0]}")
    t = data[:, 0]
    _check_times(p, t)
    d = np.diff(t)
    dt = float(np.median(d))
    ratio = d / dt
    steps = np.rint(ratio).astype(int)
    off = np.flatnonzero(np.abs(ratio - steps) > 0.05)
    if off.size:
        i = off[0] + 1
        raise ValueError(
            f"{p}, line {i + 2}, column 't_s': time {float(t[i])!r} is not on the "
            f"{dt:g} s sample grid (gap {d[off[0]]:g} s)"
        )
    acc = data[:, 1:]
    if np.any(steps > 1):
        t, acc, filled = fill_sample_gaps(t[0], dt, np.concatenate([[0], np.cumsum(steps)]), acc)
        report.add("missing samples filled", filled)
    report.add(
        "bad samples (non-finite cell)",
        int(np.count_nonzero(~np.all(np.isfinite(data[:, 1:]), axis=1))),
    )
    return ArraySamples(t, acc), report


def read_gps_csv(path: str | Path) -> tuple[GpsFixes, ReadReport]:
    """Read ``gps.csv`` (see module docstring); rows without a fix are skipped and counted."""
    p = Path(path)
    header, data = read_table(p, GPS_COLUMNS)
    report = ReadReport(str(p), rows=data.shape[0])
    col = {h: data[:, header.index(h)] for h in header}
    t = col["t_s"]
    _check_times(p, t)
    ok = np.ones(t.shape, dtype=bool)
    if "fix_type" in col:
        nofix = ~(col["fix_type"] >= 3)
        report.add("no fix (fix_type < 3)", int(np.count_nonzero(nofix)))
        ok &= ~nofix
    # an empty altitude or velocity (or its accuracy) is a field the receiver did not
    # give: the fix is used for the rest; latitude, longitude and h_acc_m it must have
    fin = {c: np.isfinite(col[c]) for c in GPS_COLUMNS[1:]}
    nan_rows = ok & ~(fin["lat_deg"] & fin["lon_deg"] & fin["h_acc_m"])
    report.add("no fix (empty or nan cell)", int(np.count_nonzero(nan_rows)))
    ok &= ~nan_rows
    given = {
        "altitude": fin["alt_m"] & fin["v_acc_m"],
        "horizontal velocity": fin["vn_mps"] & fin["ve_mps"] & fin["vel_acc_mps"],
        "vertical velocity": fin["vd_mps"] & fin["vel_acc_mps"],
    }
    for what, has in given.items():
        report.add(f"fixes without {what} (the rest used)", int(np.count_nonzero(ok & ~has)))
    col["alt_m"] = np.where(given["altitude"], col["alt_m"], np.nan)
    col["v_acc_m"] = np.where(given["altitude"], col["v_acc_m"], 1.0)
    for c in ("vn_mps", "ve_mps"):
        col[c] = np.where(given["horizontal velocity"], col[c], np.nan)
    col["vd_mps"] = np.where(given["vertical velocity"], col["vd_mps"], np.nan)
    has_vel = given["horizontal velocity"] | given["vertical velocity"]
    col["vel_acc_mps"] = np.where(has_vel, col["vel_acc_mps"], 1.0)
    acc = np.column_stack([col["h_acc_m"], col["v_acc_m"], col["vel_acc_mps"]])
    bad_acc = ok & np.any(acc <= 0, axis=1)
    report.add("no fix (accuracy not positive)", int(np.count_nonzero(bad_acc)))
    ok &= ~bad_acc
    vel = np.column_stack([col["vn_mps"], col["ve_mps"], col["vd_mps"]])
    problem = np.full(t.shape, -1)
    problem[ok] = fix_range_problems(
        col["lat_deg"][ok], col["lon_deg"][ok], col["alt_m"][ok], vel[ok]
    )
    for k, kind in enumerate(FIX_RANGE_KINDS):
        report.add(f"no fix ({kind})", int(np.count_nonzero(problem == k)))
    ok &= problem < 0
    latency = col.get("latency_s", np.zeros_like(t))
    fixes = GpsFixes(
        t_s=t[ok],
        lat_deg=col["lat_deg"][ok],
        lon_deg=col["lon_deg"][ok],
        alt_m=col["alt_m"][ok],
        vel_ned_mps=np.column_stack([col["vn_mps"], col["ve_mps"], col["vd_mps"]])[ok],
        h_acc_m=col["h_acc_m"][ok],
        v_acc_m=col["v_acc_m"][ok],
        vel_acc_mps=col["vel_acc_mps"][ok],
        latency_s=np.nan_to_num(latency[ok]),
    )
    return fixes, report


def _write(path: Path, header: list[str], data: np.ndarray, fmt: str) -> None:
    np.savetxt(path, data, delimiter=",", header=",".join(header), comments="", fmt=fmt)


def write_array_csv(path: str | Path, samples: ArraySamples) -> None:
    """Write ``array.csv``."""
    n = samples.n_channels
    header = ["t_s"] + [f"a{i + 1}_mps2" for i in range(n)]
    _write(Path(path), header, np.column_stack([samples.t_s, samples.accel_mps2]), "%.10g")


def write_gps_csv(path: str | Path, fixes: GpsFixes) -> None:
    """Write ``gps.csv`` with ``fix_type`` (3) and ``latency_s``."""
    data = np.column_stack(
        [
            fixes.t_s,
            fixes.lat_deg,
            fixes.lon_deg,
            fixes.alt_m,
            fixes.vel_ned_mps,
            fixes.h_acc_m,
            fixes.v_acc_m,
            fixes.vel_acc_mps,
            np.full(len(fixes), 3.0),
            fixes.latency_s,
        ]
    )
    header = [*GPS_COLUMNS, "fix_type", "latency_s"]
    np.savetxt(
        Path(path),
        data,
        delimiter=",",
        header=",".join(header),
        comments="",
        fmt=["%.6f", "%.10f", "%.10f", "%.4f"] + ["%.5f"] * 3 + ["%.4f"] * 3 + ["%d", "%.4f"],
    )


def write_truth_csv(path: str | Path, truth: FlightTruth) -> None:
    """Write ``truth.csv``."""
    data = np.column_stack(
        [
            truth.t_s,
            truth.pos_ned_m,
            truth.vel_ned_mps,
            truth.q_nb,
            truth.omega_b_rps,
            truth.omega_dot_b_rps2,
            truth.f_b_mps2,
        ]
    )
    _write(Path(path), list(TRUTH_COLUMNS), data, "%.12g")


def read_truth_csv(path: str | Path) -> FlightTruth:
    """Read ``truth.csv``."""
    p = Path(path)
    header, data = read_table(p, TRUTH_COLUMNS)
    c = [header.index(h) for h in TRUTH_COLUMNS]
    d = data[:, c]
    _check_times(p, d[:, 0])
    return FlightTruth(
        d[:, 0], d[:, 1:4], d[:, 4:7], d[:, 7:11], d[:, 11:14], d[:, 14:17], d[:, 17:20]
    )
