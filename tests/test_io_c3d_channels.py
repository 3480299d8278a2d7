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
    assert (
        "left out 12 channels that are not EMG: Fx1, Fy1, Fz1, Mx1, My1, Mz1 (force plate 1 (FORCE_PLATFORM:CHANNEL)); "
        "Fx2, Fy2, Fz2, Mx2, My2, Mz2 (force plate 2 (FORCE_PLATFORM:CHANNEL))"
    ) in printed
    env = read_sto(out)
    assert env.columns == EMG
    # asked for by name, a force-plate channel is still enveloped (the user's explicit choice)
    assert msk(["emg", "envelope", str(path), "--channels", "Fz1,TA", "-o", str(tmp_path / "two.sto")]) == 0
    assert read_sto(tmp_path / "two.sto").columns == ["Fz1", "TA"]


def _write_emg_c3d(path: Path, unit: str, scale: float, gap: bool = False) -> tuple[Path, np.ndarray]:
    """Three Trigno-style EMG channels (<name>.EMG<slot>) at 2 kHz, 3 s, stored in ``unit`` (values x ``scale``);
    returns the path and the volts."""
    volts = np.random.default_rng(4).normal(0.0, 2e-4, (3, 6000))
    stored = volts * scale
    if gap:
        stored[0, 3000:3100] = np.nan  # 1.5 s: the electrode lost contact
    c3d = ezc3d.c3d()
    c3d["parameters"]["POINT"]["RATE"]["value"] = np.array([100.0])
    c3d["data"]["points"] = np.zeros((4, 0, 300))
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = np.array([2000.0])
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = ("Biceps.EMG1", "Triceps.EMG2", "Delt.EMG3")
    c3d.add_parameter("ANALOG", "UNITS", [unit] * 3)
    c3d["data"]["analogs"] = stored[None]
    c3d.write(str(path))
    return path, volts


@pytest.mark.parametrize(("unit", "scale"), [("V", 1.0), ("mV", 1e3), ("uV", 1e6), ("µV", 1e6)])
def test_the_trigno_simulator_streams_volts_whatever_unit_the_c3d_stores(tmp_path, unit, scale):
    """µV used to stream as volts: every sample at the ±11 mV rail."""
    from drivers.trigno.source import load_source

    path, volts = _write_emg_c3d(tmp_path / "emg.c3d", unit, scale)
    source = load_source(path)
    assert np.allclose(source.samples[:, :3].T, volts, rtol=1e-5, atol=1e-9)


def test_c3d_emg_in_newtons_or_with_a_gap_is_refused_naming_the_channel(tmp_path, capsys):
    from drivers.trigno.source import load_source

    newtons, _ = _write_emg_c3d(tmp_path / "n.c3d", "N", 1.0)
    with pytest.raises(FileFormatError) as error:
        load_source(newtons)
    assert "not a voltage" in str(error.value) and "Biceps.EMG1" in str(error.value)
    gap, _ = _write_emg_c3d(tmp_path / "gap.c3d", "V", 1.0, gap=True)
    with pytest.raises(FileFormatError) as error:
        load_source(gap)
    assert "NaN or infinite samples, from t = 1.5 s" in str(error.value) and "Biceps.EMG1" in str(error.value)
    assert msk(["emg", "envelope", str(gap), "-o", str(tmp_path / "env.sto")]) == 2
    said = capsys.readouterr().err
    assert "field 'Biceps.EMG1': EMG channel has NaN or infinite samples from t = 1.5 s" in said, said
    assert not (tmp_path / "env.sto").exists()


def test_a_rate_given_for_a_source_that_has_its_own_is_refused(tmp_path):
    from drivers.trigno.source import load_source
    from msk_core.errors import ConfigError

    path, _ = _write_emg_c3d(tmp_path / "emg.c3d", "V", 1.0)
    with pytest.raises(ConfigError) as error:
        load_source(path, rate_hz=3000.0)
    assert error.value.field == "--rate" and "raw .bin stream only" in str(error.value)
    npz = tmp_path / "two_rates.npz"
    np.savez(npz, emg=np.zeros((100, 2)), rate_hz=np.array([2000.0, 1000.0]))
    with pytest.raises(FileFormatError, match="rate_hz must be one number"):
        load_source(npz)


def test_msk_emg_envelope_gives_volts_whatever_unit_the_c3d_stores(tmp_path):
    """The same EMG stored in mV and in µV used to give envelopes 1000x apart (each in its file's unit)."""
    envelopes = []
    for unit, scale in (("mV", 1e3), ("uV", 1e6)):
        path, _ = _write_emg_c3d(tmp_path / f"emg_{unit}.c3d", unit, scale)
        out = tmp_path / f"env_{unit}.sto"
        assert msk(["emg", "envelope", str(path), "-o", str(out)]) == 0
        env = read_sto(out)
        assert env.name == "EMG envelopes (V), causal"
        envelopes.append(env.data)
    np.testing.assert_allclose(envelopes[0], envelopes[1], rtol=1e-5, atol=0)  # C3D stores float32
    assert 1e-5 < envelopes[0].max() < 1e-3  # volts: the 0.2 mV noise's envelope


def test_channels_named_twice_are_refused_naming_them_and_one_named_once_can_be_chosen(tmp_path, capsys):
    # a lab's export that cut the labels to the sensor's name: "TA" from "Sensor 1.EMG1" and "Sensor 1.IM EMG1"
    labels = ["TA", "SOL", "TA", "VL"]
    path = _gait_c3d(tmp_path / "twice.c3d", labels=labels, units=["V"] * 4, plates_used=0, channel_numbers=None)
    out = tmp_path / "env.sto"
    assert msk(["emg", "envelope", str(path), "-o", str(out)]) == 2
    said = capsys.readouterr().err
    assert "names 1 channel(s) more than once: TA" in said and "twice.c3d" in said and not out.exists(), said
    assert msk(["emg", "envelope", str(path), "--channels", "TA", "-o", str(out)]) == 2
    assert "2 channels are named 'TA' (analog columns 1, 3)" in capsys.readouterr().err
    assert msk(["emg", "envelope", str(path), "--channels", "SOL,VL", "-o", str(out)]) == 0
    assert read_sto(out).columns == ["SOL", "VL"]
