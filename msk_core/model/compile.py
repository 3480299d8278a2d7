"""Compile an OpenSim model + pack spec into a model pack (JSON): length/moment-arm surrogates and rigid body.

Per muscle: sample poses (Latin hypercube over the pack ranges), OpenSim path lengths and their central-difference
derivatives, find the coordinates the muscle spans, fit l(q) jointly to lengths and derivatives with a polynomial
whose total degree is picked on held-out poses; moment arms are the analytic r = -dl/dq. A group's surrogate is the
F_max-weighted mean of its bundles (so F_max_ref x r_group equals the sum of bundle torques at equal activation).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError
from msk_core.model import osim_tools
from msk_core.model.extract import extract_rigid
from msk_core.model.pack import PACK_FORMAT
from msk_core.model.poly import (
    fit_length,
    hinge_derivatives,
    hinge_values,
    monomial_derivatives,
    monomials,
)
from msk_core.model.spec import PackSpec, parse_spec
from msk_core.progress import Progress

SPAN_THRESHOLD = 1e-4  # m/rad: a bundle "spans" a coordinate when |moment arm| exceeds 0.1 mm somewhere
DERIVATIVE_WEIGHT = 5.0  # moment arms matter more than lengths (and some OpenSim paths jump in length, not in r)


def latin_hypercube(n: int, lower: np.ndarray, upper: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """n stratified samples in the box [lower, upper]."""
    dims = len(lower)
    u = (np.argsort(rng.random((dims, n)), axis=1).T + rng.random((n, dims))) / n
    return lower + u * (upper - lower)


def _fit_muscle(x_fit, l_fit, d_fit, x_test, l_test, d_test, max_degree: int, hinges=()):
    """Pick the degree with the best held-out moment-arm RMS; returns (exponents, coef, report)."""
    best = None
    k = x_fit.shape[1]
    hinges = list(hinges)
    for degree in range(1, max_degree + 1):
        if math.comb(k + degree, degree) + 3 * len(hinges) > 0.5 * len(x_fit) * (k + 1):
            break
        exps, coef = fit_length(x_fit, l_fit, d_fit, degree, derivative_weight=DERIVATIVE_WEIGHT, hinges=hinges)
        dl = np.stack(
            [
                np.hstack([monomial_derivatives(x_test, exps, v), hinge_derivatives(x_test, hinges, v)]) @ coef
                for v in range(k)
            ],
            axis=1,
        )
        err_r = dl - d_test
        err_l = np.nan_to_num(np.hstack([monomials(x_test, exps), hinge_values(x_test, hinges)]) @ coef - l_test)
        score = float(np.sqrt(np.nanmean(err_r**2)))
        if best is None or score < best[2]["r_rms_x"]:
            best = (exps, coef, {"degree": degree, "r_rms_x": score, "dl_x": err_r, "l_err": err_l})
    return best


KNOT_JUMP = 1.5e-3  # m/rad: a moment-arm step this large between neighbouring scan poses is a path switch
KNOT_STEP_DEG = 0.25
MAX_KNOTS = 3  # per bundle and coordinate


def detect_knots(
    poser, names: list[str], spec: PackSpec, progress: Progress | None
) -> dict[str, list[tuple[int, float]]]:
    """Per bundle, (coordinate index, normalised x) where its moment arm jumps: a scan of each coordinate alone
    (others at their reference) on a fine grid. Isolated glitches (a jump straight back) are ignored."""
    q0 = np.array([c.reference for c in spec.coordinates])
    knots: dict[str, list[tuple[int, float]]] = {m: [] for m in names}
    for j, c in enumerate(spec.coordinates):
        count = int(np.ceil(np.degrees(c.upper - c.lower) / KNOT_STEP_DEG)) + 1
        values = np.linspace(c.lower, c.upper, count)
        poses = np.repeat(q0[None, :], count, axis=0)
        poses[:, j] = values
        _, derivs = osim_tools.sample_lengths(
            poser,
            names,
            poses,
            delta=1e-5,
            only=j,
            progress=progress,
            task=f"{spec.name}: path-switch scan {c.name} (poses)",
        )
        r = derivs[:, :, j]  # (count, m) dl/dq (NaN where the slopes disagree: right at a switch)
        for i, name in enumerate(names):
            series = r[:, i]
            good = np.flatnonzero(np.isfinite(series))
            if len(good) < 3:
                continue
            steps = np.diff(series[good])
            size = np.abs(steps)
            # a switch is a step far above the smooth variation around it (median of its +-5 neighbours)
            local = np.array([np.median(np.delete(size[max(0, a - 5) : a + 6], min(a, 5))) for a in range(len(size))])
            jumps = sorted(np.flatnonzero((size > KNOT_JUMP) & (size > 8 * local)).tolist(), key=lambda a: -size[a])[
                :MAX_KNOTS
            ]
            for a in jumps:
                back = [b for b in jumps if 0 < abs(b - a) <= 3 and np.sign(steps[b]) != np.sign(steps[a])]
                if back:
                    continue  # isolated glitch: a jump straight back
                q_knot = (values[good[a]] + values[good[a + 1]]) / 2
                x_knot = (q_knot - (c.upper + c.lower) / 2) / ((c.upper - c.lower) / 2)
                knots[name].append((j, float(x_knot)))
    return knots


def compile_pack(osim_path: str | Path, spec: PackSpec, *, progress: Progress | None = None) -> dict:
    """Compile and return the pack dictionary (write it with :func:`write_pack`)."""
    model, state = osim_tools.load_model(osim_path, gravity=spec.dynamics.gravity)
    g = np.array(model.getGravity().to_numpy())
    poser = osim_tools.OsimPoser(model, state, spec)
    names = _member_names(spec)
    table = osim_tools.muscle_table(model, names, spec)
    fits = _fit_lengths(poser, names, spec, progress)
    _check_groups_cross(spec, fits.report)
    rigid, validation = _dynamics(poser, spec, g)
    source = Path(osim_path)
    return {
        "format": PACK_FORMAT,
        "name": spec.name,
        "version": spec.version,
        "description": spec.description,
        "source_model": spec.source_model or source.name,
        "source_sha256": hashlib.sha256(source.read_bytes()).hexdigest(),
        "coordinates": spec.coordinate_names,
        "coordinate_ranges": [[c.lower, c.upper] for c in spec.coordinates],
        "reference_pose": [c.reference for c in spec.coordinates],
        "coupled": {c.name: c.coupled for c in spec.coordinates if c.coupled},
        "locked": spec.locked,
        "groups": list(spec.groups),
        "members": spec.groups,
        "member_f_max": {m: table[m]["f_max"] for m in names},
        "member_optimal_fiber_length": {m: table[m]["l_opt"] for m in names},
        **_group_parameters(spec, table),
        "basis": {
            "exponents": [list(e) for e in fits.basis],
            "centre": fits.centre.tolist(),
            "half_width": fits.half.tolist(),
            "hinges": [[j, xk] for j, xk in fits.hinges],
        },
        "length_coefficients": _group_coefficients(spec, table, fits).tolist(),
        "dynamics": rigid,
        "validation_dynamics": validation,
        "fit_report": {
            "samples": fits.n_poses,
            "holdout": fits.n_test,
            "muscles": fits.report,
            "notes": _range_notes(poser, spec) + _jump_notes(fits.report, fits.n_poses),
        },
        "spec": spec.text,
    }


NARROW_RANGE_DEG = 5.0  # a pack range narrower than this is likely radians typed as degrees
JUMP_DROP_SHARE = 0.1  # a muscle whose fit dropped more of its samples as path jumps is said


def _range_notes(poser, spec: PackSpec) -> list[str]:
    """What the compile command says about the spec's ranges: beyond the model's own range for the coordinate (its
    moment arms there are the model's geometry carried on, which OpenSim's tools clamp away when the coordinate is
    clamped), or so narrow it looks like radians typed as degrees."""
    notes = []
    for c in spec.coordinates:
        model = poser.coords[c.name]
        lo, hi = model.getRangeMin(), model.getRangeMax()
        if c.lower < lo - 1e-6 or c.upper > hi + 1e-6:
            notes.append(
                f"coordinates.{c.name}: range [{math.degrees(c.lower):g}, {math.degrees(c.upper):g}] deg goes "
                f"beyond the model's [{math.degrees(lo):.4g}, {math.degrees(hi):.4g}]"
                + (" (clamped there in the model)" if model.get_clamped() else "")
            )
        if math.degrees(c.upper - c.lower) < NARROW_RANGE_DEG:
            notes.append(
                f"coordinates.{c.name}: range [{math.degrees(c.lower):g}, {math.degrees(c.upper):g}] deg is under "
                f"{NARROW_RANGE_DEG:g} deg wide: radians typed as degrees?"
            )
    return notes


def _jump_notes(report: dict, poses: int) -> list[str]:
    """Muscles whose fit dropped many samples as path jumps (a steep but smooth path can look like one): their
    held-out figures then leave those poses out; msk model check measures every pose."""
    return [
        f"{name}: {r['derivative_samples_dropped_at_path_jumps']} of {poses} samples dropped at path jumps; check the "
        "pack with msk model check"
        for name, r in report.items()
        if r.get("derivative_samples_dropped_at_path_jumps", 0) > JUMP_DROP_SHARE * poses
    ]


def _check_groups_cross(spec: PackSpec, report: dict) -> None:
    """A group none of whose muscles crosses a pack coordinate (its moment arms would be zero everywhere: a muscle of
    another joint, a coordinate left out) is a spec mistake, refused naming the group."""
    for group, members in spec.groups.items():
        if not any(report[m]["spans"] for m in members):
            raise ConfigError(
                f"no muscle of this group ({', '.join(members)}) crosses a pack coordinate "
                f"({', '.join(spec.coordinate_names)}): its moment arms would be zero throughout",
                path=spec.path,
                line=spec.line_of(group),
                field=f"groups.{group}",
                value=members,
            )


def _member_names(spec: PackSpec) -> list[str]:
    """Every muscle of the spec's groups, in group order; a muscle may belong to one group only."""
    names = [m for g_ in spec.groups.values() for m in g_]
    if len(set(names)) != len(names):
        dup = sorted({m for m in names if names.count(m) > 1})
        owners = [g for g, members in spec.groups.items() if dup[0] in members]
        raise ConfigError(
            f"a muscle belongs to more than one group: {dup[0]} is in {' and '.join(owners)}",
            path=spec.path,
            line=spec.line_of(dup[0]),
            field="groups",
            value=dup,
        )
    return names


