"""``msk model list|compile|check|scale|show``: list the shipped packs, build packs from OpenSim models, validate them,
scale them."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError
from services.commands.progress import ProgressBar

SHARED_MODELS = Path(os.environ.get("MSK_SHARED_DIR", Path(__file__).resolve().parents[2].parent / "shared")) / "models"


def _source_osim(pack, given: Path | None) -> Path:
    """--osim, or the pack's source model in the reference material (MSK_SHARED_DIR or ../shared)."""
    if given is not None:
        return given
    if pack.raw.get("scaling"):
        raise ConfigError("a scaled pack needs --osim (its scaled .osim was written beside it)", field="--osim")
    candidate = SHARED_MODELS / pack.raw["source_model"]
    if not candidate.is_file():
        raise ConfigError(f"no --osim given and the source model is not at {candidate}", field="--osim")
    return candidate


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "model", help="compile, check, scale and show musculoskeletal model packs", description=__doc__
    )
    sub = parser.add_subparsers(dest="model_command", required=True)

    p = sub.add_parser("compile", help="compile an OpenSim model + TOML spec into a pack (JSON)")
    p.add_argument("--osim", type=Path, required=True, help="OpenSim .osim model")
    p.add_argument("--spec", type=Path, required=True, help="pack spec (TOML), see docs/models.md")
    p.add_argument("--out", type=Path, required=True, help="output pack file (.json)")
    p.set_defaults(handler=run_compile)

    p = sub.add_parser("check", help="compare a pack with OpenSim on fresh random poses")
    p.add_argument("pack", help="shipped pack name or pack .json path")
    p.add_argument(
        "--osim",
        type=Path,
        default=None,
        help="the OpenSim model the pack was compiled from (default: shared/models/<source model>)",
    )
    p.add_argument("--poses", type=int, default=30, help="random poses (default 30)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hand-load", type=float, default=200.0, help="hand load for the dynamics check, N")
    p.add_argument("--json", type=Path, default=None, help="also write the report here")
    p.add_argument(
        "--recorded",
        nargs=2,
        type=Path,
        metavar=("IK_STO", "ID_STO"),
        action="append",
        default=[],
        help="also compare with a recorded OpenSim IK + ID pair (repeatable), e.g. backmodel-lift trials",
    )
    p.add_argument("--recorded-load", type=float, default=0.0, help="hand load of the recorded trials, N")
    p.set_defaults(handler=run_check)

    p = sub.add_parser("scale", help="scale the source OpenSim model to a person and recompile the pack")
    p.add_argument("--pack", required=True, help="shipped pack name or pack .json path (its spec is reused)")
    p.add_argument(
        "--osim",
        type=Path,
        default=None,
        help="the generic OpenSim model of that pack (default: shared/models/<source model>)",
    )
    p.add_argument("--mass-kg", type=float, required=True)
    p.add_argument("--height-m", type=float, required=True)
    p.add_argument(
        "--segment",
        action="append",
        default=[],
        metavar="NAME=LENGTH_M",
        help="measured segment length, repeatable (names: see docs/models.md)",
    )
    p.add_argument("--out", type=Path, required=True, help="output pack (.json); the scaled .osim is written beside it")
    p.add_argument("--samples", type=int, default=None, help="override the spec's fit samples (faster, coarser)")
    p.set_defaults(handler=run_scale)

    p = sub.add_parser("list", help="list the shipped packs: coordinates, groups, whether msk live can drive them")
    p.set_defaults(handler=run_list)

    p = sub.add_parser("show", help="print a pack's coordinates (ranges) and groups (F_max, members)")
    p.add_argument("pack", help="shipped pack name or pack .json path")
    p.set_defaults(handler=run_show)


def run_compile(args: argparse.Namespace) -> int:
    from msk_core.model.compile import compile_pack, write_pack  # noqa: PLC0415 - needs opensim
    from msk_core.model.spec import load_spec  # noqa: PLC0415

    spec = load_spec(args.spec)
    pack = compile_pack(args.osim, spec, progress=ProgressBar())
    out = write_pack(pack, args.out)
    for note in pack["fit_report"].get("notes", []):
        print(f"note: {note}")
    print(f"wrote {out}")
    return 0


