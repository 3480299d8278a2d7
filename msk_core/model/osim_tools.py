"""OpenSim side of pack compilation and validation (imported lazily: opensim is only needed offline).

:class:`OsimPoser` sets an OpenSim state from pack coordinates: locked coordinates at their spec values, the pack
coordinates, linearly coupled coordinates (ratio x driver) and the model's own CoordinateCouplerConstraints.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError, ModelError
from msk_core.model.spec import PackSpec, closest
from msk_core.progress import Progress, counted


def import_opensim():
    try:
        import opensim  # noqa: PLC0415 - heavy optional dependency, offline only
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ModelError("the opensim package is needed to compile or check packs (pip install opensim==4.6)") from exc
    return opensim


@contextlib.contextmanager
def _quiet_stderr():
    """OpenSim prints one warning per missing mesh file; keep the terminal readable."""
    try:
        fd = os.dup(2)
    except OSError:  # pragma: no cover
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(fd, 2)
        os.close(fd)


def load_model(path: str | Path, *, gravity: tuple[float, float, float] | None = None, forces: bool = True):
    """Load an .osim model (optionally without any force elements, for inverse dynamics) -> (model, state)."""
    osim = import_opensim()
    path = Path(path)
    if not path.is_file():
        raise ConfigError("OpenSim model not found", path=path)
    osim.Logger.setLevelString("error")
    with _quiet_stderr():
        try:
            model = osim.Model(str(path))
        except RuntimeError as error:  # SWIG's wrapper of OpenSim's exception: not an .osim it can read
            first = str(error).strip().splitlines()[0] if str(error).strip() else "unreadable"
            raise ConfigError(f"not an OpenSim model OpenSim can read: {first}", path=path) from None
        if not forces:
            fs = model.updForceSet()
            for i in range(fs.getSize()):
                fs.get(i).set_appliesForce(False)
        if gravity is not None:
            model.setGravity(osim.Vec3(*gravity))
        state = model.initSystem()
    return model, state


def _mat(rotation) -> np.ndarray:
    return np.array([[rotation.get(i, j) for j in range(3)] for i in range(3)])


class OsimPoser:
    """Sets OpenSim poses from pack coordinates (see module docstring)."""

    def __init__(self, model, state, spec: PackSpec) -> None:
        osim = import_opensim()
        self.model, self.state, self.spec = model, state, spec
        cs = model.getCoordinateSet()
        self.all_names = [cs.get(i).getName() for i in range(cs.getSize())]
        self.coords = {n: cs.get(n) for n in self.all_names}
        for name in list(spec.locked) + spec.coordinate_names + [d for c in spec.coordinates for d in c.coupled]:
            if name not in self.coords:
                raise ConfigError(
                    f"unknown coordinate {name!r} ({closest(name, self.all_names)})",
                    path=spec.path,
                    line=spec.line_of(name),
                    field="locked" if name in spec.locked else "coordinates",
                    value=name,
                )
        self.couplers = []
        cset = model.getConstraintSet()
        for i in range(cset.getSize()):
            ccc = osim.CoordinateCouplerConstraint.safeDownCast(cset.get(i))
            if ccc is None or not ccc.get_isEnforced():
                continue
            names = ccc.getIndependentCoordinateNames()
            indep = [names.get(k) for k in range(names.getSize())]
            self.couplers.append((ccc.getDependentCoordinateName(), indep, ccc.getFunction()))
        self._check_free(spec)
        self._osim = osim
        self.base = {n: self.coords[n].getDefaultValue() for n in self.all_names}
        self.base.update(spec.locked)
        # U index of every coordinate (mobility order differs from the coordinate set order)
        self.u_index = {}
        for name in self.all_names:
            state.updU().setToZero()
            self.coords[name].setSpeedValue(state, 1.0)
            u = state.getU()
            self.u_index[name] = int(np.argmax([abs(u.get(k)) for k in range(u.size())]))
        state.updU().setToZero()

    def _check_free(self, spec: PackSpec) -> None:
        """Every coordinate the spec sets must be one the model lets it set: a coordinate the model locks, or one a
        coupler constraint drives from others, keeps the model's value whatever is asked (a pack coordinate would
        have zero moment arms and torque throughout, a [locked] value would be ignored), without a word."""
        driven = {dependent: independent for dependent, independent, _ in self.couplers}
        listed = [
            *((n, "coordinates") for n in spec.coordinate_names),
            *((n, "locked") for n in spec.locked),
            *((d, f"coordinates.{c.name}.coupled") for c in spec.coordinates for d in c.coupled),
        ]
        for name, where in listed:
            coordinate = self.coords[name]
            if where == "locked" and abs(spec.locked[name] - coordinate.getDefaultValue()) <= LOCKED_MATCH:
                continue  # held where the model holds it anyway
            if coordinate.get_locked():
                why = (
                    f"is locked in the model at {coordinate.getDefaultValue():.6g}: it keeps that value whatever the "
                    "pack asks; unlock it there"
                )
            elif name in driven:
                sources = " and ".join(driven[name])
                why = (
                    f"is driven by a coupler constraint of the model from {sources}: it follows {sources} whatever "
                    f"the pack asks; list {sources} instead"
                )
            else:
                continue
            raise ConfigError(
                f"coordinate {name!r} {why}", path=spec.path, line=spec.line_of(name), field=where, value=name
            )

    def values(self, q: np.ndarray) -> dict[str, float]:
        """All coordinate values for pack pose q."""
        values = dict(self.base)
        for c, v in zip(self.spec.coordinates, q):
            values[c.name] = float(v)
            for dep, ratio in c.coupled.items():
                values[dep] = ratio * float(v)
        for dep, indep, func in self.couplers:
            values[dep] = func.calcValue(self._osim.Vector([values[n] for n in indep]))
        return values

    def set(self, q: np.ndarray) -> None:
        for name, value in self.values(q).items():
            self.coords[name].setValue(self.state, value, False)
        self.model.realizePosition(self.state)

    def coordinate_jacobian(self, q: np.ndarray, delta: float = 1e-6) -> tuple[list[str], np.ndarray]:
        """d(all coordinate values)/d(pack q) by central differences -> (names, (n_all, n))."""
        cols = []
        for j in range(len(q)):
            e = np.zeros(len(q))
            e[j] = delta
            plus, minus = self.values(q + e), self.values(q - e)
            cols.append([(plus[n] - minus[n]) / (2 * delta) for n in self.all_names])
        return self.all_names, np.array(cols).T

    def transforms(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """World rotation and origin of every body (and ground) at the current state."""
        out = {"ground": (np.eye(3), np.zeros(3))}
        bs = self.model.getBodySet()
        for i in range(bs.getSize()):
            body = bs.get(i)
            t = body.getTransformInGround(self.state)
            out[body.getName()] = (_mat(t.R()), np.array(t.p().to_numpy()))
        return out


def muscle_table(model, names: list[str], spec: PackSpec) -> dict[str, dict[str, float]]:
    """Max isometric force, optimal fibre length, tendon slack length and control bounds of each named muscle."""
    muscles = model.getMuscles()
    all_names = [muscles.get(i).getName() for i in range(muscles.getSize())]
    table = {}
    for name in names:
        if name not in all_names:
            raise ConfigError(
                f"unknown muscle {name!r} ({closest(name, all_names)})",
                path=spec.path,
                line=spec.line_of(f'"{name}"'),
                field="groups",
                value=name,
            )
        m = muscles.get(name)
        table[name] = {
            "f_max": m.getMaxIsometricForce(),
            "l_opt": m.getOptimalFiberLength(),
            "l_slack": m.getTendonSlackLength(),
            "min_control": m.getMinControl(),  # OpenSim's StaticOptimization bounds the activation by these
            "max_control": m.getMaxControl(),
        }
    return table


JUMP_TOLERANCE = 1e-3  # m/rad disagreement between forward and backward slopes
#: a [locked] value this close to where the model locks the coordinate is that value (degrees typed to 3 decimals)
LOCKED_MATCH = 1e-4
#: At twice the step a smooth path's second difference is 4 x the first's, a kink's 2 x at the pose (more when the
#: kink lies off it): within this share of the first of 4 x, it is smooth.
SMOOTH_TOLERANCE = 0.5
GLITCH_TOLERANCE = 1e-3  # m: a length this far from the mean of its two neighbours 2e-4 rad apart is an OpenSim glitch


def sample_lengths(
    poser: OsimPoser,
    names: list[str],
    poses: np.ndarray,
    delta: float = 1e-4,
    only: int | None = None,
    progress: Progress | None = None,
    task: str = "OpenSim lengths (poses)",
):
    """Muscle-tendon lengths (S, m) and dl/dq (S, m, n): central differences of OpenSim path lengths (NaN at jumps)."""
    muscles = [poser.model.getMuscles().get(n) for n in names]
    s, n = poses.shape
    lengths = np.empty((s, len(names)))
    derivs = np.full((s, len(names), n), np.nan)

    def read() -> np.ndarray:
        return np.array([m.getLength(poser.state) for m in muscles])

    for i, q in enumerate(counted(poses, progress, task)):
        poser.set(q)
        lengths[i] = centre = read()
        for j in range(n) if only is None else (only,):
            e = np.zeros(n)
            e[j] = delta
            poser.set(q + e)
            plus = read()
            poser.set(q - e)
            minus = read()
            # a path that jumps (wrap-object switch) makes the one-sided slopes disagree: no derivative there
            second = plus - 2 * centre + minus
            jump = np.abs(second) > JUMP_TOLERANCE * delta
            if jump.any():
                # ... but so does a steep smooth path (the 6 coupled lumbar levels of a full-body trunk): its second
                # difference grows with the step squared (x4 at twice the step), a kink's only with the step (x2)
                poser.set(q + 2 * e)
                plus2 = read()
                poser.set(q - 2 * e)
                jump &= ~(np.abs(read() + plus2 - 2 * centre - 4 * second) < SMOOTH_TOLERANCE * np.abs(second))
            derivs[i, :, j] = np.where(jump, np.nan, (plus - minus) / (2 * delta))
            # OpenSim wrapping occasionally fails at an isolated pose (length off by cm): drop that length too
            lengths[i] = np.where(np.abs(plus + minus - 2 * centre) > GLITCH_TOLERANCE, np.nan, lengths[i])
    return lengths, derivs


def opensim_moment_arms(poser: OsimPoser, names: list[str], q: np.ndarray) -> np.ndarray:
    """OpenSim computeMomentArm (m, n) at pack pose q; coupled coordinates contribute ratio x their moment arm."""
    poser.set(q)
    muscles = [poser.model.getMuscles().get(n) for n in names]
    out = np.zeros((len(names), len(q)))
    for j, c in enumerate(poser.spec.coordinates):
        parts = [(c.name, 1.0)] + list(c.coupled.items())
        for coord_name, ratio in parts:
            coord = poser.coords[coord_name]
            for i, m in enumerate(muscles):
                out[i, j] += ratio * m.getGeometryPath().computeMomentArm(poser.state, coord)
    return out


def opensim_lengths(poser: OsimPoser, names: list[str], q: np.ndarray) -> np.ndarray:
    poser.set(q)
    return np.array([poser.model.getMuscles().get(n).getLength(poser.state) for n in names])


def opensim_glitches(poser: OsimPoser, names: list[str], q: np.ndarray, delta: float = 1e-3) -> np.ndarray:
    """Mask (m,) of bundles whose OpenSim path at q disagrees by > 1 mm with the mean of two nearby poses.

    Such isolated wrap failures are OpenSim artefacts (the path a hair away is fine); checks exclude them.
    """
    direction = np.ones(len(q)) * delta
    centre = opensim_lengths(poser, names, q)
    plus = opensim_lengths(poser, names, q + direction)
    minus = opensim_lengths(poser, names, q - direction)
    return np.abs(plus + minus - 2 * centre) > 1e-3


def _subtree(model, top: str) -> list[str]:
    """``top`` and every body distal of it (children through joints, away from ground)."""
    js = model.getJointSet()
    children: dict[str, list[str]] = {}
    for i in range(js.getSize()):
        j = js.get(i)
        children.setdefault(j.getParentFrame().findBaseFrame().getName(), []).append(
            j.getChildFrame().findBaseFrame().getName()
        )
    out, stack = [], [top]
    while stack:
        body = stack.pop()
        out.append(body)
        stack.extend(children.get(body, []))
    return out


HANGING_RESIDUAL_MASS = 1e-9  # kg


def hang_subtrees(model, state, spec: PackSpec) -> dict[str, str]:
    """Reproduce the pack's pendulum assumption (``[dynamics] hanging``) in an OpenSim model (before initSystem).

    Every body of a hanging subtree becomes (nearly) massless; its total mass becomes a point mass welded to the pivot
    body's parent at the pivot (the pivot body's origin at the current pose). Returns hanging body -> the point-mass
    body that carries its load points. ``state`` must be realised to Position (the pose that defines the pivot).
    """
    osim = import_opensim()
    bodies = model.getBodySet()
    redirect: dict[str, str] = {}
    plan = []  # measure every pivot before the first edit invalidates the system
    for pivot in spec.dynamics.hanging:
        members = _subtree(model, pivot)
        mass = sum(bodies.get(b).getMass() for b in members)
        joint = next(
            model.getJointSet().get(i)
            for i in range(model.getJointSet().getSize())
            if model.getJointSet().get(i).getChildFrame().findBaseFrame().getName() == pivot
        )
        parent = bodies.get(joint.getParentFrame().findBaseFrame().getName())
        ground_point = bodies.get(pivot).getPositionInGround(state)
        local = model.getGround().findStationLocationInAnotherFrame(state, ground_point, parent).to_numpy()
        plan.append((pivot, members, mass, parent, local))
    for pivot, members, mass, parent, local in plan:
        for b in members:
            # OpenSim refuses massless leaf bodies: 1 µg (torques ~1e-8 N·m) stands in for zero
            bodies.get(b).setMass(HANGING_RESIDUAL_MASS)
            bodies.get(b).setInertia(osim.Inertia(0.0, 0.0, 0.0))
        name = f"msk_pendulum_{pivot}"
        point_mass = osim.Body(name, mass, osim.Vec3(0.0), osim.Inertia(0.0, 0.0, 0.0))
        model.addBody(point_mass)
        model.addJoint(
            osim.WeldJoint(
                f"{name}_weld", parent, osim.Vec3(*local), osim.Vec3(0.0), point_mass, osim.Vec3(0.0), osim.Vec3(0.0)
            )
        )
        redirect.update({b: name for b in members})
    return redirect


def add_hand_loads(
    model, spec: PackSpec, total_load: float, gravity: np.ndarray, share: float, redirect: dict[str, str] | None = None
) -> None:
    """Constant forces along gravity at the spec's load points (before initSystem), as the pack applies them.

    ``redirect`` (from :func:`hang_subtrees`): load points on hanging bodies act at the pendulum's pivot instead
    (same line of action as the hand hanging plumb below it)."""
    osim = import_opensim()
    points = spec.dynamics.load_points
    if not points:
        return
    redirect = redirect or {}
    unit = gravity / np.linalg.norm(gravity)
    force = unit * share * total_load / len(points)
    for k, lp in enumerate(points):
        body, point = (redirect[lp.body], (0.0, 0.0, 0.0)) if lp.body in redirect else (lp.body, lp.point)
        pf = osim.PrescribedForce(f"msk_hand_load_{k}", model.getBodySet().get(body))
        pf.setForceFunctions(osim.Constant(force[0]), osim.Constant(force[1]), osim.Constant(force[2]))
        pf.setPointFunctions(osim.Constant(point[0]), osim.Constant(point[1]), osim.Constant(point[2]))
        pf.set_forceIsGlobal(True)
        pf.set_pointIsGlobal(False)
        model.addForce(pf)


def opensim_inverse_dynamics(poser: OsimPoser, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
    """OpenSim InverseDynamicsSolver torques projected on the pack coordinates (virtual work through couplings)."""
    osim = poser._osim
    names, jac = poser.coordinate_jacobian(q)
    poser.set(q)
    u_all = jac @ qd
    udot_all = jac @ qdd
    state = poser.state
    nu = state.getNU()
    udot = osim.Vector(nu, 0.0)
    for k, name in enumerate(names):
        poser.coords[name].setSpeedValue(state, float(u_all[k]))
        udot.set(poser.u_index[name], float(udot_all[k]))
    poser.model.realizeVelocity(state)
    solver = osim.InverseDynamicsSolver(poser.model)
    tau = solver.solve(state, udot)
    tau_all = np.array([tau.get(poser.u_index[n]) for n in names])
    for name in names:
        poser.coords[name].setSpeedValue(state, 0.0)
    return jac.T @ tau_all
