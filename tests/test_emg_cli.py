"""``msk emg envelope`` and ``msk emg reps`` on real files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.io import read_anc, read_sto
from msk_core.signal.emg import EmgFilterConfig, envelope_causal, envelope_zero_phase_noncausal
from services.cli import main


def test_envelope_command_matches_library(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(anc), "--channels", "SOL,TA", "-o", str(out)]) == 0
    s = read_sto(out)
    raw, own_unit = read_anc(anc).select(["SOL", "TA"]).in_volts()
    assert not own_unit and raw.units == ["V", "V"]
    assert s.columns == ["SOL", "TA"] and s.name == "EMG envelopes (V), causal"
    np.testing.assert_allclose(s.data, envelope_causal(raw.data, EmgFilterConfig(rate_hz=2000.0)), rtol=1e-12, atol=0)
    # offline zero-phase, normalised by an "MVC" trial (here the same file): by its highest 0.5 s mean
    out2 = tmp_path / "env_norm.sto"
    assert (
        main(["emg", "envelope", str(anc), "--channels", "SOL,TA", "--zero-phase", "--mvc", str(anc), "-o", str(out2)])
        == 0
    )
    s2 = read_sto(out2)
    zp = envelope_zero_phase_noncausal(raw.data, EmgFilterConfig(rate_hz=2000.0))
    window = np.stack([np.convolve(zp[:, j], np.ones(1000) / 1000, mode="valid") for j in range(2)], axis=1)
    np.testing.assert_allclose(s2.data, zp / window.max(axis=0), rtol=1e-9)
    assert np.all(s2.data.max(axis=0) > 1.2)  # the walk's bursts are shorter than 0.5 s: their peaks exceed it
    assert "normalised peak per channel" in capsys.readouterr().out


def test_reps_command(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ik = shared_dir / "data/backmodel-lift/stoop5kg/ik.sto"
    phase_file = tmp_path / "phase.sto"
    assert (
        main(
            [
                "emg",
                "reps",
                str(ik),
                "--coordinate",
                "pelvis_ty",
                "--excursion",
                "decrease",
                "--phase-out",
                str(phase_file),
            ]
        )
        == 0
    )
    assert "4 repetitions" in capsys.readouterr().out
    ph = read_sto(phase_file)
    assert ph.columns == ["phase", "rep"] and set(np.unique(ph.column("rep"))) == {-1.0, 0.0, 1.0, 2.0, 3.0}


def test_errors_exit_2(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"
    assert main(["emg", "envelope", str(anc), "--channels", "SOL,NOPE", "-o", str(tmp_path / "x.sto")]) == 2
    assert "no channel 'NOPE'" in capsys.readouterr().err
    assert main(["emg", "envelope", str(tmp_path / "x.txt"), "-o", str(tmp_path / "x.sto")]) == 2
    assert "unknown EMG file type" in capsys.readouterr().err
    assert main(["emg", "envelope", str(anc), "--lowpass-hz", "5000", "-o", str(tmp_path / "x.sto")]) == 2
    assert "lowpass_hz" in capsys.readouterr().err


def _write_anc(
    path: Path, names: list[str], ranges: list[int], counts: np.ndarray, rate: float = 1000.0, polarity: str = "Bipolar"
) -> Path:
    """A Motion Analysis .anc as Cortex writes it: header pairs, Name / Rate / Range rows, time and ADC counts."""
    lines = [
        "File_Type:\tAnalog R/C ASCII\tGeneration#:\t2",
        f"Trial_Name:\tsmall\tTrial#:\t1\tDuration(Sec.):\t{len(counts) / rate:f}\t#Channels:\t{len(names)}",
        f"Board_Type:\tNI USB-6225\tPolarity:\t{polarity}",
        "BitDepth:\t16\tPreciseRate:\t1000.000000",
        "",
        "Name\t" + "\t".join(names) + "\t",
        "Rate\t" + "\t".join(f"{rate:g}" for _ in names) + "\t",
        "Range\t" + "\t".join(str(r) for r in ranges) + "\t",
    ]
    lines += [f"{k / rate:f}\t" + "\t".join(str(int(v)) for v in row) + "\t" for k, row in enumerate(counts)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_anc_counts_become_volts_and_its_force_plates_are_left_out(tmp_path: Path, capsys) -> None:
    """One EMG signal recorded on a +-1000 mV and on a +-2500 mV channel: in counts 2.5x apart, in volts the same; the
    force-plate channels (F1X ... M1Z, the .anc naming) are left out unless asked for by name."""
    volts = 0.2 * np.sin(np.linspace(0, 40, 2000)) * np.random.default_rng(2).normal(1.0, 0.3, 2000)
    plates = ["F1X", "F1Y", "F1Z", "M1X", "M1Y", "M1Z"]
    counts = np.column_stack([np.full((2000, 6), 100.0), np.round(volts / 1.0 * 32768), np.round(volts / 2.5 * 32768)])
    anc = _write_anc(tmp_path / "trial.anc", [*plates, "SOL", "SOL_wide"], [5000] * 6 + [1000, 2500], counts)
    rec, own = read_anc(anc).in_volts()
    assert not own and rec.units == ["V"] * 8
    np.testing.assert_allclose(rec.channel("SOL"), volts, atol=1.0 / 32768)
    np.testing.assert_allclose(rec.channel("SOL_wide"), volts, atol=2.5 / 32768)
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(anc), "-o", str(out)]) == 0
    assert (
        "left out 6 channels that are not EMG: F1X, F1Y, F1Z, M1X, M1Y, M1Z (force-plate channel"
        in capsys.readouterr().out
    )
    env = read_sto(out)
    assert env.columns == ["SOL", "SOL_wide"] and env.name == "EMG envelopes (V), causal"
    np.testing.assert_allclose(env.column("SOL_wide"), env.column("SOL"), atol=3e-4 * env.column("SOL").max())
    assert main(["emg", "envelope", str(anc), "--channels", "F1Z,SOL", "-o", str(tmp_path / "two.sto")]) == 0
    assert read_sto(tmp_path / "two.sto").columns == ["F1Z", "SOL"]


def test_channels_without_a_voltage_unit_stay_in_their_own_and_are_named(tmp_path: Path, capsys) -> None:
    """A .sto gives no unit: its values are enveloped as they are, and the command says so."""
    from msk_core.io import write_sto

    t = np.arange(2000) / 1000.0
    sto = write_sto(tmp_path / "raw.sto", t, ["TA", "SOL"], np.random.default_rng(1).normal(size=(2000, 2)))
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(sto), "-o", str(out)]) == 0
    assert "2 channel(s) left in the file's own unit (it gives none that is a voltage): TA, SOL" in (
        capsys.readouterr().out
    )
    assert read_sto(out).name == "EMG envelopes (file units), causal"


def test_a_unipolar_anc_spans_its_range_with_all_its_counts(tmp_path: Path) -> None:
    """Unipolar: 0 .. 2^16 counts span 0 .. Range (bipolar: +-2^15 counts span +-Range)."""
    counts = np.column_stack([np.arange(0, 65536, 64.0)])
    rec, own = read_anc(_write_anc(tmp_path / "u.anc", ["EMG1"], [2000], counts, polarity="Unipolar")).in_volts()
    assert not own
    np.testing.assert_allclose(rec.channel("EMG1"), counts[:, 0] * 2.0 / 65536)
    bipolar, _ = read_anc(_write_anc(tmp_path / "b.anc", ["EMG1"], [2000], counts - 32768)).in_volts()
    np.testing.assert_allclose(bipolar.channel("EMG1"), (counts[:, 0] - 32768) * 2.0 / 32768)


def test_envelope_refuses_what_it_would_get_wrong_and_makes_its_output_folder(tmp_path: Path, capsys) -> None:
    from msk_core.io import write_sto

    t = np.cumsum(np.r_[0.0, np.full(999, 1e-3), np.full(1000, 2e-3)])  # 1 kHz, then 500 Hz: one rate cannot hold
    uneven = write_sto(tmp_path / "uneven.sto", t, ["TA"], np.random.default_rng(1).normal(size=(2000, 1)))
    assert main(["emg", "envelope", str(uneven), "-o", str(tmp_path / "x.sto")]) == 2
    error = capsys.readouterr().err
    assert "uneven.sto" in error and "field 'time'" in error and "needs a uniform sample rate" in error, error
    assert "resample it evenly first" in error, error
    even = write_sto(tmp_path / "even.sto", t[:1000], ["TA"], np.random.default_rng(1).normal(size=(1000, 1)))
    assert main(["emg", "envelope", str(even), "--normalise", "max_all_trials", "-o", str(tmp_path / "x.sto")]) == 2
    assert "field '--normalise': normalising needs the MVC trial(s): add --mvc FILE" in capsys.readouterr().err
    nested = tmp_path / "not" / "yet" / "env.sto"
    assert main(["emg", "envelope", str(even), "-o", str(nested)]) == 0 and read_sto(nested).columns == ["TA"]
    (tmp_path / "a-file").write_text("")
    assert main(["emg", "envelope", str(even), "-o", str(tmp_path / "a-file" / "env.sto")]) == 2
    assert "field '--output'" in capsys.readouterr().err


def test_envelope_says_which_channels_are_zero_throughout(tmp_path: Path, capsys) -> None:
    from msk_core.io import write_sto

    data = np.column_stack([np.random.default_rng(1).normal(size=1000), np.zeros(1000)])
    sto = write_sto(tmp_path / "two.sto", np.arange(1000) / 1000.0, ["TA", "slot16"], data)
    assert main(["emg", "envelope", str(sto), "-o", str(tmp_path / "env.sto")]) == 0
    assert "two.sto: 1 channel(s) are zero throughout (no sensor?): slot16" in capsys.readouterr().out


def test_an_mvc_trial_sampled_at_another_rate_is_filtered_at_its_own(shared_dir: Path, tmp_path: Path) -> None:
    """The MVC trial kept at 1000 Hz, the task at 2000 Hz: each envelope with its own rate's filters (and its own
    rate's 0.5 s window), so the same EMG normalises as by itself at 2000 Hz (filtered at the task's rate, the MVC's
    6 Hz low-pass was a 12 Hz one: peaks 3-65 % off)."""
    from msk_core.io import write_sto

    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"
    raw, _ = read_anc(anc).select(["SOL", "GAS", "TA"]).in_volts()
    mvc = tmp_path / "mvc_1000hz.sto"
    write_sto(mvc, raw.time[::2], ["SOL", "GAS", "TA"], raw.data[::2], name="the same EMG at 1000 Hz")
    peaks = []
    for reference in (mvc, anc):
        out = tmp_path / "normalised.sto"
        argv = ["emg", "envelope", str(anc), "--channels", "SOL,GAS,TA", "--zero-phase", "--mvc", str(reference)]
        assert main([*argv, "-o", str(out)]) == 0
        peaks.append(read_sto(out).data.max(axis=0))
    np.testing.assert_allclose(peaks[0], peaks[1], rtol=0.05)


def test_a_steady_maximal_contraction_normalised_by_itself_reads_one(tmp_path: Path) -> None:
    """Found with held-out data: `--mvc` divided by the envelope's plain peak, which sits on its ripple, so a steady
    contraction normalised by itself read 0.79, and every normalised envelope that much low. The MVC amplitude is the
    highest 0.5 s mean (docs/signal.md, the convention)."""
    from msk_core.io import write_sto

    rng = np.random.default_rng(7)
    time = np.arange(10_000) / 2000.0  # 5 s of a steady contraction: raw EMG as band-limited noise, 1 mV RMS
    raw = tmp_path / "mvc_raw.sto"
    write_sto(raw, time, ["TA"], 1e-3 * rng.standard_normal((time.size, 1)), name="raw EMG (V)")
    out = tmp_path / "mvc_norm.sto"
    assert main(["emg", "envelope", str(raw), "--zero-phase", "--mvc", str(raw), "-o", str(out)]) == 0
    steady = read_sto(out).data[2000:8000, 0]  # away from the filters' edges
    assert 0.9 < np.median(steady) <= 1.0, np.median(steady)  # the plain peak: 0.81


def test_an_envelope_file_given_as_raw_emg_is_named_with_what_to_do(tmp_path: Path, capsys) -> None:
    """Found by a new user's walk: a 100 Hz envelope file gave "field 'bandpass_hz': band-pass edges must satisfy
    ... < 50.0 Hz (Nyquist)", naming neither the file nor a way out. It now names the file and --no-bandpass."""
    from msk_core.io import write_sto

    t = np.arange(500) / 100.0
    sto = write_sto(tmp_path / "env.sto", t, ["TA"], np.abs(np.random.default_rng(2).normal(size=(500, 1))))
    assert main(["emg", "envelope", str(sto), "-o", str(tmp_path / "out.sto")]) == 2
    error = capsys.readouterr().err
    assert f"{sto}, field '--bandpass-hz': sampled at 100 Hz, too slowly for raw EMG's 20-450 Hz band-pass" in error
    assert "--no-bandpass" in error
    assert main(["emg", "envelope", str(sto), "-o", str(tmp_path / "out.sto"), "--no-bandpass"]) == 0


