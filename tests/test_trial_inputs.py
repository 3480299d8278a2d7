"""Real trial files go wrong in ordinary ways: a channel with a gap, a misspelt divisor, angles in degrees under an
``inDegrees=no`` header, a file with a header only, raw EMG with a gap, a repeated time stamp, a torque file that
ends early. Each is either used with what it lacks said out loud, or refused naming the file, the field and the value.
(Found by using the offline commands on the demo trial as a new user would.)"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError, InputError
from msk_core.estimate.emd import estimate_emd
from msk_core.estimate.trial import load_trial, trial_notes
from msk_core.io import read_sto, write_sto
from msk_core.io.files import json_text
from msk_core.model import load_pack
from services import cli

DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo" / "bench_press" / "bench_press_40kg"


@pytest.fixture(scope="module")
def pack():
    return load_pack("bench_press")


def _trial(tmp_path: Path, swap: tuple[tuple[str, str], ...] = (), **files: Path) -> Path:
    """The demo's bench press trial with absolute paths: its files, or those of ``files`` (kinematics=..., emg=...),
    and the text pairs of ``swap`` replaced."""
    text = (DEMO / "trial.toml").read_text()
    for key, default in (("kinematics", "ik.sto"), ("torques", "id.sto"), ("emg", "emg.sto")):
        text = text.replace(f'{key} = "{default}"', f'{key} = "{files.get(key, DEMO / default)}"')
    for old, new in swap:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / "trial.toml"
    path.write_text(text)
    return path


def _training_copy(tmp_path: Path) -> Path:
    """The demo trial as another file and name, for --train beside it held out (one file as both is refused)."""
    path = tmp_path / "train" / "trial.toml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(_trial(tmp_path).read_text().replace('name = "bench_press_40kg"', 'name = "training"'))
    return path


def _write_like(source: Path, out: Path, time: np.ndarray, data: np.ndarray, in_degrees: bool = False) -> Path:
    storage = read_sto(source)
    write_sto(out, time, list(storage.columns), data, name="edited", in_degrees=in_degrees)
    return out


def test_a_gap_in_one_emg_channel_is_said_and_does_not_stop_the_delay_estimate(tmp_path, pack):
    emg = read_sto(DEMO / "emg.sto")
    data = emg.data.copy()
    data[(emg.time >= 5.0) & (emg.time < 6.0), emg.columns.index("PMCla")] = np.nan  # the electrode came off
    gap = _write_like(DEMO / "emg.sto", tmp_path / "emg_gap.sto", emg.time, data)
    trial = load_trial(_trial(tmp_path, emg=gap), pack)
    assert trial_notes(trial) == [
        "EMG of PMCla: 100 of 1361 frames not measured (NaN, or outside the EMG file's time span); those frames carry "
        "no EMG term for it"
    ]
    delay = estimate_emd(pack, [trial]).delay_s  # was: LinAlgError "SVD did not converge"
    assert 0.0 <= delay <= 0.15


def test_a_misspelt_emg_max_channel_is_refused_not_left_unnormalised(tmp_path, pack):
    path = _trial(tmp_path, swap=(("PMCla = 0.000364", "PMCLa = 0.000364"),))
    with pytest.raises(ConfigError) as error:
        load_trial(path, pack)
    assert error.value.field == "emg_max.PMCLa" and "did you mean PMCla?" in str(error.value), error.value


def test_angles_in_degrees_under_an_in_degrees_no_header_are_refused_naming_the_cause(tmp_path, pack):
    ik = read_sto(DEMO / "ik.sto")
    degrees = _write_like(DEMO / "ik.sto", tmp_path / "ik_deg.sto", ik.time, np.degrees(ik.data))
    with pytest.raises(InputError) as error:
        load_trial(_trial(tmp_path, kinematics=degrees), pack)
    said = str(error.value)
    assert "1361 of 1361 frames lie outside the fitted ranges of pack 'bench_press'" in said, said
    assert "look like degrees in a file whose header says inDegrees=no" in said and "ik_deg.sto" in said, said


def test_files_with_a_header_only_or_time_that_does_not_increase_are_refused_naming_the_row(tmp_path, pack):
    emg = read_sto(DEMO / "emg.sto")
    empty = _write_like(DEMO / "emg.sto", tmp_path / "empty.sto", emg.time[:0], emg.data[:0])
    with pytest.raises(InputError, match="EMG file has a header but no data rows"):
        load_trial(_trial(tmp_path, emg=empty), pack)
    ik = read_sto(DEMO / "ik.sto")
    time = ik.time.copy()
    time[500] = time[499]
    repeated = _write_like(DEMO / "ik.sto", tmp_path / "ik_dup.sto", time, ik.data)
    with pytest.raises(InputError) as error:
        load_trial(_trial(tmp_path, kinematics=repeated), pack)
    assert "kinematics time must increase: data row 501 has t = 4.99 s after 4.99 s" in str(error.value)
    assert "ik_dup.sto" in str(error.value) and error.value.field == "time"


def test_raw_emg_with_a_gap_is_refused_naming_where(tmp_path, pack):
    rate = 1000.0
    time = np.arange(0.0, 13.6, 1.0 / rate)
    time = np.r_[time[time < 5.0], time[time >= 7.0]]  # 2 s missing
    raw = np.random.default_rng(1).normal(0.0, 1e-4, (time.size, 10))
    path = _write_like(DEMO / "emg.sto", tmp_path / "raw_gap.sto", time, raw)
    trial = _trial(tmp_path, swap=(("emg_is_envelope = true", "emg_is_envelope = false"),), emg=path)
    with pytest.raises(InputError) as error:
        load_trial(trial, pack)
    said = str(error.value)
    assert "raw EMG (emg_is_envelope = false) needs a uniform sample rate" in said, said
    assert "2.001 s from t = 4.999 s" in said and "raw_gap.sto" in said, said


def test_frames_beyond_a_short_torque_file_are_said_by_the_commands(tmp_path, pack, capsys):
    torques = read_sto(DEMO / "id.sto")
    keep = torques.time <= 6.0
    short = _write_like(DEMO / "id.sto", tmp_path / "id_short.sto", torques.time[keep], torques.data[keep])
    path = _trial(tmp_path, torques=short)
    from services.commands.estimate import load_trials

    (trial,) = load_trials([path], pack)
    assert trial.n_frames == 601 and trial.dropped_frames == 760
    said = capsys.readouterr().err
    assert (
        f"trial bench_press_40kg ({path}): 760 kinematics frames outside the torque file's time span left out" in said
    )


def test_a_report_folder_that_is_a_file_is_refused_before_the_work(tmp_path, capsys):
    taken = tmp_path / "report"
    taken.write_text("not a folder")
    argv = [
        "evaluate",
        "--pack",
        "bench_press",
        "--train",
        str(_training_copy(tmp_path)),
        "--trial",
        str(_trial(tmp_path)),
    ]
    assert cli.main([*argv, "--leave-out", "all", "--report", str(taken)]) == 2
    assert "field '--report': is a file, not a folder" in capsys.readouterr().err


def test_json_outputs_write_null_where_a_number_is_undefined():
    text = json_text({"r": math.nan, "lag": np.float64(np.inf), "per_rep": np.array([0.5, np.nan]), "n": np.int64(3)})
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"r": None, "lag": None, "per_rep": [0.5, None], "n": 3}


def test_a_window_outside_the_file_or_backwards_says_so(tmp_path, pack):
    backwards = _trial(tmp_path, swap=(("load_kg = 40.0", "load_kg = 40.0\nstart = 9.0\nend = 2.0"),))
    with pytest.raises(ConfigError) as error:
        load_trial(backwards, pack)
    assert error.value.field == "start" and "start must come before end (end = 2)" in str(error.value)
    beyond = _trial(tmp_path, swap=(("load_kg = 40.0", "load_kg = 40.0\nstart = 100.0\nend = 200.0"),))
    with pytest.raises(ConfigError) as error:
        load_trial(beyond, pack)
    assert "fewer than 3 kinematics frames between start and end (0); the kinematics span 0 .. 13.6 s" in str(
        error.value
    ), error.value


@pytest.mark.parametrize(
    ("name", "said"),
    [("5", "must be a non-empty string"), ('"bench/40kg"', "must not contain /")],  # reports are files named by it
)
def test_a_trial_name_must_be_text_that_can_name_a_file(tmp_path, pack, name, said):
    with pytest.raises(ConfigError) as error:
        load_trial(_trial(tmp_path, swap=(('name = "bench_press_40kg"', f"name = {name}"),)), pack)
    assert error.value.field == "name" and said in str(error.value)


def test_a_trial_without_a_complete_rep_is_said(tmp_path, pack):
    ik = read_sto(DEMO / "ik.sto")
    still = _write_like(DEMO / "ik.sto", tmp_path / "ik_still.sto", ik.time, np.repeat(ik.data[:1], ik.n_rows, axis=0))
    trial = load_trial(_trial(tmp_path, kinematics=still), pack)
    assert any("every frame counts as rest, and per-cycle plots stay empty" in note for note in trial_notes(trial))


def test_raw_emg_whose_time_column_is_rounded_is_read_at_its_mean_rate(tmp_path, pack):
    """The Trigno's 1925.926 Hz printed to 5 decimals: intervals of 0.00051 and 0.00052 s are rounding, not gaps."""
    rate = 1925.926
    time = np.round(np.arange(0.0, 13.6, 1.0 / rate), 5)
    raw = np.random.default_rng(2).normal(0.0, 1e-4, (time.size, 10))
    path = _write_like(DEMO / "emg.sto", tmp_path / "raw_rounded.sto", time, raw)
    trial = load_trial(_trial(tmp_path, swap=(("emg_is_envelope = true", "emg_is_envelope = false"),), emg=path), pack)
    assert set(trial.emg) == {
        "PMCla",
        "PMSte",
        "DelAnt",
        "DelMed",
        "DelPos",
        "BicLong",
        "TriLong",
        "TriLat",
        "BRD",
        "LD",
    }
    assert all(np.all(np.isfinite(e[trial.time < 13.5])) for e in trial.emg.values())


