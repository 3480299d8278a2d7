"""A gait C3D keeps force plates and EMG in one analog block: the file's FORCE_PLATFORM:CHANNEL and ANALOG:UNITS say
which channels are not EMG, and `msk emg envelope` leaves those out (and says which). Small C3D files are written here
with ezc3d."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import FileFormatError, InputError
from msk_core.io import read_c3d_analogs, read_sto
from services.cli import main as msk

ezc3d = pytest.importorskip("ezc3d")

PLATES = [f"{k}{plate}" for plate in (1, 2) for k in ("Fx", "Fy", "Fz", "Mx", "My", "Mz")]
EMG = ["TA", "SOL", "GAS", "VL"]
RATE = 1000.0


def _write_gait_c3d(
    path: Path,
    *,
    labels: list[str],
    units: list[str] | None,
    plates_used: int,
    channel_numbers: list[list[int]] | None,
    seconds: float = 2.0,
) -> Path:
    """Markers at 100 Hz, the analog block at 1 kHz: force-plate channels ~ hundreds of N, EMG ~ mV bursts."""
    c3d = ezc3d.c3d()
    n_frames = int(seconds * 100)
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c3d["parameters"]["POINT"]["LABELS"]["value"] = ("heel_r",)
    c3d["data"]["points"] = np.zeros((4, 1, n_frames))
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = np.array([RATE])
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = tuple(labels)
    if units is not None:
        c3d["parameters"]["ANALOG"]["UNITS"]["value"] = tuple(units)
    rng = np.random.default_rng(3)
    n = n_frames * 10
    t = np.arange(n) / RATE
    data = np.empty((len(labels), n))
    for j, label in enumerate(labels):
        if label in EMG:  # bursts of noise, 1 Hz
            data[j] = 1e-3 * rng.normal(size=n) * (0.1 + (np.sin(2 * np.pi * t + j) > 0))
        else:
            data[j] = 300.0 + 200.0 * np.sin(2 * np.pi * t) + rng.normal(size=n)
    c3d["data"]["analogs"] = data[None]
    c3d.add_parameter("FORCE_PLATFORM", "USED", plates_used)
    if channel_numbers is not None:
        c3d.add_parameter("FORCE_PLATFORM", "CHANNEL", channel_numbers)
        c3d.add_parameter("FORCE_PLATFORM", "TYPE", [2] * len(channel_numbers[0]))
    c3d.write(str(path))
    return path


def _gait_c3d(path: Path, **options) -> Path:
    """:func:`_write_gait_c3d` in a fresh interpreter: ezc3d's SWIG parameter setter refused a list of ints
    (``Parameter_set``: wrong number or type of arguments) in a test process that had run other tests first, and
    passed alone; the file written is the same."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_write_gait_c3d, path, **options).result(timeout=60)


def _plate_channels(first: int, plates: int) -> list[list[int]]:
    """FORCE_PLATFORM:CHANNEL: 6 rows (Fx..Mz), one column per plate, 1-based analog channel numbers."""
    return [[first + 6 * p + row for p in range(plates)] for row in range(6)]


def test_force_plate_channels_and_non_voltage_units_are_not_emg(tmp_path):
    labels = PLATES + EMG + ["Acc_x"]
    units = ["N", "N", "N", "Nmm", "Nmm", "Nmm"] * 2 + ["V"] * len(EMG) + ["g"]
    path = _gait_c3d(
        tmp_path / "walk.c3d", labels=labels, units=units, plates_used=2, channel_numbers=_plate_channels(1, 2)
    )
    rec = read_c3d_analogs(path)
    assert rec.labels == labels and rec.rate_hz == RATE
    assert set(rec.not_emg) == set(PLATES) | {"Acc_x"}
    assert rec.not_emg["Mz2"] == "force plate 2 (FORCE_PLATFORM:CHANNEL)"
    assert "'g'" in rec.not_emg["Acc_x"]
    emg = rec.emg_only()
    assert emg.labels == EMG and emg.not_emg == {}
    np.testing.assert_array_equal(emg.channel("SOL"), rec.channel("SOL"))


def test_plates_in_volts_are_found_by_their_channel_numbers(tmp_path):
    """Uncalibrated amplifier outputs in V: only FORCE_PLATFORM:CHANNEL tells them from EMG (here after the EMG)."""
    labels = EMG + PLATES[:6]
    path = _gait_c3d(
        tmp_path / "volts.c3d",
        labels=labels,
        units=["V"] * len(labels),
        plates_used=1,
        channel_numbers=_plate_channels(len(EMG) + 1, 1),
    )
    rec = read_c3d_analogs(path)
    assert list(rec.not_emg) == PLATES[:6]
    assert rec.emg_only().labels == EMG


def test_unused_plates_and_missing_units_leave_every_channel(tmp_path):
    labels = PLATES[:6] + EMG
    path = _gait_c3d(tmp_path / "unused.c3d", labels=labels, units=None, plates_used=0, channel_numbers=None)
    rec = read_c3d_analogs(path)
    assert rec.not_emg == {} and rec.emg_only().labels == labels


def test_inconsistent_plate_channels_are_refused(tmp_path):
    labels = PLATES[:6] + EMG
    path = _gait_c3d(
        tmp_path / "bad.c3d",
        labels=labels,
        units=["V"] * len(labels),
        plates_used=2,
        channel_numbers=_plate_channels(1, 2),
    )  # plate 2 names channels 7..12; there are 10
    with pytest.raises(FileFormatError, match="force plate 2 names analog channel 11, but there are 10") as err:
        read_c3d_analogs(path)
    assert err.value.field == "FORCE_PLATFORM:CHANNEL" and "bad.c3d" in str(err.value)
    only_plates = _gait_c3d(
        tmp_path / "plates.c3d", labels=PLATES, units=["N"] * 12, plates_used=2, channel_numbers=_plate_channels(1, 2)
    )
    with pytest.raises(InputError, match="no EMG channel: all 12 analog channels are not EMG"):
        read_c3d_analogs(only_plates).emg_only()


def test_msk_emg_envelope_leaves_the_force_plates_out_and_says_so(tmp_path, capsys):
    labels = PLATES + EMG
    units = ["N", "N", "N", "Nmm", "Nmm", "Nmm"] * 2 + ["V"] * len(EMG)
    path = _gait_c3d(
        tmp_path / "gait.c3d", labels=labels, units=units, plates_used=2, channel_numbers=_plate_channels(1, 2)
    )
    out = tmp_path / "env.sto"
    assert msk(["emg", "envelope", str(path), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "left out 12 channels that are not EMG: Fx1 (force plate 1 (FORCE_PLATFORM:CHANNEL))" in printed
    env = read_sto(out)
    assert env.columns == EMG
    # asked for by name, a force-plate channel is still enveloped (the user's explicit choice)
    assert msk(["emg", "envelope", str(path), "--channels", "Fz1,TA", "-o", str(tmp_path / "two.sto")]) == 0
    assert read_sto(tmp_path / "two.sto").columns == ["Fz1", "TA"]