def test_a_channel_asked_for_in_another_case_is_suggested(tmp_path: Path, capsys) -> None:
    """Found by a new user's walk: `--channels sol` listed every channel, force plates among them, without a hint."""
    from msk_core.io import write_sto

    t = np.arange(2000) / 1000.0
    sto = write_sto(tmp_path / "raw.sto", t, ["TA", "SOL"], np.random.default_rng(1).normal(size=(2000, 2)))
    assert main(["emg", "envelope", str(sto), "-o", str(tmp_path / "e.sto"), "--channels", "sol"]) == 2
    assert "no channel 'sol'; did you mean SOL?; EMG channels: TA, SOL" in capsys.readouterr().err


def test_a_ground_reaction_force_file_is_not_enveloped_as_emg(tmp_path: Path, capsys) -> None:
    """Found by a new user's walk: OpenSim's external-load .mot (forces, points, torques) was enveloped as if its
    columns were muscles, with only a units warning. They are named as not EMG; a file of nothing else is refused."""
    from msk_core.io import write_sto

    t = np.arange(2000) / 1000.0
    data = np.random.default_rng(3).normal(size=(2000, 4))
    loads = write_sto(tmp_path / "grf.mot", t, ["ground_force_vy", "l_ground_force_px", "ground_torque_z", "TA"], data)
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(loads), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "left out 3 channels that are not EMG: ground_force_vy, l_ground_force_px, ground_torque_z" in printed
    assert read_sto(out).columns == ["TA"]
    only = write_sto(tmp_path / "only.mot", t, ["ground_force_vy", "ground_force_px"], data[:, :2])
    assert main(["emg", "envelope", str(only), "-o", str(out)]) == 2
    assert "no EMG channel: all 2 analog channels are not EMG (an external load's force" in capsys.readouterr().err