# one muscle's length polynomial: exponents (terms, n), coefficients (terms,), hinges (coordinate, knot) and the
# hinge coefficients (3 per hinge)
_MuscleFit = tuple[np.ndarray, np.ndarray, list[tuple[int, float]], np.ndarray]


@dataclass
class _LengthFits:
    """Per-muscle polynomial length fits and the shared basis they are expressed in."""

    muscles: dict[str, _MuscleFit]
    basis: list[tuple[int, ...]]
    hinges: list[tuple[int, float]]
    centre: np.ndarray
    half: np.ndarray
    n_poses: int
    n_test: int
    report: dict


def _fit_lengths(poser, names: list[str], spec: PackSpec, progress: Progress | None) -> _LengthFits:
    """Sample OpenSim's muscle lengths over the coordinate box and fit each muscle's length polynomial."""
    lo = np.array([c.lower for c in spec.coordinates])
    hi = np.array([c.upper for c in spec.coordinates])
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    rng = np.random.default_rng(spec.fit.seed)
    poses = latin_hypercube(spec.fit.samples, lo, hi, rng)
    n_test = max(1, int(round(spec.fit.holdout * len(poses))))
    lengths, derivs = osim_tools.sample_lengths(
        poser, names, poses, progress=progress, task=f"{spec.name}: OpenSim lengths (poses)"
    )
    knots = detect_knots(poser, names, spec, progress)
    x = (poses - centre) / half
    dx = derivs * half[None, None, :]  # dl/dx
    fit_idx, test_idx = np.arange(n_test, len(poses)), np.arange(n_test)
    n = len(spec.coordinates)
    muscle_fits: dict[str, _MuscleFit] = {}
    report = {}
    for i, name in enumerate(names):
        spanned = [j for j in range(n) if np.nanmax(np.abs(derivs[:, i, j])) > SPAN_THRESHOLD]
        if not spanned:
            muscle_fits[name] = (
                np.zeros((1, n), dtype=np.int64),
                np.array([np.nanmean(lengths[:, i])]),
                [],
                np.zeros(0),
            )
            report[name] = {"spans": [], "degree": 0, "length_rms_mm": float(1e3 * np.nanstd(lengths[:, i]))}
            continue
        xs = x[:, spanned]
        local_hinges = [(spanned.index(j), xk) for j, xk in knots[name] if j in spanned]
        fitted = _fit_muscle(
            xs[fit_idx],
            lengths[fit_idx, i],
            dx[fit_idx, i][:, spanned],
            xs[test_idx],
            lengths[test_idx, i],
            dx[test_idx, i][:, spanned],
            spec.fit.max_degree,
            local_hinges,
        )
        if fitted is None:  # not even a first-degree polynomial has enough poses to be fitted
            raise ConfigError(
                f"{len(fit_idx)} poses are too few to fit {name}, which crosses {len(spanned)} pack coordinate(s): "
                "raise [fit] samples or lower [fit] holdout",
                path=spec.path,
                field="fit.samples",
                value=spec.fit.samples,
            )
        exps, coef, info = fitted
        full = np.zeros((len(exps), n), dtype=np.int64)
        full[:, spanned] = exps
        global_hinges = [(spanned[lj], xk) for lj, xk in local_hinges]
        muscle_fits[name] = (full, coef[: len(exps)], global_hinges, coef[len(exps) :])
        r_err = info["dl_x"] / half[spanned][None, :]
        report[name] = {
            "spans": [spec.coordinates[j].name for j in spanned],
            "degree": info["degree"],
            "knots_deg": [
                [spec.coordinates[j].name, float(np.degrees(centre[j] + xk * half[j]))] for j, xk in global_hinges
            ],
            "holdout_moment_arm_rms_mm": float(1e3 * np.sqrt(np.nanmean(r_err**2))),
            "holdout_moment_arm_max_mm": float(1e3 * np.nanmax(np.abs(r_err))),
            "derivative_samples_dropped_at_path_jumps": int(np.isnan(derivs[:, i, spanned]).any(axis=1).sum()),
            "length_samples_dropped_as_opensim_glitches": int(np.isnan(lengths[:, i]).sum()),
            "holdout_length_max_mm": float(1e3 * np.max(np.abs(info["l_err"]))),
        }
    # shared basis: union of all bundles' exponents (each closed under differentiation, so is the union)
    basis = sorted({tuple(e) for fit in muscle_fits.values() for e in fit[0].tolist()}, key=lambda e: (sum(e), e))
    hinges = sorted({h for fit in muscle_fits.values() for h in fit[2]})
    return _LengthFits(muscle_fits, basis, hinges, centre, half, len(poses), n_test, report)


