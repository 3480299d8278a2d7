"""OpenSim's own StaticOptimization as the offline reference (regression tests and the benchmark baseline).

OpenSim is imported lazily: it is slow to load and belongs offline, never in the per-frame loop.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError
from msk_core.io import Storage, read_sto


@dataclass
class OpenSimSOResult:
    activations: Storage
    forces: Storage
    wall_time_s: float
    min_control: dict[str, float]

    @property
    def seconds_per_frame(self) -> float:
        return self.wall_time_s / max(self.activations.n_rows, 1)


def run_opensim_static_optimization(
    setup_xml: str | Path,
    model_file: str | Path,
    coordinates_file: str | Path,
    out_dir: str | Path,
    *,
    use_muscle_physiology: bool = False,
    final_time: float | None = None,
) -> OpenSimSOResult:
    """Run OpenSim's AnalyzeTool with its StaticOptimization analysis from a setup file.

    The setup is rewritten into ``out_dir`` with absolute model/coordinates/results paths and the physiology flag
    (off: muscle force = max isometric force x activation, the model the estimator uses).
    """
    import opensim as osim

    setup_xml, out_dir = Path(setup_xml), Path(out_dir)
    text = setup_xml.read_text()
    replacements = {
        "model_file": str(Path(model_file).resolve()),
        "coordinates_file": str(Path(coordinates_file).resolve()),
        "results_directory": str(out_dir.resolve() / "results"),
        "use_muscle_physiology": "true" if use_muscle_physiology else "false",
    }
    if final_time is not None:
        replacements["final_time"] = repr(float(final_time))
        replacements["end_time"] = repr(float(final_time))
    for tag, value in replacements.items():
        text, n = re.subn(rf"<{tag}>[^<]*</{tag}>", f"<{tag}>{value}</{tag}>", text)
        if n == 0:
            raise ConfigError("setup file has no such element", path=setup_xml, field=tag)
    out_dir.mkdir(parents=True, exist_ok=True)
    local = out_dir / "setup_static_optimization.xml"
    local.write_text(text)
    osim.Logger.setLevelString("error")
    tool = osim.AnalyzeTool(str(local))
    model = tool.getModel()
    muscles = model.getMuscles()
    min_control = {muscles.get(i).getName(): muscles.get(i).getMinControl() for i in range(muscles.getSize())}
    t0 = time.perf_counter()
    tool.run()
    wall = time.perf_counter() - t0
    results = out_dir / "results"
    name = tool.getName()
    return OpenSimSOResult(
        activations=read_sto(results / f"{name}_StaticOptimization_activation.sto"),
        forces=read_sto(results / f"{name}_StaticOptimization_force.sto"),
        wall_time_s=wall,
        min_control=min_control,
    )


def opensim_filtered_kinematics(
    model_file: str | Path, coordinates_file: str | Path, coordinates: list[str], times: np.ndarray, cutoff_hz: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q, qd, qdd (radians) at ``times`` prepared exactly as AnalyzeTool does: pad, low-pass IIR, GCV quintic spline."""
    import opensim as osim

    osim.Logger.setLevelString("error")
    model = osim.Model(str(model_file))
    model.initSystem()
    storage = osim.Storage(str(coordinates_file))
    if storage.isInDegrees():
        model.getSimbodyEngine().convertDegreesToRadians(storage)
    storage.pad(storage.getSize() // 2)
    if cutoff_hz > 0:
        storage.lowpassIIR(cutoff_hz)
    splines = osim.GCVSplineSet(5, storage)
    out = np.zeros((3, len(times), len(coordinates)))
    # plain lists, which SWIG converts: an osim.StdVectorInt was once refused in a long test run ("argument 2 of type
    # std::vector< int > const &"), another module's wrapper of the same type having been registered first
    d1, d2 = [0], [0, 0]
    for j, name in enumerate(coordinates):
        spline = splines.get(name)
        for i, t in enumerate(times):
            x = osim.Vector(1, float(t))
            out[0, i, j] = spline.calcValue(x)
            out[1, i, j] = spline.calcDerivative(d1, x)
            out[2, i, j] = spline.calcDerivative(d2, x)
    return out[0], out[1], out[2]