def test_slow_channels_not_labelled_emg_are_left_out_by_their_spectrum(tmp_path: Path, capsys) -> None:
    """Found with held-out data: a C3D's Voltage.1-6 (a load cell's forces, in volts like the EMG) were enveloped as
    six muscles. Surface EMG's power lies at 20-450 Hz; a channel with 90 % of its power below 20 Hz whose label does
    not say EMG is left out, said with its share; one labelled EMG is kept and said; --channels takes any."""
    from msk_core.io import write_sto
    from msk_core.signal.quality import below_band_share

    rng = np.random.default_rng(5)
    t = np.arange(8000) / 2000.0
    emg = 1e-4 * rng.standard_normal(t.size) * (1 + np.sin(2 * np.pi * 0.5 * t))  # noise modulated by a slow burst
    load = 0.05 * np.sin(2 * np.pi * 0.7 * t) + 1e-4 * rng.standard_normal(t.size)  # a load cell: slow, small noise
    drift = 2e-3 * t + emg  # an EMG electrode on a DC-coupled amplifier: its offset drifting
    data = np.column_stack([emg, load, drift])
    clean = data.copy()
    data[1000:1100, 1] = np.nan  # a gap in the load cell: judged on its finite samples, and left out all the same
    shares = below_band_share(data, 2000.0)
    assert shares[0] < 0.05 and shares[1] > 0.95 and shares[2] > 0.9, shares
    sto = write_sto(tmp_path / "lab.sto", t, ["TA", "Voltage.1", "Delt.EMG2"], data)
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(sto), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "left out 1 channel(s) whose power lies below 20 Hz, not EMG" in printed and "Voltage.1 (1" in printed
    assert "1 EMG channel(s) with most of their power below 20 Hz, enveloped as EMG: Delt.EMG2" in printed
    assert read_sto(out).columns == ["TA", "Delt.EMG2"]
    sto = write_sto(tmp_path / "lab_clean.sto", t, ["TA", "Voltage.1", "Delt.EMG2"], clean)
    assert main(["emg", "envelope", str(sto), "--channels", "Voltage.1", "-o", str(out)]) == 0  # asked for: taken
    assert read_sto(out).columns == ["Voltage.1"]
    only = write_sto(tmp_path / "load.sto", t, ["Voltage.1"], clean[:, 1:2])
    assert main(["emg", "envelope", str(only), "-o", str(out)]) == 2
    assert "no EMG channel: all 1 channels have their power below 20 Hz" in capsys.readouterr().err


def test_the_real_c3d_load_channels_are_left_out(shared_dir: Path, tmp_path: Path, capsys) -> None:
    c3d = shared_dir / "data/pyomeca-upper/markers_analogs.c3d"
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(c3d), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "left out 6 channel(s) whose power lies below 20 Hz" in printed, printed
    columns = read_sto(out).columns
    assert not [c for c in columns if c.startswith("Voltage")] and "Delt_ant.EMG1" in columns and len(columns) == 32
    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"  # every EMG channel of the real walk stays
    assert main(["emg", "envelope", str(anc), "-o", str(out)]) == 0
    assert "power lies below 20 Hz" not in capsys.readouterr().out and len(read_sto(out).columns) == 10
