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
from pathlib import Path

import numpy as np
from tqdm import tqdm

from msk_core.errors import ConfigError
from msk_core.model import osim_tools
from msk_core.model.extract import extract_rigid
from msk_core.model.pack import PACK_FORMAT
from msk_core.model.poly import fit_length, monomial_derivatives, monomials
from msk_core.model.spec import PackSpec

SPAN_THRESHOLD = 1e-4  # m/rad: a bundle "spans" a coordinate when |moment arm| exceeds 0.1 mm somewhere
DERIVATIVE_WEIGHT = 5.0  # moment arms matter more than lengths (and some OpenSim paths jump in length, not in r)


def latin_hypercube(n: int, lower: np.ndarray, upper: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """n stratified samples in the box [lower, upper]."""
    dims = len(lower)
    u = (np.argsort(rng.random((dims, n)), axis=1).T + rng.random((n, dims))) / n
    return lower + u * (upper - lower)


def _fit_muscle(x_fit, l_fit, d_fit, x_test, l_test, d_test, max_degree: int):
    """Pick the degree with the best held-out moment-arm RMS; returns (exponents, coef, report)."""
    best = None
    k = x_fit.shape[1]
    for degree in range(1, max_degree + 1):
        if math.comb(k + degree, degree) > 0.5 * len(x_fit) * (k + 1):
            break
        exps, coef = fit_length(x_fit, l_fit, d_fit, degree, derivative_weight=DERIVATIVE_WEIGHT)
        dl = np.stack([monomial_derivatives(x_test, exps, v) @ coef for v in range(k)], axis=1)
        err_r = dl - d_test
        err_l = np.nan_to_num(monomials(x_test, exps) @ coef - l_test)
        score = float(np.sqrt(np.nanmean(err_r**2)))
        if best is None or score < best[2]["r_rms_x"]:
            best = (exps, coef, {"degree": degree, "r_rms_x": score, "dl_x": err_r, "l_err": err_l})
    return best


def compile_pack(osim_path: str | Path, spec: PackSpec, *, progress: bool = True) -> dict:
    """Compile and return the pack dictionary (write it with :func:`write_pack`)."""
    gravity = spec.dynamics.gravity
    model, state = osim_tools.load_model(osim_path, gravity=gravity)
    g = np.array(model.getGravity().to_numpy())
    poser = osim_tools.OsimPoser(model, state, spec)
    names = [m for g_ in spec.groups.values() for m in g_]
    if len(set(names)) != len(names):
        dup = sorted({m for m in names if names.count(m) > 1})
        raise ConfigError("a muscle belongs to more than one group", path=spec.path, line=spec.line_of(dup[0]),
                          field="groups", value=dup)
    table = osim_tools.muscle_table(model, names, spec)
    lo = np.array([c.lower for c in spec.coordinates])
    hi = np.array([c.upper for c in spec.coordinates])
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    rng = np.random.default_rng(spec.fit.seed)
    poses = latin_hypercube(spec.fit.samples, lo, hi, rng)
    n_test = max(1, int(round(spec.fit.holdout * len(poses))))
    bar = tqdm(total=len(poses), desc=f"{spec.name}: OpenSim lengths", unit="pose", disable=not progress)
    lengths, derivs = osim_tools.sample_lengths(poser, names, poses, progress=bar)
    bar.close()
    x = (poses - centre) / half
    dx = derivs * half[None, None, :]  # dl/dx
    fit_idx, test_idx = np.arange(n_test, len(poses)), np.arange(n_test)
    n = len(spec.coordinates)
    muscle_fits = {}
    report = {}
    for i, name in enumerate(names):
        spanned = [j for j in range(n) if np.nanmax(np.abs(derivs[:, i, j])) > SPAN_THRESHOLD]
        if not spanned:
            muscle_fits[name] = (np.zeros((1, n), dtype=np.int64), np.array([np.nanmean(lengths[:, i])]))
            report[name] = {"spans": [], "degree": 0,
                            "length_rms_mm": float(1e3 * np.nanstd(lengths[:, i]))}
            continue
        xs = x[:, spanned]
        exps, coef, info = _fit_muscle(
            xs[fit_idx], lengths[fit_idx, i], dx[fit_idx, i][:, spanned],
            xs[test_idx], lengths[test_idx, i], dx[test_idx, i][:, spanned], spec.fit.max_degree,
        )
        full = np.zeros((len(exps), n), dtype=np.int64)
        full[:, spanned] = exps
        muscle_fits[name] = (full, coef)
        r_err = info["dl_x"] / half[spanned][None, :]
        report[name] = {
            "spans": [spec.coordinates[j].name for j in spanned],
            "degree": info["degree"],
            "holdout_moment_arm_rms_mm": float(1e3 * np.sqrt(np.nanmean(r_err**2))),
            "holdout_moment_arm_max_mm": float(1e3 * np.nanmax(np.abs(r_err))),
            "derivative_samples_dropped_at_path_jumps": int(np.isnan(derivs[:, i, spanned]).any(axis=1).sum()),
            "length_samples_dropped_as_opensim_glitches": int(np.isnan(lengths[:, i]).sum()),
            "holdout_length_max_mm": float(1e3 * np.max(np.abs(info["l_err"]))),
        }
    # shared basis: union of all bundles' exponents (each closed under differentiation, so is the union)
    basis = sorted({tuple(e) for full, _ in muscle_fits.values() for e in full.tolist()}, key=lambda e: (sum(e), e))
    index = {e: k for k, e in enumerate(basis)}
    coefficients = np.zeros((len(spec.groups), len(basis)))
    f_max, l_opt, l_slack = [], [], []
    for gi, (group, members) in enumerate(spec.groups.items()):
        forces = np.array([table[m]["f_max"] for m in members])
        weights = forces / forces.sum()
        for w, m in zip(weights, members):
            full, coef = muscle_fits[m]
            for e, c in zip(full.tolist(), coef):
                coefficients[gi, index[tuple(e)]] += w * c
        f_max.append(float(forces.sum()))
        l_opt.append(float(weights @ [table[m]["l_opt"] for m in members]))
        l_slack.append(float(weights @ [table[m]["l_slack"] for m in members]))
    dyn = spec.dynamics
    rigid = extract_rigid(poser, spec, root=dyn.root, exclude=dyn.exclude_bodies, shared_from=dyn.shared_from,
                          gravity=g, load_share=dyn.load_share)
    validation = None
    if dyn.root != "ground" or dyn.shared_from or dyn.exclude_bodies:
        # the whole model as OpenSim has it (pelvis-rooted, nothing shared: the full bar on this model)
        validation = extract_rigid(poser, spec, root="ground", exclude=(), shared_from="", gravity=g,
                                   load_share=1.0 if dyn.shared_from else dyn.load_share)
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
        "f_max_ref": f_max,
        "optimal_fiber_lengths": l_opt,
        "tendon_slack_lengths": l_slack,
        "basis": {"exponents": [list(e) for e in basis], "centre": centre.tolist(), "half_width": half.tolist()},
        "length_coefficients": coefficients.tolist(),
        "dynamics": rigid,
        "validation_dynamics": validation,
        "fit_report": {"samples": len(poses), "holdout": n_test, "muscles": report},
        "spec": spec.text,
    }


def write_pack(pack: dict, out: str | Path) -> Path:
    out = Path(out)
    if out.suffix != ".json":
        out = out.with_suffix(".json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(pack, indent=1))
    return out
