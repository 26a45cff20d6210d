"""A run's inputs as files: a CSV run directory or a tlog, read and written alike.

``read_run`` and ``write_run`` pick the format from the path: a name ending in
``.tlog`` is a MAVLink telemetry log (see :mod:`telemetry.inputs`), anything
else a run directory (``config.toml``, ``array.csv``, ``gps.csv``). A
simulated run's truth goes beside a tlog as ``NAME.truth.csv``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ngnav.records import ArraySamples, GpsFixes
from ngnav.runconfig import RunConfig, read_run_config, write_run_config
from ngnav.runio import read_array_csv, read_gps_csv, write_array_csv, write_gps_csv


@dataclass(frozen=True)
class RunInputs:
    """What a filter run needs, with what reading it skipped (counts by kind per source)."""

    samples: ArraySamples
    fixes: GpsFixes
    config: RunConfig
    reports: dict[str, dict[str, int]]


def is_tlog(path: str | Path) -> bool:
    """True for a path named ``*.tlog``."""
    return Path(path).suffix.lower() == ".tlog"


def truth_path(path: str | Path) -> Path:
    """Where the truth of a run at ``path`` lives (``truth.csv`` or ``NAME.truth.csv``)."""
    p = Path(path)
    return p.with_suffix(".truth.csv") if is_tlog(p) else p / "truth.csv"


def read_run(path: str | Path) -> RunInputs:
    """Read a run directory or a tlog (ValueError naming the file on bad input)."""
    p = Path(path)
    if is_tlog(p):
        from telemetry.frames import FrameDecoder
        from telemetry.inputs import InputAssembler
        from telemetry.tlog import read_tlog

        dec = FrameDecoder()
        asm = InputAssembler(counts=dec.counts)
        for _, msg in read_tlog(p, dec):
            asm.add(msg)
        asm.finish()
        cfg = asm.config(str(p))
        if asm.n_channels is not None and asm.n_channels != cfg.layout.n_sensors:
            raise ValueError(
                f"{p}: array messages have {asm.n_channels} channels, the configuration "
                f"{cfg.layout.n_sensors}"
            )
        samples, fixes = asm.samples(), asm.fixes()
        return RunInputs(samples, fixes, cfg, {str(p): dec.counts.as_dict()})
    cfg = read_run_config(p / "config.toml")
    samples, arep = read_array_csv(p / "array.csv", cfg.layout.n_sensors)
    fixes, grep_ = read_gps_csv(p / "gps.csv")
    return RunInputs(samples, fixes, cfg, {arep.file: arep.counts, grep_.file: grep_.counts})


def write_run(path: str | Path, samples: ArraySamples, fixes: GpsFixes, cfg: RunConfig) -> Path:
    """Write a run's inputs as a tlog (``*.tlog``) or a run directory; returns the path."""
    p = Path(path)
    if is_tlog(p):
        from telemetry.inputs import input_frames
        from telemetry.tlog import write_tlog

        p.parent.mkdir(parents=True, exist_ok=True)
        write_tlog(p, input_frames(samples, fixes, cfg))
        return p
    p.mkdir(parents=True, exist_ok=True)
    write_array_csv(p / "array.csv", samples)
    write_gps_csv(p / "gps.csv", fixes)
    write_run_config(cfg, p / "config.toml")
    return p
