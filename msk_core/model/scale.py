"""Subject-specific packs: scale the source OpenSim model (OpenSim's own Model.scale) and recompile the pack.

Scale factors: every body gets height / reference_height; bodies of a measured segment get
measured_length / generic_length instead, where a segment's length is the distance between two body origins (joint
centres) in the generic model at its default pose. Masses keep the generic distribution and are multiplied by
mass / reference_mass (the whole-body mass the generic model stands for; partial models such as arm26 scale their
own bodies by that ratio). The spec's ``[scaling]`` table defines reference height/mass and the segments.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError
from msk_core.model import osim_tools
from msk_core.model.compile import compile_pack, write_pack
from msk_core.model.pack import load_pack
from msk_core.model.spec import closest, parse_spec
from msk_core.progress import Progress


def parse_segments(items: list[str]) -> dict[str, float]:
    """``["upper_arm=0.31", ...]`` -> {"upper_arm": 0.31}; errors name the flag and value."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            length = float(value)
        except ValueError:
            length = math.nan
        if not sep or not name or not (0.01 < length < 3.0):
            raise ConfigError("expected NAME=LENGTH_M with 0.01 < LENGTH_M < 3", field="--segment", value=item)
        out[name.strip()] = length
    return out


def scaling_table(spec_text: str, spec_path: Path | None = None) -> dict:
    import tomllib  # noqa: PLC0415

    raw = tomllib.loads(spec_text).get("scaling")
    if not raw:
        raise ConfigError("the pack's spec has no [scaling] table (reference height, segments)", path=spec_path)
    return raw


def segment_lengths(model, state, segments: dict) -> dict[str, float]:
    """Generic-pose distance between the two body origins that define each segment."""
    bodies = model.getBodySet()
    model.realizePosition(state)
    out = {}
    for name, seg in segments.items():
        a, b = (bodies.get(x).getPositionInGround(state).to_numpy() for x in seg["between"])
        out[name] = float(np.linalg.norm(np.asarray(a) - np.asarray(b)))
    return out


def model_mass(model) -> float:
    bodies = model.getBodySet()
    return float(sum(bodies.get(i).getMass() for i in range(bodies.getSize())))


def scale_model(
    osim_path: str | Path,
    spec_text: str,
    *,
    mass_kg: float,
    height_m: float,
    segments: dict[str, float],
    out_osim: Path,
    spec_path: Path | None = None,
) -> dict:
    """Write the scaled .osim; returns the factors and the generic/scaled segment lengths."""
    osim = osim_tools.import_opensim()
    if not 20.0 <= mass_kg <= 250.0:
        raise ConfigError("body mass must be within 20..250 kg", field="--mass-kg", value=mass_kg)
    if not 1.0 <= height_m <= 2.5:
        raise ConfigError("height must be within 1.0..2.5 m", field="--height-m", value=height_m)
    table = scaling_table(spec_text, spec_path)
    defined = table.get("segments", {})
    for name in segments:
        if name not in defined:
            raise ConfigError(
                f"unknown segment {name!r} ({closest(name, list(defined))}); defined: {', '.join(defined)}",
                field="--segment",
                value=name,
            )
    model, state = osim_tools.load_model(osim_path)
    generic = segment_lengths(model, state, defined)
    base = height_m / float(table["reference_height_m"])
    factors = {}
    bodies = model.getBodySet()
    for i in range(bodies.getSize()):
        factors[bodies.get(i).getName()] = base
    for name, length in segments.items():
        for body in defined[name]["bodies"]:
            factors[body] = length / generic[name]
    reference_mass = float(table.get("reference_mass_kg", model_mass(model)))
    final_mass = model_mass(model) * mass_kg / reference_mass
    scale_set = osim.ScaleSet()
    for body, factor in factors.items():
        scale = osim.Scale()
        scale.setSegmentName(body)
        scale.setScaleFactors(osim.Vec3(factor, factor, factor))
        scale.setApply(True)
        scale_set.cloneAndAppend(scale)
    with osim_tools._quiet_stderr():
        model.scale(state, scale_set, True, final_mass)
        out_osim.parent.mkdir(parents=True, exist_ok=True)
        model.printToXML(str(out_osim))
    scaled_model, scaled_state = osim_tools.load_model(out_osim)
    return {
        "height_factor": base,
        "segment_factors": {n: segments[n] / generic[n] for n in segments},
        "generic_segment_lengths_m": generic,
        "scaled_segment_lengths_m": segment_lengths(scaled_model, scaled_state, defined),
        "model_mass_kg": model_mass(scaled_model),
        "scaled_osim": str(out_osim),
    }


def scale_pack(
    pack_name_or_path: str,
    osim_path: str | Path,
    *,
    mass_kg: float,
    height_m: float,
    segments: dict[str, float],
    out: str | Path,
    samples: int | None = None,
    progress: Progress | None = None,
) -> tuple[Path, dict]:
    """Scale the pack's source model to the person and recompile the pack from it (same spec)."""
    pack = load_pack(pack_name_or_path)
    spec_text = pack.raw["spec"]
    out = Path(out)
    out_osim = out.with_suffix(".osim")
    summary = scale_model(
        osim_path, spec_text, mass_kg=mass_kg, height_m=height_m, segments=segments, out_osim=out_osim
    )
    spec = parse_spec(spec_text, pack.path)
    if samples is not None:
        from dataclasses import replace  # noqa: PLC0415

        spec = replace(spec, fit=replace(spec.fit, samples=samples))
    data = compile_pack(out_osim, spec, progress=progress)
    data["name"] = f"{pack.name}"
    data["scaling"] = {
        "mass_kg": mass_kg,
        "height_m": height_m,
        "segments_m": segments,
        **{k: v for k, v in summary.items() if k != "scaled_osim"},
    }
    data["source_model"] = f"{spec.source_model} scaled to {mass_kg} kg, {height_m} m"
    written = write_pack(data, out)
    return written, summary