def _group_coefficients(spec: PackSpec, table: dict, fits: _LengthFits) -> np.ndarray:
    """Each group's length polynomial: its members' fits weighted by their share of the group's F_max."""
    index = {e: k for k, e in enumerate(fits.basis)}
    hinge_index = {h: k for k, h in enumerate(fits.hinges)}
    coefficients = np.zeros((len(spec.groups), len(fits.basis) + 3 * len(fits.hinges)))
    for gi, members in enumerate(spec.groups.values()):
        forces = np.array([table[m]["f_max"] for m in members])
        for w, m in zip(forces / forces.sum(), members):
            full, coef, muscle_hinges, hinge_coef = fits.muscles[m]
            for e, c in zip(full.tolist(), coef):
                coefficients[gi, index[tuple(e)]] += w * c
            for h_i, h in enumerate(muscle_hinges):
                col = len(fits.basis) + 3 * hinge_index[h]
                coefficients[gi, col : col + 3] += w * hinge_coef[3 * h_i : 3 * h_i + 3]
    return coefficients


def _group_parameters(spec: PackSpec, table: dict) -> dict:
    """Per-group F_max (sum), force-weighted optimal fibre and tendon slack lengths, and activation bounds."""
    f_max, l_opt, l_slack = [], [], []
    for members in spec.groups.values():
        forces = np.array([table[m]["f_max"] for m in members])
        weights = forces / forces.sum()
        f_max.append(float(forces.sum()))
        l_opt.append(float(weights @ [table[m]["l_opt"] for m in members]))
        l_slack.append(float(weights @ [table[m]["l_slack"] for m in members]))
    return {
        "f_max_ref": f_max,
        "optimal_fiber_lengths": l_opt,
        "tendon_slack_lengths": l_slack,
        **group_activation_bounds(spec.groups, table),
    }