def test_several_channels_of_one_group_weigh_the_same(tmp_path, pack):
    """Three electrodes on one group: their plain mean (a running mean of pairs gave a/4 + b/4 + c/2)."""
    emg = read_sto(DEMO / "emg.sto")
    path = _trial(tmp_path, swap=(('PMSte = "PMSte"', 'PMSte = "PMCla"'), ('DelAnt = "DelAnt"', 'DelAnt = "PMCla"')))
    trial = load_trial(path, pack)
    assert "PMSte" not in trial.emg and "DelAnt" not in trial.emg
    maxima = {"PMCla": 0.0003645911353159428, "PMSte": 0.0003662885272659023, "DelAnt": 0.00024246465794182726}
    columns = [np.interp(trial.time, emg.time, emg.column(ch) / m) for ch, m in maxima.items()]
    np.testing.assert_allclose(trial.emg["PMCla"], np.mean(columns, axis=0), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    ("factor", "with_max", "said"),
    [
        (100.0, True, "its 99th percentile is"),  # % of MVC under divisors for volts
        (1.0, False, "its largest value is"),  # the raw envelope in volts, no divisor
    ],
)
def test_emg_that_is_not_a_normalised_envelope_is_refused(tmp_path, pack, factor, with_max, said):
    emg = read_sto(DEMO / "emg.sto")
    scaled = _write_like(DEMO / "emg.sto", tmp_path / "emg_units.sto", emg.time, emg.data * factor)
    path = _trial(tmp_path, emg=scaled)
    if not with_max:
        text = path.read_text()
        path.write_text(text[: text.index("[emg_max]")])
    with pytest.raises(ConfigError) as error:
        load_trial(path, pack)
    message = str(error.value)
    assert "EMG column 'PMCla' is not a normalised envelope" in message and said in message, message
    assert error.value.field == ("emg_max.PMCla" if with_max else "emg_map.PMCla"), error.value.field
    assert (
        error.value.line
        == path.read_text()
        .splitlines()
        .index(f"PMCla = {'0.0003645911353159428' if with_max else chr(34) + 'PMCla' + chr(34)}")
        + 1
    )


