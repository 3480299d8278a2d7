"""From OpenSim's StaticOptimization setup to `msk estimate`: the command line reproduces OpenSim's SO on OpenSim's own
arm26 tutorial files when asked to prepare the data as OpenSim does (docs/estimation.md, "From OpenSim's SO setup").

OpenSim runs in the test; `msk estimate` runs without it (the recipe needs no OpenSim at run time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.reference import opensim_filtered_kinematics, run_opensim_static_optimization
from msk_core.io import read_sto
from msk_core.signal.kinematics_filter import lowpass_coordinates
from services.cli import main as msk

pytest.importorskip("opensim")

COORDS = ["r_shoulder_elev", "r_elbow_flex"]


@pytest.fixture(scope="module")
def arm26(shared_dir, tmp_path_factory):
    data = shared_dir / "data" / "opensim-arm26"
    ref = run_opensim_static_optimization(
        data / "arm26_Setup_StaticOptimization.xml",
        shared_dir / "models" / "arm26.osim",
        data / "arm26_InverseKinematics.mot",
        tmp_path_factory.mktemp("opensim_so"),
        use_muscle_physiology=False,
    )
    return {"ref": ref, "data": data, "model": shared_dir / "models" / "arm26.osim"}


def _trial(tmp_path, data, lowpass: float | None) -> str:
    # the recipe: coordinates_file -> kinematics, the ID of the same motion -> torques,
    # lowpass_cutoff_frequency_for_coordinates -> lowpass_coordinates_hz
    lines = [
        f'kinematics = "{data / "arm26_InverseKinematics.mot"}"',
        f'torques = "{data / "arm26_InverseDynamics.sto"}"',
        'phase_signal = "r_elbow_flex"',
    ]
    if lowpass is not None:
        lines.append(f"lowpass_coordinates_hz = {lowpass}")
    path = tmp_path / ("trial_lowpass.toml" if lowpass else "trial.toml")
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _rms_against_opensim(arm26, out) -> float:
    ref = arm26["ref"].activations
    mine = read_sto(out)
    assert list(mine.columns) == list(ref.columns)
    at = np.array([np.argmin(np.abs(mine.time - t)) for t in ref.time])
    assert np.abs(mine.time[at] - ref.time).max() < 1e-6
    return float(np.sqrt(np.mean((mine.data[at] - ref.data) ** 2)))


def test_msk_estimate_with_the_recipe_matches_opensim_static_optimization(arm26, tmp_path, capsys):
    out = tmp_path / "so.sto"
    trial = _trial(tmp_path, arm26["data"], 6.0)
    code = msk(
        [
            "estimate",
            "--pack",
            "arm26",
            "--trial",
            trial,
            "--method",
            "so",
            "--activation-bounds",
            "model",
            "--out",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr().err
    recipe = _rms_against_opensim(arm26, out)
    plain_out = tmp_path / "so_plain.sto"
    assert (
        msk(
            [
                "estimate",
                "--pack",
                "arm26",
                "--trial",
                _trial(tmp_path, arm26["data"], None),
                "--method",
                "so",
                "--out",
                str(plain_out),
            ]
        )
        == 0
    )
    plain = _rms_against_opensim(arm26, plain_out)
    print(f"RMS activation against OpenSim SO: recipe {recipe:.4f}, without it {plain:.4f}")
    assert recipe <= 0.01
    assert recipe < plain  # the recipe is what closes the gap, not a coincidence of this motion


def test_coordinate_lowpass_equals_opensims_preparation(arm26):
    mot = read_sto(arm26["data"] / "arm26_InverseKinematics.mot")
    ref = opensim_filtered_kinematics(
        arm26["model"], arm26["data"] / "arm26_InverseKinematics.mot", COORDS, mot.time, 6.0
    )
    mine = lowpass_coordinates(mot.time, np.deg2rad(mot.select(COORDS)), 6.0)
    for derivative, (r, m) in enumerate(zip(ref, mine)):
        assert np.abs(m - r).max() <= 0.005 * np.abs(r).max(), derivative


def test_pack_activation_bounds_are_opensims_min_and_max_control(arm26):
    import opensim

    from msk_core.model import load_pack

    pack = load_pack("arm26")
    model = opensim.Model(str(arm26["model"]))
    muscles = model.getMuscles()
    for g, lo, hi in zip(pack.groups, pack.min_control, pack.max_control):
        members = [muscles.get(m) for m in pack.members[g]]
        assert lo == max(m.getMinControl() for m in members)
        assert hi == min(m.getMaxControl() for m in members)
    assert np.all(pack.min_control > 0)  # arm26's muscles are bounded at 0.01: a bound the unit box would miss


def test_lowpass_key_errors_name_the_field(tmp_path, shared_dir):
    from msk_core.errors import ConfigError
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    bad = tmp_path / "bad.toml"
    bad.write_text(
        f'kinematics = "{shared_dir / "data" / "opensim-arm26" / "arm26_InverseKinematics.mot"}"\n'
        "lowpass_coordinates_hz = -6\n"
    )
    with pytest.raises(ConfigError) as err:
        load_trial(bad, load_pack("arm26"))
    assert err.value.field == "lowpass_coordinates_hz" and "bad.toml" in str(err.value)


def test_lowpass_torques_filters_the_torque_file_and_names_its_errors(tmp_path, shared_dir):
    from msk_core.errors import ConfigError
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    data, pack = shared_dir / "data" / "opensim-arm26", load_pack("arm26")
    # the recorded ID with an impact-like spike added: 2 frames of +5 N·m on the elbow
    torques = read_sto(data / "arm26_InverseDynamics.sto")
    column = torques.columns.index("r_elbow_flex_moment")
    spiked = torques.data.copy()
    middle = torques.n_rows // 2
    spiked[middle : middle + 2, column] += 5.0
    header = torques.path.read_text().split("endheader")[0] + "endheader\n"
    rows = "\n".join("\t".join(f"{v:.9g}" for v in (t, *row)) for t, row in zip(torques.time, spiked))
    spiked_file = tmp_path / "id_spiked.sto"
    spiked_file.write_text(header + "\t".join(["time", *torques.columns]) + "\n" + rows + "\n")

    def trial(extra: str) -> Path:
        path = tmp_path / "t.toml"
        path.write_text(
            f'kinematics = "{data / "arm26_InverseKinematics.mot"}"\ntorques = "{spiked_file}"\n'
            f'phase_signal = "r_elbow_flex"\n{extra}'
        )
        return path

    raw, filtered = load_trial(trial(""), pack), load_trial(trial("lowpass_torques_hz = 6.0\n"), pack)
    elbow = list(pack.coordinates).index("r_elbow_flex")
    expected = lowpass_coordinates(torques.time, spiked[:, column], 6.0)[0][:, 0]
    expected = np.interp(filtered.time, torques.time, expected)
    assert np.allclose(filtered.torques[:, elbow], expected, atol=1e-9)
    assert raw.torques[:, elbow].max() - filtered.torques[:, elbow].max() > 2.0  # the spike is spread, not kept
    with pytest.raises(ConfigError) as err:
        load_trial(trial("lowpass_torques_hz = 0\n"), pack)
    assert err.value.field == "lowpass_torques_hz" and "t.toml" in str(err.value)
    no_torques = tmp_path / "no_torques.toml"
    no_torques.write_text(f'kinematics = "{data / "arm26_InverseKinematics.mot"}"\nlowpass_torques_hz = 6.0\n')
    with pytest.raises(ConfigError) as err:
        load_trial(no_torques, pack)
    assert err.value.field == "lowpass_torques_hz" and "without `torques`" in str(err.value)