def group_activation_bounds(groups: dict[str, list[str]], table: dict) -> dict:
    """OpenSim's per-muscle control bounds as the pack's per-group activation bounds: one activation drives every
    member, so it must respect all of them (largest min_control, smallest max_control)."""
    return {
        "member_min_control": {m: float(table[m]["min_control"]) for ms in groups.values() for m in ms},
        "member_max_control": {m: float(table[m]["max_control"]) for ms in groups.values() for m in ms},
        "min_control": [max(float(table[m]["min_control"]) for m in ms) for ms in groups.values()],
        "max_control": [min(float(table[m]["max_control"]) for m in ms) for ms in groups.values()],
    }


def _dynamics(poser, spec: PackSpec, g: np.ndarray) -> tuple[dict, dict | None]:
    """(live rigid-body description, ground-rooted validation description or None)."""
    dyn = spec.dynamics
    rigid = extract_rigid(
        poser,
        spec,
        root=dyn.root,
        exclude=dyn.exclude_bodies,
        shared_from=dyn.shared_from,
        gravity=g,
        load_share=dyn.load_share,
    )
    validation = None
    if dyn.root != "ground" or dyn.shared_from or dyn.exclude_bodies:
        # the whole model as OpenSim has it (pelvis-rooted, nothing shared: the full bar on this model)
        validation = extract_rigid(
            poser,
            spec,
            root="ground",
            exclude=(),
            shared_from="",
            gravity=g,
            load_share=1.0 if dyn.shared_from else dyn.load_share,
        )
    return rigid, validation


