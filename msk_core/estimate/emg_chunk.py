"""One chunk of raw EMG as a device sent it: what the live EMG envelope (:mod:`msk_core.estimate.live_emg`), the
electrode quality monitor (:mod:`msk_core.estimate.live_quality`) and the fatigue tracker
(:mod:`msk_core.estimate.live_fatigue`) each take, chunk by chunk."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class RawEmgChunk:
    """``samples`` (n, channels) of EMG source ``source`` in ``units`` ("V", "mV", "uV"; "normalised" is not raw),
    one column per channel label; its first row is the source's sample ``first_sample_index``, measured at
    ``device_time_ns`` on the device's clock, and rows are ``1 / rate_hz`` apart. Built from any sequence of labels
    and any array of n * channels values (kept as a tuple and a float (n, channels) array)."""

    source: str
    labels: tuple[str, ...]
    rate_hz: float
    first_sample_index: int
    device_time_ns: int
    samples: np.ndarray
    units: str = "V"

    def __init__(
        self,
        source: str,
        labels: Iterable[str],
        rate_hz: float,
        first_sample_index: int,
        device_time_ns: int,
        samples: np.ndarray,
        units: str = "V",
    ) -> None:
        labels = tuple(labels)
        object.__setattr__(self, "source", source)
        object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "rate_hz", float(rate_hz))
        object.__setattr__(self, "first_sample_index", int(first_sample_index))
        object.__setattr__(self, "device_time_ns", int(device_time_ns))
        object.__setattr__(self, "samples", np.asarray(samples, dtype=float).reshape(-1, len(labels)))
        object.__setattr__(self, "units", units)

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])

    @property
    def stream(self) -> tuple[tuple[str, ...], float, str]:
        """What a consumer's state of the source rests on (labels, rate, units): a chunk with others starts it again."""
        return self.labels, self.rate_hz, self.units

    def rows_from(self, index: int) -> RawEmgChunk:
        """This chunk without its rows before the source's sample ``index`` (rows sent again, already taken), its
        first index and device time moved on with them; itself when it starts at ``index`` or later."""
        skip = min(self.n_samples, index - self.first_sample_index)
        if skip <= 0:
            return self
        return replace(
            self,
            first_sample_index=self.first_sample_index + skip,
            device_time_ns=int(self.device_time_ns + skip * 1e9 / self.rate_hz),
            samples=self.samples[skip:],
        )