def test_emg_that_misses_the_trial_or_is_all_nan_there_is_refused_with_both_spans(tmp_path, pack):
    emg = read_sto(DEMO / "emg.sto")
    later = _write_like(DEMO / "emg.sto", tmp_path / "emg_later.sto", emg.time + 100.0, emg.data)
    with pytest.raises(ConfigError) as error:
        load_trial(_trial(tmp_path, emg=later), pack)
    assert (
        "EMG column 'PMCla' has no sample within the trial's frames (0 .. 13.6 s): the EMG file spans 100 .. "
        in str(error.value)
    ), error.value
    data = emg.data.copy()
    data[:, emg.columns.index("LD")] = np.nan
    dead = _write_like(DEMO / "emg.sto", tmp_path / "emg_dead.sto", emg.time, data)
    with pytest.raises(ConfigError, match=r"EMG column 'LD' has no sample .*: its values there are all NaN"):
        load_trial(_trial(tmp_path, emg=dead), pack)


def test_torques_that_are_not_finite_are_said_apart_from_a_short_file(tmp_path, pack):
    torques = read_sto(DEMO / "id.sto")
    data = torques.data.copy()
    data[(torques.time >= 5.0) & (torques.time < 5.5), 0] = np.nan
    holed = _write_like(DEMO / "id.sto", tmp_path / "id_nan.sto", torques.time, data)
    trial = load_trial(_trial(tmp_path, torques=holed), pack)
    notes = trial_notes(trial)
    assert not any("outside the torque file's time span" in note for note in notes), notes
    assert "50 kinematics frames left out where the torque file is not finite (NaN), the first at t = 5 s" in notes[0]


