"""EMG envelope chain: 16 channels at 2000 Hz streamed in 27-sample chunks (one Trigno frame)."""

from __future__ import annotations

import time

import numpy as np
from scipy import signal

from msk_core.errors import ConfigError
from msk_core.signal.emg import EmgEnvelopeFilter, EmgFilterConfig, envelope_causal
from services.bench import BenchResult

NAME = "emg"
DESCRIPTION = "streaming EMG envelope, 16 ch x 2000 Hz in 27-sample chunks, vs scipy batch sosfilt"

RATE_HZ = 2000.0
N_CHANNELS = 16
CHUNK = 27


def _best(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(quick: bool) -> list[BenchResult]:
    seconds = 10.0 if quick else 60.0
    repeats = 2 if quick else 3
    rng = np.random.default_rng(0)
    emg = rng.standard_normal((int(seconds * RATE_HZ), N_CHANNELS)) * 1e-4  # volts, like Trigno
    cfg = EmgFilterConfig(rate_hz=RATE_HZ)
    starts = range(0, emg.shape[0], CHUNK)

    f = EmgEnvelopeFilter(cfg, N_CHANNELS)
    out: list[np.ndarray] = []

    def streaming() -> None:
        f.reset()
        out.clear()
        for i in starts:
            out.append(f.process(emg[i : i + CHUNK]))

    bp, lp = cfg.bandpass_sos(), cfg.lowpass_sos()
    if bp is None:
        raise ConfigError(
            "the EMG filter benchmark times the band-pass too: the default filter must have one",
            field="bandpass_hz",
            value=cfg.bandpass_hz,
        )

    def batch() -> None:
        signal.sosfilt(lp, np.abs(signal.sosfilt(bp, emg, axis=0)), axis=0)

    def naive_streaming() -> None:
        zb = np.zeros((bp.shape[0], 2, N_CHANNELS))
        zl = np.zeros((lp.shape[0], 2, N_CHANNELS))
        for i in starts:
            y, zb = signal.sosfilt(bp, emg[i : i + CHUNK], axis=0, zi=zb)
            _, zl = signal.sosfilt(lp, np.abs(y), axis=0, zi=zl)

    f.process(emg[:CHUNK])  # build the block matrices for this chunk size once, outside the timing
    t_stream = _best(streaming, repeats)
    t_batch = _best(batch, repeats)
    t_naive = _best(naive_streaming, 1)
    ref = envelope_causal(emg, cfg)
    max_rel = float(np.max(np.abs(np.vstack(out) - ref)) / np.max(np.abs(ref)))
    rtf = seconds / t_stream
    n_chunks = len(starts)
    return [
        BenchResult(
            name=f"streaming chain ({seconds:.0f} s of data)",
            value=t_stream,
            unit="s",
            baseline_name="scipy batch sosfilt, same chain and data",
            baseline_value=t_batch,
            target=">= 1000x real time",
            passed=rtf >= 1000.0,
            details={
                "real_time_factor": rtf,
                "per_chunk_us": 1e6 * t_stream / n_chunks,
                "batch_real_time_factor": seconds / t_batch,
                "max_rel_diff_vs_batch": max_rel,
            },
        ),
        BenchResult(
            name="streaming real-time factor", value=rtf, unit="x real time", target=">= 1000", passed=rtf >= 1000.0
        ),
        BenchResult(
            name="naive streaming (scipy sosfilt per chunk, zi carried)",
            value=t_naive,
            unit="s",
            baseline_name="scipy batch sosfilt",
            baseline_value=t_batch,
            details={"real_time_factor": seconds / t_naive},
        ),
    ]
