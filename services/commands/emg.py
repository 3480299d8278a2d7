"""``msk emg``: raw EMG files -> envelopes (.sto), and repetitions/phase of a kinematics file.

Examples::

    msk emg envelope ../shared/data/rajagopal-walk/emg_walk_raw.anc --channels SOL,GAS,TA -o walk_env.sto
    msk emg envelope session.csv --zero-phase --mvc mvc1.csv --mvc mvc2.csv -o env.sto   # Delsys CSV, offline
    msk emg reps ../shared/data/backmodel-lift/squat5kg/ik.sto --coordinate pelvis_ty --excursion decrease
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.io import AnalogRecording, read_anc, read_c3d_analogs, read_delsys_csv, read_sto, write_sto
from msk_core.io.storage import seconds, uniform_step
from msk_core.signal.emg import (
    EmgFilterConfig,
    NormalisationMode,
    envelope_causal,
    envelope_zero_phase_noncausal,
    mvc_window_samples,
    normalisation_reference,
    windowed_peak,
)
from msk_core.signal.reps import Excursion, PhaseMode, RepDetectionConfig, detect_reps, rep_phase
from services.commands import described

#: OpenSim's external-load columns (a .mot of ground reaction forces): ground_force_vx, l_ground_torque_y, 1_force_px
EXTERNAL_LOAD_COLUMN = re.compile(r"(^|_)(ground_)?(force_[vp][xyz]|torque_[xyz])$")


def _is_load(column: str) -> bool:
    return EXTERNAL_LOAD_COLUMN.search(column) is not None


def read_emg_file(path: Path, channels: list[str] | None) -> AnalogRecording:
    """Raw EMG from .anc, .c3d, Delsys .csv or an OpenSim .sto/.mot (evenly sampled), in volts where the file says
    how (:meth:`AnalogRecording.in_volts`: its units, an .anc's ranges); the channels it does not say it of are
    printed."""
    suffix = path.suffix.lower()
    if suffix == ".anc":
        rec = read_anc(path)
    elif suffix == ".c3d":
        rec = read_c3d_analogs(path)
    elif suffix == ".csv":
        rec = read_delsys_csv(path).recording()
    elif suffix in (".sto", ".mot"):
        s = read_sto(path)
        try:  # the filters are designed for one rate: an irregular time column would be filtered at its mean rate
            rate_hz = 1.0 / uniform_step(s.time)
        except InputError as error:
            raise InputError(f"{error.args[0]}; resample it evenly first", path=path, field="time") from None
        rec = AnalogRecording(
            time=s.time,
            labels=list(s.columns),
            data=s.data,
            rate_hz=rate_hz,
            units=[""] * len(s.columns),
            path=path,
            not_emg={
                c: "an external load's force, point or torque (OpenSim's naming)" for c in s.columns if _is_load(c)
            },
        )
    else:
        raise InputError("unknown EMG file type; expected .anc, .c3d, .csv, .sto or .mot", path=path, value=suffix)
    if channels:
        rec = rec.select(channels)  # asked for by name: taken as they are
    else:
        if rec.not_emg:  # e.g. the force-plate channels of a gait C3D
            by_reason: dict[str, list[str]] = {}
            for channel, why in rec.not_emg.items():
                by_reason.setdefault(why, []).append(channel)
            print(
                f"left out {len(rec.not_emg)} channels that are not EMG: "
                + "; ".join(f"{', '.join(channels)} ({why})" for why, channels in by_reason.items())
            )
        emg = [label for label in rec.labels if label not in rec.not_emg]
        twice = sorted({label for label in emg if emg.count(label) > 1})
        if twice:  # the envelopes' columns must be told apart (a C3D's labels cut to the sensor name, say)
            raise InputError(
                f"the file names {len(twice)} channel(s) more than once: {', '.join(twice)}; rename them in the file, "
                "or choose channels named once with --channels",
                path=path,
                field="channels",
            )
        rec = _without_slow_channels(rec.emg_only())
    rec, own_unit = rec.in_volts()
    if suffix == ".anc":
        print(f"{path.name}: volts at the acquisition board's input (the EMG amplifiers' gain is not removed)")
    silent = [label for label, column in zip(rec.labels, np.asarray(rec.data).T) if not np.any(column)]
    if silent:  # e.g. the unpaired slots a Trigno export keeps
        print(f"{path.name}: {len(silent)} channel(s) are zero throughout (no sensor?): " + ", ".join(silent))
    if own_unit:
        print(
            f"{path.name}: {len(own_unit)} channel(s) left in the file's own unit (it gives none that is a voltage): "
            + ", ".join(own_unit)
        )
    for label, column in zip(rec.labels, np.asarray(rec.data).T):
        if not np.all(np.isfinite(column)):  # the filters would carry it to the end of the file
            first = int(np.argmax(~np.isfinite(column)))
            raise InputError(
                f"EMG channel has NaN or infinite samples from t = {seconds(rec.time[first])} s; fill or cut the gap "
                "(the envelope filters would carry it to the end of the recording)",
                path=path,
                field=label,
            )
    return rec


def _without_slow_channels(rec: AnalogRecording) -> AnalogRecording:
    """The recording without the channels whose power lies below the EMG band and whose label does not say EMG (found
    with held-out data: a C3D's Voltage.1-6, a load cell's forces in volts, were enveloped as six muscles). A channel
    labelled EMG with such a spectrum is kept and said (a DC-coupled amplifier's drift). ``--channels`` takes any."""
    from msk_core.signal.quality import EMG_BAND_HZ, NOT_EMG_BELOW_BAND_SHARE, below_band_share

    below = f"{EMG_BAND_HZ[0]:g} Hz"
    shares = below_band_share(rec.data, rec.rate_hz)
    flagged = [(label, f) for label, f in zip(rec.labels, shares) if f >= NOT_EMG_BELOW_BAND_SHARE]
    left_out = [(label, f) for label, f in flagged if "emg" not in label.lower()]
    kept_slow = [(label, f) for label, f in flagged if "emg" in label.lower()]
    band = f"surface EMG's lies at {EMG_BAND_HZ[0]:g}-{EMG_BAND_HZ[1]:g} Hz; --channels takes them"
    if left_out:
        print(
            f"left out {len(left_out)} channel(s) whose power lies below {below}, not EMG (a force, a load cell, a "
            f"goniometer or a trigger?; {band}): " + ", ".join(f"{label} ({f:.0%})" for label, f in left_out)
        )
    if kept_slow:
        print(
            f"{len(kept_slow)} EMG channel(s) with most of their power below {below}, enveloped as EMG: "
            + ", ".join(f"{label} ({f:.0%})" for label, f in kept_slow)
            + " (drift or motion artefact? the band-pass removes it)"
        )
    if len(left_out) == len(rec.labels):
        raise InputError(
            f"no EMG channel: all {len(rec.labels)} channels have their power below {below} ({band})", path=rec.path
        )
    out = {label for label, _ in left_out}
    return rec.select([label for label in rec.labels if label not in out]) if left_out else rec


def _channels(text: str | None) -> list[str] | None:
    return [c.strip() for c in text.split(",") if c.strip()] if text else None


def _envelope(args: argparse.Namespace) -> int:
    from services.commands.estimate import output_folder

    if args.normalise is not None and not args.mvc:
        raise ConfigError(
            "normalising needs the MVC trial(s): add --mvc FILE", field="--normalise", value=args.normalise
        )
    output_folder(args.output.parent, "--output")  # before the filtering, as a user would want
    channels = _channels(args.channels)
    rec = read_emg_file(args.input, channels)
    band = None if args.no_bandpass else tuple(args.bandpass_hz)

    def filtered(recording: AnalogRecording) -> np.ndarray:
        """The envelope of a recording at its own rate (an MVC trial may be sampled unlike the task)."""
        if band is not None and band[1] >= recording.rate_hz / 2:  # raw EMG is sampled at 1-2 kHz or more
            raise ConfigError(
                f"sampled at {recording.rate_hz:g} Hz, too slowly for raw EMG's {band[0]:g}-{band[1]:g} Hz "
                "band-pass: it looks like an envelope or a resampled signal already. Give the raw EMG, or "
                "--no-bandpass (rectify and low-pass only) if this is raw EMG at a low rate",
                path=recording.path,
                field="--bandpass-hz",
                value=list(band),
            )
        cfg = EmgFilterConfig(
            rate_hz=recording.rate_hz, bandpass_hz=band, lowpass_hz=args.lowpass_hz, lowpass_order=args.lowpass_order
        )
        chain = envelope_zero_phase_noncausal if args.zero_phase else envelope_causal
        return chain(recording.data, cfg)

    def amplitude(recording: AnalogRecording, envelope: np.ndarray) -> np.ndarray:
        """Per channel, the highest MVC_WINDOW_S mean of an envelope at its recording's rate, as one row (the plain
        peak, used before, read a steady maximal contraction 21 % high: every normalised envelope that much low)."""
        return windowed_peak(envelope, mvc_window_samples(recording.rate_hz))[None, :]

    env = filtered(rec)
    if args.mvc:
        mvc_recordings = [read_emg_file(p, rec.labels) for p in args.mvc]
        mvc = [amplitude(r, filtered(r)) for r in mvc_recordings]
        mode = NormalisationMode(args.normalise or NormalisationMode.MVC.value)
        ref = normalisation_reference(
            mvc,
            task_envelopes=[amplitude(rec, env)] if mode is NormalisationMode.MAX_ALL_TRIALS else None,
            mode=mode,
            channels=tuple(rec.labels),
        )
        env = ref.normalise(env)
        above = np.max(env, axis=0)
        print(
            "normalised peak per channel (values > 1 kept): "
            + ", ".join(f"{c}={v:.2f}" for c, v in zip(rec.labels, above))
        )
    labels = [lab.replace(",", "_").replace("\t", "_") for lab in rec.labels]
    kind = "zero-phase (non-causal)" if args.zero_phase else "causal"
    unit = "normalised" if args.mvc else "V" if set(rec.units) == {"V"} else "file units"
    write_sto(args.output, rec.time, labels, env, name=f"EMG envelopes ({unit}), {kind}")
    print(f"wrote {args.output}: {env.shape[1]} channels x {env.shape[0]} samples at {rec.rate_hz:g} Hz ({kind})")
    return 0


def _reps(args: argparse.Namespace) -> int:
    s = read_sto(args.input)
    values = s.column(args.coordinate)
    cfg = RepDetectionConfig(
        excursion=Excursion(args.excursion),
        start_fraction=args.start_fraction,
        min_depth_fraction=args.min_depth_fraction,
    )
    reps = detect_reps(s.time, values, cfg)
    print(f"{len(reps)} repetitions in {args.input} ({args.coordinate}, {args.excursion})")
    print(f"{'rep':>3} {'start s':>10} {'turn s':>10} {'end s':>10} {'duration s':>10}")
    for k, r in enumerate(reps):
        print(
            f"{k + 1:>3} {r.t_start - s.time[0]:>10.3f} {r.t_turn - s.time[0]:>10.3f} "
            f"{r.t_end - s.time[0]:>10.3f} {r.duration:>10.3f}"
        )
    if args.phase_out:
        phase, index = rep_phase(s.time, reps, PhaseMode(args.mode))
        write_sto(args.phase_out, s.time, ["phase", "rep"], np.column_stack([phase, index]), name="Repetition phase")
        print(f"wrote {args.phase_out}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = described(
        subparsers.add_parser("emg", help="EMG envelopes from raw files; repetitions and phase of kinematics"), __doc__
    )
    sub = p.add_subparsers(dest="emg_command", required=True)

    e = sub.add_parser("envelope", help="raw EMG (.anc/.c3d/Delsys .csv/.sto) -> envelope .sto")
    e.add_argument("input", type=Path, help="raw EMG: .anc, .c3d, Delsys .csv, or an evenly sampled .sto/.mot")
    e.add_argument("-o", "--output", type=Path, required=True, help="the envelopes' .sto (its folder is made)")
    e.add_argument("--channels", help="comma-separated channel labels (default: all the file's EMG channels)")
    e.add_argument(
        "--bandpass-hz",
        type=float,
        nargs=2,
        default=(20.0, 450.0),
        metavar=("LOW", "HIGH"),
        help="band-pass before rectifying (default 20 450)",
    )
    e.add_argument("--no-bandpass", action="store_true", help="rectify the raw signal directly")
    e.add_argument("--lowpass-hz", type=float, default=6.0, help="envelope low-pass cut-off (default 6 Hz)")
    e.add_argument("--lowpass-order", type=int, default=3, help="Butterworth order of the low-pass (default 3)")
    e.add_argument("--zero-phase", action="store_true", help="offline forward-backward filtering (non-causal)")
    e.add_argument("--mvc", type=Path, action="append", default=[], help="MVC trial file(s) for normalisation")
    e.add_argument(
        "--normalise",
        choices=[m.value for m in NormalisationMode],
        default=None,
        help="with --mvc: divide by the MVC amplitude (mvc, the default: the highest 0.5 s mean of the MVC trials' "
        "envelopes), or by the highest over MVC and this trial",
    )
    e.set_defaults(handler=_envelope)

    r = sub.add_parser("reps", help="repetitions and phase from one coordinate of a .sto/.mot")
    r.add_argument("input", type=Path)
    r.add_argument("--coordinate", required=True)
    r.add_argument(
        "--excursion",
        choices=[x.value for x in Excursion],
        required=True,
        help="direction the coordinate moves away from rest during a rep",
    )
    r.add_argument(
        "--start-fraction",
        type=float,
        default=0.2,
        help="a rep is under way above this progress (0 at the trial's rest level, 1 at its full-rep level; "
        "default 0.2)",
    )
    r.add_argument(
        "--min-depth-fraction", type=float, default=0.5, help="a rep counts once it reaches this progress (default 0.5)"
    )
    r.add_argument("--mode", choices=[m.value for m in PhaseMode], default=PhaseMode.TURNING_POINT.value)
    r.add_argument("--phase-out", type=Path, help="write time, phase and rep index as .sto")
    r.set_defaults(handler=_reps)