def test_times_of_epoch_stamped_files_are_said_to_the_microsecond(tmp_path, pack):
    ik = read_sto(DEMO / "ik.sto")
    time = ik.time + 1667315600.0
    time[500] = time[499]
    stamped = _write_like(DEMO / "ik.sto", tmp_path / "ik_epoch.sto", time, ik.data)
    with pytest.raises(InputError, match=r"data row 501 has t = 1667315604\.99 s after 1667315604\.99 s"):
        load_trial(_trial(tmp_path, kinematics=stamped), pack)


def test_two_trials_of_one_name_are_refused_before_their_reports_overwrite_each_other(tmp_path, pack, capsys):
    first = _trial(tmp_path)
    second = tmp_path / "again" / "trial.toml"
    second.parent.mkdir()
    second.write_text(first.read_text())
    argv = ["evaluate", "--pack", "bench_press", "--train", str(_training_copy(tmp_path)), "--trial", str(first)]
    argv += ["--trial", str(second)]
    assert cli.main([*argv, "--leave-out", "all", "--report", str(tmp_path / "report")]) == 2
    said = capsys.readouterr().err
    assert f"two trials are named 'bench_press_40kg' ({first} and {second})" in said, said
    assert not (tmp_path / "report").exists()


def test_a_folder_of_unnamed_trial_files_names_each_after_its_folder(tmp_path, pack):
    """--trial FOLDER takes every trial.toml under it; without a `name` each was 'trial', and two were refused as
    one name twice."""
    from services.commands.estimate import load_trials

    text = _trial(tmp_path).read_text().replace('name = "bench_press_40kg"\n', "")
    for folder in ("monday", "tuesday"):
        (tmp_path / "trials" / folder).mkdir(parents=True)
        (tmp_path / "trials" / folder / "trial.toml").write_text(text)
    assert sorted(t.name for t in load_trials([tmp_path / "trials"], pack)) == ["monday", "tuesday"]


@pytest.mark.parametrize(
    "column, values, refused",
    [("pelvis_tilt", (0.0, 1.13), "pelvis_tilt spans 64.7 deg"), ("pelvis_tx", (0.0, 0.05), None)],
)
def test_without_a_torques_file_a_moving_pelvis_is_refused_a_still_one_is_not(tmp_path, pack, column, values, refused):
    """Found by a new user's walk through the offline commands: a stoop without its `torques` line got L5/S1 torques
    of half the recorded ones, printed as "flagged: none": the pack's inverse dynamics holds the pelvis fixed and
    upright. A pelvis that turns (here 64.7 deg) or moves (> 0.1 m) within the trial is now refused naming the file,
    the column and its span; one that stays (5 cm) is used as before."""
    kin = read_sto(DEMO / "ik.sto")
    pelvis = np.linspace(*values, kin.n_rows)[:, None]
    moved = tmp_path / "ik_pelvis.sto"
    write_sto(moved, kin.time, [*kin.columns, column], np.hstack([kin.data, pelvis]), name="edited")
    without = _trial(tmp_path, (('torques = "' + str(DEMO / "id.sto") + '"\n', ""),), kinematics=moved)
    if refused is None:
        assert load_trial(without, pack).torque_source == "inverse_dynamics"
        return
    with pytest.raises(ConfigError) as error:
        load_trial(without, pack)
    assert error.value.field == "torques" and str(moved) in str(error.value) and refused in str(error.value)
    assert load_trial(_trial(tmp_path, kinematics=moved), pack) is not None  # with its torques file: as before