def _print_check(report: dict) -> None:
    m, d = report["muscles"], report["dynamics"]
    print(
        f"moment arms over {m['poses']} fresh poses: RMS {m['moment_arm_rms_mm']:.3f} mm, max "
        f"{m['moment_arm_max_mm']:.3f} mm (targets 0.5 / 2 mm); lengths RMS {m['length_rms_mm']:.3f} mm, max "
        f"{m['length_max_mm']:.3f} mm; OpenSim glitch poses excluded: {m['opensim_glitch_poses_excluded']}"
    )
    print(
        f"moment arms vs -dl/dq of OpenSim's own path length: RMS {m['path_derivative_rms_mm']:.3f} mm, max "
        f"{m['path_derivative_max_mm']:.3f} mm (computeMomentArm may pick another wrap solution)"
    )
    coords = list(next(iter(m["groups"].values()))["moment_arm_rms_mm"])
    print(f"{'group':14s} " + " ".join(f"{c[:18]:>18s} rms/max" for c in coords) + "   length max")
    for g, s in m["groups"].items():
        cells = " ".join(f"{s['moment_arm_rms_mm'][c]:12.3f}/{s['moment_arm_max_mm'][c]:<12.3f}" for c in coords)
        print(f"{g:14s} {cells}   {s['length_max_mm']:.3f} mm")
    print(
        f"inverse dynamics vs OpenSim InverseDynamicsSolver ({d['poses']} poses, "
        + (
            f"hand load {d['hand_load_newton']} N):"
            if d.get("pack_has_hand_load", True)
            else "no hand load: the pack has none):"
        )
    )
    for c in d["peak_nm"]:
        print(
            f"  {c:22s} peak {d['peak_nm'][c]:9.3f} N·m  max error {d['max_error_nm'][c]:.3g} N·m "
            f"= {d['max_error_percent_of_peak'][c]:.3f} % of peak (target 1 %)"
        )


def run_check(args: argparse.Namespace) -> int:
    from msk_core.model import load_pack  # noqa: PLC0415
    from msk_core.model.check import check_dynamics, check_muscles  # noqa: PLC0415

    if args.poses < 2:
        raise ConfigError("need at least 2 poses", field="--poses", value=args.poses)
    pack = load_pack(args.pack)
    args.osim = _source_osim(pack, args.osim)
    muscles = check_muscles(pack, args.osim, n_poses=args.poses, seed=args.seed, progress=ProgressBar())
    dynamics = check_dynamics(
        pack, args.osim, n_poses=args.poses, seed=args.seed, hand_load=args.hand_load, progress=ProgressBar()
    )
    recorded: list[dict] = []  # filled below, printed with the report
    report = {"pack": pack.name, "muscles": muscles, "dynamics": dynamics, "recorded": recorded}
    _print_check(report)
    if args.recorded:
        from msk_core.model.reference_id import compare_with_recorded_id  # noqa: PLC0415

        for ik, idf in args.recorded:
            rec = compare_with_recorded_id(pack, args.osim, ik, idf, hand_load_newton=args.recorded_load)
            recorded.append({"ik": str(ik), "id": str(idf), **rec})
            for c in pack.coordinates:
                print(
                    f"recorded {idf}: {c} RMS error {rec['rms_error_nm'][c]:.2f} N·m = "
                    f"{rec['rms_error_percent_of_peak'][c]:.1f} % of peak {rec['peak_nm'][c]:.1f} N·m, "
                    f"correlation {rec['correlation'][c]:.3f} ({rec['frames']} frames)"
                )
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1, default=lambda o: np.asarray(o).tolist()))
    return 0


def run_scale(args: argparse.Namespace) -> int:
    from msk_core.model import load_pack  # noqa: PLC0415
    from msk_core.model.scale import parse_segments, scale_pack  # noqa: PLC0415 - needs opensim

    segments = parse_segments(args.segment)
    osim = _source_osim(load_pack(args.pack), args.osim)
    out, summary = scale_pack(
        args.pack,
        osim,
        mass_kg=args.mass_kg,
        height_m=args.height_m,
        segments=segments,
        out=args.out,
        samples=args.samples,
        progress=ProgressBar(),
    )
    print(f"wrote {out}")
    for key, value in summary.items():
        print(f"  {key}: {value}")
    return 0


def run_list(args: argparse.Namespace) -> int:
    """The shipped packs, one line each (a new user found their names only in error messages)."""
    from msk_core.imu.mapping import MAPPINGS  # noqa: PLC0415
    from msk_core.model import load_pack  # noqa: PLC0415
    from msk_core.model.pack import available_packs  # noqa: PLC0415

    for name in available_packs():
        pack = load_pack(name)
        live = "msk live: yes (IMU table)" if name in MAPPINGS else "offline only (no IMU table)"
        n = len(pack.coordinates)
        counts = f"{n:2d} coordinate{'' if n == 1 else 's'}, {len(pack.groups):3d} groups"
        print(f"{name:12s} {counts}; {live}; {pack.description}")
    print("details: msk model show NAME")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from msk_core.model import load_pack  # noqa: PLC0415

    pack = load_pack(args.pack)
    print(f"{pack.name} {pack.version}: {pack.description}")
    for c, (lo, hi) in zip(pack.coordinates, np.degrees(pack.coordinate_ranges)):
        print(f"  coordinate {c}: [{lo:.1f}, {hi:.1f}] deg")
    for g, f in zip(pack.groups, pack.f_max_ref):
        print(f"  group {g:12s} F_max {f:8.1f} N  members {', '.join(pack.members[g])}")
    return 0