def recompile_dynamics(pack: dict, osim_path: str | Path, spec: PackSpec) -> dict:
    """A copy of ``pack`` with its rigid-body part rebuilt from ``spec`` (whose muscle part must be unchanged).

    The muscle fits depend only on coordinates, groups, locked pose and [fit] -- all checked equal to the pack's
    own spec -- so this equals a full :func:`compile_pack` without the slow OpenSim path sampling."""
    old = parse_spec(pack["spec"])
    for field in ("coordinates", "locked", "groups", "fit"):
        if getattr(old, field) != getattr(spec, field):
            raise ConfigError(f"spec changes {field!r}: recompile the whole pack", path=spec.path, field=field)
    model, state = osim_tools.load_model(osim_path, gravity=spec.dynamics.gravity)
    g = np.array(model.getGravity().to_numpy())
    poser = osim_tools.OsimPoser(model, state, spec)
    rigid, validation = _dynamics(poser, spec, g)
    source = Path(osim_path)
    out = dict(pack)
    out.update(
        dynamics=rigid,
        validation_dynamics=validation,
        spec=spec.text,
        version=spec.version,
        description=spec.description,
        source_sha256=hashlib.sha256(source.read_bytes()).hexdigest(),
    )
    if out["source_sha256"] != pack["source_sha256"]:
        raise ConfigError("a different OpenSim model than the pack was compiled from", path=source)
    return out


def write_pack(pack: dict, out: str | Path) -> Path:
    out = Path(out)
    if out.suffix != ".json":
        out = out.with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(pack, indent=1))
    return out