def test_more_phase_bins_than_a_rep_has_frames_are_refused(tmp_path, capsys):
    """Found by a new user's walk: `--bins 100000` on 405 frames wrote a 52 MB profile whose prior was its empty
    bins' fill (worse held out), without a word. More bins than the longest rep has frames is now refused before the
    calibration, naming how many the reps allow."""
    out = tmp_path / "s.json"
    argv = ["calibrate", "--pack", "bench_press", "--trial", str(_trial(tmp_path)), "--emd", "0"]
    assert cli.main([*argv, "--bins", "100000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "field 'bins': 100000 phase bins, but the longest of the" in err and "choose at most" in err, err
    assert not out.exists()


def test_plots_of_trials_on_epoch_seconds_count_from_the_trials_start():
    """Found by a new user's walk: the evaluation plots of the real lifts (files on Unix epoch seconds) read
    "+1.6673156e9" under their time axis. They now count seconds from the trial's first frame and say its UTC time;
    files on seconds from their start keep their own axis."""
    from services.surfaces.reports.evaluation import time_axis

    axis, label = time_axis(np.array([1_667_315_607.25, 1_667_315_608.5]))
    np.testing.assert_allclose(axis, [0.0, 1.25])
    assert label == "time (s) from 2022-11-01 15:13:27 UTC (the files' clock)"
    axis, label = time_axis(np.array([12.0, 13.0]))
    np.testing.assert_array_equal(axis, [12.0, 13.0])
    assert label == "time in the trial's files (s)"


def test_a_profile_of_another_pack_or_other_groups_is_named_in_a_short_message(tmp_path, pack):
    """Found by a new user's walk: a profile of another pack was refused with an 881-character list of both packs'
    57 groups that did not name the profile file. It now names the file, both packs and what to do; other groups of
    the same pack are named, a few at a time."""
    from msk_core.errors import EstimationError
    from msk_core.estimate.profile import SubjectProfile

    groups = list(pack.groups)
    path = tmp_path / "ana.json"
    SubjectProfile("deadlift", "1.0", groups, np.ones(len(groups)), np.ones(len(groups))).save(path)
    with pytest.raises(EstimationError) as error:
        SubjectProfile.load(path).check_pack(pack)
    said = str(error.value)
    assert said == (
        f"subject profile {path} was calibrated for pack 'deadlift' (13 groups), not for pack 'bench_press': give a "
        "profile calibrated on 'bench_press', or --pack deadlift"
    )
    renamed = [*groups[:-1], "TriMed"]
    SubjectProfile("bench_press", str(pack.version), renamed, np.ones(13), np.ones(13)).save(path)
    with pytest.raises(EstimationError) as error:
        SubjectProfile.load(path).check_pack(pack)
    assert f"the pack's {groups[-1]} are not in it; its TriMed are not in the pack; recalibrate" in str(error.value)


def test_a_data_file_given_as_the_trial_says_what_a_trial_is(pack):
    """Found by a new user's walk: `--trial ik.sto` said "invalid TOML: Expected '=' after a key"."""
    with pytest.raises(ConfigError) as error:
        load_trial(DEMO / "ik.sto", pack)
    assert "a trial is a description (TOML) of its data files, not a .sto data file" in str(error.value)
    assert 'kinematics = "ik.sto"' in str(error.value) and error.value.path == DEMO / "ik.sto"


def test_a_table_header_with_a_comment_keeps_the_line_of_its_keys(tmp_path, pack):
    """Found by a new user's walk: `[emg_map]  # ...` (the committed lift trials) gave its errors no line number."""
    trial = _trial(
        tmp_path, swap=(("[emg_map]", "[emg_map]  # the electrodes"), ('TriLat = "TriLat"', 'TriLat = "TriMed"'))
    )
    with pytest.raises(ConfigError) as error:
        load_trial(trial, pack)
    line = trial.read_text().splitlines().index('TriLat = "TriMed"') + 1
    assert error.value.line == line and error.value.field == "emg_map.TriLat", str(error.value)


def test_kinematics_given_as_the_torques_are_refused_and_moment_columns_beat_angle_columns(tmp_path, pack):
    # a kinematics file in the torques' place (in radians and in degrees) holds angles under the coordinates' names
    ik = read_sto(DEMO / "ik.sto")
    for name, data, degrees in (("rad", ik.data, False), ("deg", np.degrees(ik.data), True)):
        angles = _write_like(DEMO / "ik.sto", tmp_path / f"ik_{name}.sto", ik.time, data, in_degrees=degrees)
        with pytest.raises(InputError, match="hold the same values as the kinematics file .*: angles, not torques"):
            load_trial(_trial(tmp_path, torques=angles), pack)
    # OpenSim's inverse dynamics beside the bare angle columns: the <coordinate>_moment columns are the torques
    tq = read_sto(DEMO / "id.sto")
    coordinates = list(pack.coordinates)
    moments = tq.select([f"{c}_moment" for c in coordinates])
    angles_then = np.column_stack([np.interp(tq.time, ik.time, ik.column(c)) for c in coordinates])
    both = tmp_path / "id_and_angles.sto"
    columns = [f"{c}_moment" for c in coordinates] + coordinates
    write_sto(both, tq.time, columns, np.column_stack([moments, angles_then]), name="edited")
    assert np.array_equal(
        load_trial(_trial(tmp_path, torques=both), pack).torques, load_trial(_trial(tmp_path), pack).torques
    )


def test_times_in_milliseconds_are_refused_naming_the_file_and_the_rate(tmp_path, pack):
    ik = read_sto(DEMO / "ik.sto")
    slow = _write_like(DEMO / "ik.sto", tmp_path / "ik_ms.sto", ik.time * 1000.0, ik.data)
    with pytest.raises(InputError, match=r"sampled every 10 s \(0\.1 Hz\).*times in milliseconds") as error:
        load_trial(_trial(tmp_path, kinematics=slow), pack)
    assert "ik_ms.sto" in str(error.value) and "time" in str(error.value)


@pytest.mark.parametrize("factor, said", [(1 / 81.31, "N·m/kg"), (1000.0, "N·mm")])
def test_torques_in_other_units_than_newton_metres_are_refused(tmp_path, pack, factor, said):
    tq = read_sto(DEMO / "id.sto")
    scaled = _write_like(DEMO / "id.sto", tmp_path / "id_scaled.sto", tq.time, tq.data * factor)
    with pytest.raises(InputError, match=f"times the pack's inverse dynamics of the same motion .* in {said}"):
        load_trial(_trial(tmp_path, torques=scaled), pack)
    # physics, not units: heavier than declared with the load left out (about 11x the pack's), not refused
    heavier = _write_like(DEMO / "id.sto", tmp_path / "id_heavier.sto", tq.time, tq.data * 1.4)
    load_trial(_trial(tmp_path, (("load_kg = 40.0", "load_kg = 0.0"),), torques=heavier), pack)


def test_emg_labels_in_another_case_are_suggested_and_a_missing_in_degrees_line_is_named(tmp_path, pack):
    emg = read_sto(DEMO / "emg.sto")
    upper = tmp_path / "emg_upper.sto"
    write_sto(upper, emg.time, [c.upper() for c in emg.columns], emg.data, name="edited")
    with pytest.raises(ConfigError, match="EMG file has no column 'PMCla'; did you mean PMCLA"):
        load_trial(_trial(tmp_path, emg=upper), pack)
    ik = read_sto(DEMO / "ik.sto")
    degrees = _write_like(DEMO / "ik.sto", tmp_path / "ik_deg.sto", ik.time, np.degrees(ik.data))
    text = degrees.read_text().replace("inDegrees=no\n", "")
    degrees.write_text(text)
    with pytest.raises(InputError, match="header has no inDegrees line .*add inDegrees=yes"):
        load_trial(_trial(tmp_path, kinematics=degrees), pack)


def test_a_c3d_as_the_trials_emg_says_how_to_make_the_storage_it_needs(tmp_path, pack):
    recording = tmp_path / "session.c3d"
    recording.write_bytes(b"\x02\x50")  # never opened: the key's value says what it is
    with pytest.raises(
        ConfigError, match=r"msk emg envelope .*session\.c3d --zero-phase --mvc MVC_TRIAL -o emg\.sto"
    ) as error:
        load_trial(_trial(tmp_path, emg=recording), pack)
    assert "emg" in str(error.value)


def test_an_isometric_trials_held_pose_may_be_sampled_slowly(tmp_path, pack):
    # the 2 Hz floor on the kinematics' rate is for movements: a held pose written once a second is read
    mvc = DEMO.parent / "mvc" / "BRD"
    ik = read_sto(mvc / "ik.sto")
    every = np.searchsorted(ik.time, [0.0, 1.0, 2.0, 3.0])
    sparse = _write_like(mvc / "ik.sto", tmp_path / "ik_1hz.sto", ik.time[every], ik.data[every])
    text = (mvc / "trial.toml").read_text().replace('kinematics = "ik.sto"', f'kinematics = "{sparse}"')
    text = text.replace('torques = "id.sto"', f'torques = "{mvc / "id.sto"}"').replace(
        'emg = "emg.sto"', f'emg = "{mvc / "emg.sto"}"'
    )
    (tmp_path / "mvc.toml").write_text(text)
    assert load_trial(tmp_path / "mvc.toml", pack).n_frames == 4
    (tmp_path / "moving.toml").write_text(text.replace("isometric = true\n", ""))
    with pytest.raises(InputError, match="slower than 2 Hz"):
        load_trial(tmp_path / "moving.toml", pack)


@pytest.mark.parametrize(
    "swap, field, said",
    [
        (("load_kg = 40.0", "load_kg = 40000.0"), "load_kg", "is it in grams (40 kg)?"),
        (("body_mass_kg = 81.31", "body_mass_kg = 81310"), "body_mass_kg", "within 20-400 (grams?"),
    ],
)
def test_a_load_or_body_mass_in_grams_is_refused_naming_its_key(tmp_path, pack, swap, field, said):
    """Found by a new user: `load_kg = 50000` was refused as torques "0.00112 times" the model's ("are they in
    N·m/kg?"), blaming the torque file; `body_mass_kg = 81310` went through. Both are now refused where they are."""
    with pytest.raises(ConfigError) as error:
        load_trial(_trial(tmp_path, swap=(swap,)), pack)
    assert error.value.field == field and said in str(error.value), error.value


def test_envelopes_msk_emg_envelope_left_in_volts_are_refused_as_activation(tmp_path, pack):
    """Found with held-out data: the trial's own hint led to `msk emg envelope RAW -o emg.sto`, whose envelopes are in
    volts ("EMG envelopes (V), causal"); an amplifier's volts (peaks 0.007-0.12) passed the range checks and were
    fitted as activation: scores ~10x better than true, strengths at the wrong bound. Its first line says what it
    holds: refused unless each channel's MVC is given as [emg_max]."""
    import tomllib

    demo = read_sto(DEMO / "emg.sto")  # the demo's envelopes, in volts, with their MVCs in the trial's [emg_max]
    volts = tmp_path / "emg_v.sto"
    write_sto(volts, demo.time, list(demo.columns), demo.data, name="EMG envelopes (V), causal")
    with_max = _trial(tmp_path, emg=volts).read_text()
    without_max = with_max.split("[emg_max]")[0]
    (tmp_path / "no_max.toml").write_text(without_max)
    with pytest.raises(ConfigError) as error:
        load_trial(tmp_path / "no_max.toml", pack)
    assert "emg_v.sto holds EMG envelopes that are not normalised" in str(error.value), error.value
    assert error.value.field.startswith("emg_map.")
    assert len(tomllib.loads(with_max)["emg_max"]) == len(tomllib.loads(with_max)["emg_map"])
    (tmp_path / "with_max.toml").write_text(with_max)  # each channel's MVC in volts: the envelopes as the demo's
    loaded, reference = load_trial(tmp_path / "with_max.toml", pack).emg, load_trial(_trial(tmp_path), pack).emg
    assert loaded.keys() == reference.keys()
    for group in reference:
        np.testing.assert_allclose(loaded[group], reference[group], equal_nan=True)


def test_torques_of_the_opposite_sign_are_refused_or_said(tmp_path, pack):
    """Found with held-out data: a walk exported with the other model's knee convention (its knee moment left
    unflipped), or every moment negated (external moments), loaded and calibrated without a word. Every column against
    the pack's inverse dynamics of the same motion is refused; one column is said in the trial's notes."""
    tq = read_sto(DEMO / "id.sto")
    negated = _write_like(DEMO / "id.sto", tmp_path / "id_external.sto", tq.time, -tq.data)
    with pytest.raises(InputError, match="every torque column runs against the pack's inverse dynamics") as error:
        load_trial(_trial(tmp_path, torques=negated), pack)
    assert error.value.field == "torques" and "external moments" in str(error.value)
    elbow = list(tq.columns).index("elbow_flex_r_moment")
    one = tq.data.copy()
    one[:, elbow] *= -1
    flipped = _write_like(DEMO / "id.sto", tmp_path / "id_elbow.sto", tq.time, one)
    notes = trial_notes(load_trial(_trial(tmp_path, torques=flipped), pack))
    said = [n for n in notes if "runs against" in n]
    assert len(said) == 1 and said[0].startswith("the torque of elbow_flex_r runs against"), notes
    assert not [n for n in trial_notes(load_trial(_trial(tmp_path), pack)) if "runs against" in n]


def test_kinematics_of_another_model_say_what_each_side_has(tmp_path, pack):
    """Found with held-out data: another model's kinematics got "no column for pack coordinate 'elv_angle_r'" with
    neither a close name nor the file's columns."""
    ik = read_sto(DEMO / "ik.sto")
    other = tmp_path / "ik_other.sto"
    write_sto(other, ik.time, ["shoulder_ele", "elbow_flexion"], ik.data, name="another model", in_degrees=False)
    with pytest.raises(InputError) as error:
        load_trial(_trial(tmp_path, kinematics=other), pack)
    said = str(error.value)
    assert "its columns: shoulder_ele, elbow_flexion; pack 'bench_press' needs elv_angle_r, elbow_flex_r" in said, said


def test_a_reports_trials_notes_end_the_report(tmp_path, pack):
    """Found with held-out data: a trial without a complete repetition was scored as rest throughout, said only on
    stderr, and its report did not say so. The trials' notes now end report.md."""
    from services.commands.estimate import append_trial_notes

    tq = read_sto(DEMO / "id.sto")
    half = tq.time <= tq.time[len(tq.time) // 2]
    short = _write_like(DEMO / "id.sto", tmp_path / "id_short.sto", tq.time[half], tq.data[half])
    trial = load_trial(_trial(tmp_path, torques=short), pack)
    assert trial_notes(trial)
    report = tmp_path / "report.md"
    report.write_text("# scores\n")
    append_trial_notes(report, [trial])
    text = report.read_text()
    assert "## Notes on the trials" in text and "outside the torque file's time span left out" in text, text
    report.write_text("# scores\n")
    append_trial_notes(report, [load_trial(_trial(tmp_path), pack)])  # nothing left out: nothing added
    assert report.read_text() == "# scores\n"


def test_a_calibration_whose_every_emg_strength_ends_at_a_bound_is_warned():
    """Found with held-out data: EMG 0.5 s off its torques put 10 of 10 strengths at a bound, reported "converged"."""
    from services.commands.estimate import all_at_bound_warning

    said = all_at_bound_warning(["at_bound"] * 10 + ["not_calibrated"] * 3)
    assert said is not None and "all 10 muscles with EMG ended at a strength bound" in said
    assert all_at_bound_warning(["at_bound"] * 7 + ["unidentified"]) is None  # the real stoop: 7 of 8
    assert all_at_bound_warning(["at_bound", "not_calibrated"]) is None  # one measured muscle says little


def test_a_model_of_the_other_convention_is_read_through_the_coordinates_table(tmp_path, pack):
    """Left open by held-out data: a walk's knee in the other model's convention, or a coordinate named otherwise,
    had to be rewritten by hand, which is where sign errors start. The trial's [coordinates] table names each
    coordinate's column, "-" flipping its angle and moment together; the result is the pack's own trial."""
    ik, tq = read_sto(DEMO / "ik.sto"), read_sto(DEMO / "id.sto")
    theirs_ik, theirs_tq = ik.data.copy(), tq.data.copy()
    theirs_ik[:, list(ik.columns).index("elbow_flex_r")] *= -1
    theirs_tq[:, list(tq.columns).index("elbow_flex_r_moment")] *= -1
    ik_cols = ["elbow_extension" if c == "elbow_flex_r" else c for c in ik.columns]
    tq_cols = ["elbow_extension_moment" if c == "elbow_flex_r_moment" else c for c in tq.columns]
    kin = tmp_path / "ik_theirs.sto"
    write_sto(kin, ik.time, ik_cols, theirs_ik, name="their model", in_degrees=ik.in_degrees)
    torques = tmp_path / "id_theirs.sto"
    write_sto(torques, tq.time, tq_cols, theirs_tq, name="their model")
    plain = _trial(tmp_path, kinematics=kin, torques=torques)
    with pytest.raises(InputError) as error:  # without the table: refused, saying where the mapping goes
        load_trial(plain, pack)
    assert "or the trial's [coordinates] table naming each one's column" in str(error.value), error.value

    mapped = tmp_path / "mapped.toml"
    mapped.write_text(plain.read_text() + '\n[coordinates]\nelbow_flex_r = "-elbow_extension"\n')
    ours, reference = load_trial(mapped, pack), load_trial(_trial(tmp_path), pack)
    np.testing.assert_allclose(ours.q, reference.q, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours.torques, reference.torques, rtol=0, atol=1e-9)
    assert not [n for n in trial_notes(ours) if "runs against" in n]

    unflipped = tmp_path / "unflipped.toml"  # named but not flipped: out of the pack's ranges, said
    unflipped.write_text(plain.read_text() + '\n[coordinates]\nelbow_flex_r = "elbow_extension"\n')
    with pytest.raises(InputError, match="sign convention"):
        load_trial(unflipped, pack)
    for entry, said in (
        ('elbow_flex = "-elbow_extension"', "not a coordinate of pack 'bench_press'; did you mean elbow_flex_r?"),
        ('elbow_flex_r = "-"', 'with "-" before it to flip its sign'),
        ('elbow_flex_r = "-elbow_extensio"', "column 'elbow_extensio' (its [coordinates] entry)"),
    ):
        bad = tmp_path / "bad.toml"
        bad.write_text(plain.read_text() + f"\n[coordinates]\n{entry}\n")
        with pytest.raises((ConfigError, InputError)) as error:
            load_trial(bad, pack)
        assert said in str(error.value), (entry, str(error.value))


def test_the_sign_note_says_the_moment_alone_is_flipped(tmp_path, pack):
    tq = read_sto(DEMO / "id.sto")
    one = tq.data.copy()
    one[:, list(tq.columns).index("elbow_flex_r_moment")] *= -1
    flipped = _write_like(DEMO / "id.sto", tmp_path / "id_elbow.sto", tq.time, one)
    said = [n for n in trial_notes(load_trial(_trial(tmp_path, torques=flipped), pack)) if "runs against" in n]
    # the angles are in range: the moment alone is flipped, which [coordinates] (angle and moment together) is not for
    assert said and "the moment alone runs the other way" in said[0] and "negate that column" in said[0], said
