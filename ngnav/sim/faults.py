"""Channel faults injected into a simulated array: the ``[faults]`` section of a scenario.

Each fault names a channel (1-based, the paper's A1..A9), a kind, the time it starts
and a size. From the start on the channel's output (after noise, clipping and
quantisation) is replaced or altered:

- ``dead``: reads exactly 0 (a broken wire, a powered-down part); size unused;
- ``stuck``: holds the value it read at the start (a frozen converter); size unused;
- ``drift``: a bias ramp of ``size`` m/s^2 per second from the start;
- ``noisy``: its white noise multiplied by ``size`` (default 10: a loose mount, a failing
  reference);
- ``saturated``: reads its full-scale rail whatever the motion, the sign of ``size``
  (default +1) choosing the rail.

A section looks like::

    [faults]
    inject = [ { channel = 6, kind = "dead", start_s = 20.0 } ]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The kinds of channel fault the simulator injects (and the monitor names).
FAULT_KINDS = ("dead", "stuck", "drift", "noisy", "saturated")
#: The drift ``ngnav faults`` injects unless told, m/s^2 per s: 1 milli-g per second.
TRIAL_DRIFT_MPS2_PER_S = 0.00980665
#: The size a fault takes when its table leaves ``size`` out (NaN: the kind needs one).
_DEFAULT_SIZE = {"dead": 0.0, "stuck": 0.0, "drift": float("nan"), "noisy": 10.0, "saturated": 1.0}


@dataclass(frozen=True)
class ChannelFault:
    """One injected channel fault.

    Parameters
    ----------
    channel : int
        Channel number, 1-based (``A1`` is 1).
    kind : str
        One of :data:`FAULT_KINDS`.
    start_s : float
        Time the fault starts, s from the run's first sample.
    size : float
        ``drift``: m/s^2 per s; ``noisy``: the noise's multiple (> 1); ``saturated``:
        its sign picks the rail; unused otherwise.
    """

    channel: int
    kind: str
    start_s: float
    size: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {self.kind!r} is not one of {', '.join(FAULT_KINDS)}")
        if isinstance(self.channel, bool) or not isinstance(self.channel, int) or self.channel < 1:
            raise ValueError(f"fault channel must be a channel number from 1, got {self.channel!r}")
        if not (np.isfinite(self.start_s) and self.start_s >= 0.0):
            raise ValueError(f"fault start_s must be a time >= 0 s, got {self.start_s}")
        if not np.isfinite(self.size):
            raise ValueError(f"a {self.kind} fault needs a finite size, got {self.size}")
        if self.kind == "noisy" and not self.size > 1.0:
            raise ValueError(f"a noisy fault multiplies the noise by size > 1, got {self.size}")
        if self.kind == "saturated" and self.size == 0.0:
            raise ValueError("a saturated fault's size is +1 or -1 (the rail), got 0")

    def describe(self) -> str:
        """``channel 6 dead from 20.0 s``, ``channel 3 drift 0.01 m/s^2/s from 20.0 s``."""
        size = {
            "drift": f" {self.size:g} m/s^2/s",
            "noisy": f" x{self.size:g}",
            "saturated": " (+rail)" if self.size > 0 else " (-rail)",
        }.get(self.kind, "")
        return f"channel {self.channel} {self.kind}{size} from {self.start_s:g} s"


def parse_faults(table: object, source: str) -> tuple[ChannelFault, ...]:
    """The ``[faults]`` table of a scenario into faults (a one-line error naming the entry)."""
    if not isinstance(table, dict):
        raise ValueError(f"{source}: [faults] must be a table")
    unknown = sorted(set(table) - {"inject"})
    if unknown:
        raise ValueError(
            f"{source}: unknown key faults.{unknown[0]} (the section has inject, lose_track_at_s)"
        )
    items = table.get("inject", [])
    if not isinstance(items, list):
        raise ValueError(f"{source}: faults.inject must be a list of tables")
    out = []
    for i, item in enumerate(items):
        where = f"{source}: faults.inject[{i}]"
        if not isinstance(item, dict):
            raise ValueError(f"{where} must be a table (channel, kind, start_s, size)")
        extra = sorted(set(item) - {"channel", "kind", "start_s", "size"})
        if extra:
            raise ValueError(f"{where}: unknown key {extra[0]}")
        missing = [k for k in ("channel", "kind", "start_s") if k not in item]
        if missing:
            raise ValueError(f"{where}: missing key {missing[0]}")
        kind = item["kind"]
        size = item.get("size", _DEFAULT_SIZE.get(kind, 0.0) if isinstance(kind, str) else 0.0)
        for key, value in (("start_s", item["start_s"]), ("size", size)):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"{where}: {key} must be a number, got {value!r}")
        try:
            out.append(ChannelFault(item["channel"], kind, float(item["start_s"]), float(size)))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
    return tuple(out)


def inject_faults(
    t_s: np.ndarray,
    accel_mps2: np.ndarray,
    faults: tuple[ChannelFault, ...],
    noise_sigma_mps2: float,
    range_mps2: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Channel outputs (T, N) with ``faults`` applied (a new array).

    ``noise_sigma_mps2`` is a channel's white noise per sample (a noisy fault adds
    ``sqrt(size^2 - 1)`` of it), ``range_mps2`` its full scale (a saturated fault's
    rail). ``rng`` draws the extra noise only, so a run's other channels are the same
    as without the faults.
    """
    out = np.array(accel_mps2, dtype=float, copy=True)
    n = out.shape[1]
    for f in faults:
        if f.channel > n:
            raise ValueError(f"fault on channel {f.channel}: the array has {n} channels")
        on = t_s - t_s[0] >= f.start_s - 1e-12
        if not np.any(on):
            continue
        c = f.channel - 1
        first = int(np.argmax(on))
        if f.kind == "dead":
            out[on, c] = 0.0
        elif f.kind == "stuck":
            out[on, c] = out[first, c]
        elif f.kind == "drift":
            out[on, c] += f.size * (t_s[on] - t_s[first])
        elif f.kind == "noisy":
            extra = noise_sigma_mps2 * np.sqrt(f.size**2 - 1.0)
            out[on, c] += rng.normal(0.0, extra, int(np.count_nonzero(on)))
        else:  # saturated
            out[on, c] = np.copysign(range_mps2, f.size)
    return out
