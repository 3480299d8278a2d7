"""Extract the reduced rigid-body description of a pack from OpenSim (screw axes at the reference pose).

For every OpenSim joint and pack coordinate, the relative motion child-vs-parent per unit coordinate is measured by
central differences at the reference pose: its instantaneous screw gives the pinocchio joint (point, axis, gain),
exact for constant-axis joints and linear couplings. Joints whose screw changes across the range (the rolling
walker knee, the patella coupler) become a chain of three translations and three rotations, each a polynomial of
the coordinate fitted to OpenSim's relative transforms (``msk model check`` reports the resulting ID error).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from msk_core.errors import ConfigError
from msk_core.model.osim_tools import OsimPoser
from msk_core.model.spec import PackSpec, closest

Graph = list[tuple[str, str, str]]  # (joint name, parent body, child body)
Screws = dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]
Transforms = dict[str, tuple[np.ndarray, np.ndarray]]  # body -> (rotation, origin) in ground


def _log_rotation(r: np.ndarray) -> np.ndarray:
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-12:
        return w / 2
    return w * angle / (2 * np.sin(angle))


def joint_graph(model: Any) -> Graph:
    """(joint name, parent body, child body) for every joint."""
    js = model.getJointSet()
    out = []
    for i in range(js.getSize()):
        j = js.get(i)
        parent, child = j.getParentFrame().findBaseFrame(), j.getChildFrame().findBaseFrame()
        out.append((j.getName(), parent.getName(), child.getName()))
    return out


def _screws(poser: OsimPoser, graph: Graph, delta: float = 1e-5) -> Screws:
    """(joint, coordinate index) -> (omega_world, v_child_origin_world) per unit coordinate, for moving joints."""
    q0 = np.array([c.reference for c in poser.spec.coordinates])
    poser.set(q0)
    t0 = poser.transforms()
    screws = {}
    for k in range(len(q0)):
        e = np.zeros(len(q0))
        e[k] = delta
        poser.set(q0 + e)
        tp = poser.transforms()
        poser.set(q0 - e)
        tm = poser.transforms()
        for name, parent, child in graph:
            rel = {}
            for key, t in (("p", tp), ("m", tm)):
                rp, pp = t[parent]
                rc, pc = t[child]
                rel[key] = (rp.T @ rc, rp.T @ (pc - pp))
            omega_p = _log_rotation(rel["p"][0] @ rel["m"][0].T) / (2 * delta)
            v_p = (rel["p"][1] - rel["m"][1]) / (2 * delta)
            r0 = t0[parent][0]
            omega, v = r0 @ omega_p, r0 @ v_p
            if np.linalg.norm(omega) > 1e-7 or np.linalg.norm(v) > 1e-9:
                screws[(name, k)] = (omega, v)
    poser.set(q0)
    return screws


NONLINEAR_TOLERANCE = 1e-4  # rad or m: screw change across the range beyond which a joint gets the 6-DoF chain
CHAIN_SAMPLES = 61
CHAIN_DEGREE = 8


def _relative(t: Transforms, fixed: str, moving: str) -> tuple[np.ndarray, np.ndarray]:
    rf, pf = t[fixed]
    rm, pm = t[moving]
    return rf.T @ rm, rf.T @ (pm - pf)


def _screw_at(
    poser: OsimPoser, q: np.ndarray, k: int, parent: str, child: str, delta: float = 1e-5
) -> tuple[np.ndarray, np.ndarray]:
    """(axis point, omega) of child vs parent per unit coordinate k at pose q, in the parent's frame."""
    e = np.zeros(len(q))
    e[k] = delta
    poser.set(q + e)
    rp, pp = _relative(poser.transforms(), parent, child)
    poser.set(q - e)
    rm, pm = _relative(poser.transforms(), parent, child)
    poser.set(q)
    r0, p0 = _relative(poser.transforms(), parent, child)
    omega = _log_rotation(rp @ rm.T) / (2 * delta)
    v = (pp - pm) / (2 * delta)
    w = np.linalg.norm(omega)
    if w < 1e-7:
        return np.zeros(3), omega
    return p0 + np.cross(omega, v) / w**2, omega


def _is_nonlinear(poser: OsimPoser, spec: PackSpec, k: int, parent: str, child: str) -> bool:
    """True when the joint's screw (axis, point, rate) changes across coordinate k's range."""
    q0 = np.array([c.reference for c in spec.coordinates])
    c = spec.coordinates[k]
    samples = []
    for value in (c.lower, c.reference, c.upper):
        q = q0.copy()
        q[k] = value
        samples.append(_screw_at(poser, q, k, parent, child))
    poser.set(q0)
    # compare in the parent frame: the rate vector and the axis line (point projected off the axis)
    (p_ref, w_ref) = samples[1]
    for point, omega in (samples[0], samples[2]):
        if np.linalg.norm(omega - w_ref) > NONLINEAR_TOLERANCE:
            return True
        if np.linalg.norm(w_ref) > 1e-7:
            u = w_ref / np.linalg.norm(w_ref)
            d = point - p_ref
            if np.linalg.norm(d - u * (u @ d)) > NONLINEAR_TOLERANCE:
                return True
    return False


def _euler_xyz(r: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) with r = Rx(a) Ry(b) Rz(c)."""
    b = np.arcsin(np.clip(r[0, 2], -1.0, 1.0))
    return np.array([np.arctan2(-r[1, 2], r[2, 2]), b, np.arctan2(-r[0, 1], r[0, 0])])


def _chain(poser: OsimPoser, spec: PackSpec, k: int, fixed: str, moving: str) -> tuple[np.ndarray, list[dict]]:
    """Exact 1-coordinate joint as x, y, z translations then X, Y, Z rotations (world-aligned at the reference,
    through the moving body's origin), each a degree-8 polynomial of the coordinate. Returns (origin, functions)."""
    q0 = np.array([c.reference for c in spec.coordinates])
    c = spec.coordinates[k]
    poser.set(q0)
    t0 = poser.transforms()
    rf0 = t0[fixed][0]
    rel_r0, rel_p0 = _relative(t0, fixed, moving)
    values = np.linspace(c.lower, c.upper, CHAIN_SAMPLES)
    dof_rows = []
    for value in values:
        q = q0.copy()
        q[k] = value
        poser.set(q)
        rel_r, rel_p = _relative(poser.transforms(), fixed, moving)
        d = rf0 @ (rel_p - rel_p0)
        dr = rf0 @ rel_r @ rel_r0.T @ rf0.T
        dof_rows.append(np.concatenate([d, _euler_xyz(dr)]))
    poser.set(q0)
    dofs = np.unwrap(np.array(dof_rows), axis=0)
    centre, half = (c.upper + c.lower) / 2 - c.reference, (c.upper - c.lower) / 2
    x = (values - c.reference - centre) / half
    vander = x[:, None] ** np.arange(CHAIN_DEGREE + 1)[None, :]
    functions = []
    for j in range(6):
        coef, *_ = np.linalg.lstsq(vander, dofs[:, j], rcond=None)
        coef[0] -= np.polynomial.polynomial.polyval(-centre / half, coef)  # exactly the reference pose at q_ref
        functions.append(
            {
                "coordinate": k,
                "centre": centre,
                "half_width": half,
                "coefficients": coef.tolist(),
                "fit_max_error": float(np.max(np.abs(vander @ coef - dofs[:, j]))),
            }
        )
    return t0[moving][1], functions


def extract_rigid(
    poser: OsimPoser,
    spec: PackSpec,
    *,
    root: str,
    exclude: tuple[str, ...],
    shared_from: str,
    gravity: np.ndarray,
    load_share: float,
) -> dict:
    """Rigid-body description (see :class:`msk_core.model.rigid.RigidModel`) rooted at ``root``."""
    model = poser.model
    graph = joint_graph(model)
    bodies = {"ground"} | {b for _, p, c in graph for b in (p, c)}
    hanging = tuple(spec.dynamics.hanging)
    _check_bodies(spec, bodies, root, shared_from, exclude)
    screws = _screws(poser, graph)
    q0 = np.array([c.reference for c in spec.coordinates])
    poser.set(q0)
    scene = _Scene(poser, spec, graph, screws, poser.transforms())
    tree = _walk(scene, bodies, root=root, exclude=exclude, shared_from=shared_from, hanging=hanging)
    share = load_share if shared_from else 1.0
    body_list = _body_entries(model, tree, scene.t0, share)
    loads = [load for load in _load_entries(spec, tree, scene.t0) if load["joint"] >= 0]
    torque_scale = _torque_scale(spec, tree, shared_from, share)
    joints, n = tree.joints, len(spec.coordinates)
    gain_matrix = np.array([j.pop("gains_row") for j in joints]).reshape(len(joints), n)
    return {
        "root": root,
        "joints": joints,
        "bodies": body_list,
        "load_points": loads,
        "gravity": np.asarray(gravity, dtype=float).tolist(),
        "load_share": load_share,
        "gains": gain_matrix.tolist(),
        "torque_scale": torque_scale.tolist(),
    }


def _unknown_body(spec: PackSpec, name: str, bodies: set[str], field: str) -> ConfigError:
    return ConfigError(
        f"unknown body {name!r} ({closest(name, sorted(bodies))})",
        path=spec.path,
        line=spec.line_of(name),
        field=field,
        value=name,
    )


def _check_bodies(spec: PackSpec, bodies: set[str], root: str, shared_from: str, exclude: tuple[str, ...]) -> None:
    """Every body the spec names (root, shared_from, excluded, hanging, load points) is one of the model's."""
    for name, field in (
        [(root, "dynamics.root"), (shared_from, "dynamics.shared_from")]
        + [(b, "dynamics.exclude_bodies") for b in exclude]
        + [(b, "dynamics.hanging") for b in spec.dynamics.hanging]
    ):
        if name and name not in bodies:
            raise _unknown_body(spec, name, bodies, field)
    for lp in spec.dynamics.load_points:
        if lp.body not in bodies:
            raise _unknown_body(spec, lp.body, bodies, "dynamics.load_points")


@dataclass(frozen=True)
class _Scene:
    """What the tree walk reads: the model posed by ``poser``, its joint graph, screws and reference transforms."""

    poser: OsimPoser
    spec: PackSpec
    graph: Graph
    screws: Screws
    t0: Transforms


class _Tree:
    """The reduced model grown breadth-first from the root: its joints, the joint each body rides on, which bodies
    are shared (distal to ``shared_from``) and which hang from a pivot."""

    def __init__(self, root: str, shared_from: str) -> None:
        self.shared_from = shared_from
        self.attach: dict[str, int] = {root: -1}  # body -> pinocchio joint index it rides on (-1: fixed to the root)
        self.in_shared: dict[str, bool] = {root: root == shared_from}
        self.pivot_of: dict[str, str] = {}  # body of a hanging subtree -> the body whose origin it hangs from
        self.joints: list[dict] = []
        self.joint_distal_shared: list[bool] = []

    def add_joint(self, joint: dict, body: str) -> int:
        """Append a joint distal to ``body``; returns its index (the parent of the next one)."""
        self.joints.append(joint)
        self.joint_distal_shared.append(self.in_shared[body])
        return len(self.joints) - 1

    def attach_body(self, other: str, body: str, joint: int) -> None:
        """``other``, reached from ``body``, rides on ``joint``."""
        self.attach[other] = joint
        self.in_shared[other] = self.in_shared[body] or other == self.shared_from


def _walk(
    scene: _Scene, bodies: set[str], *, root: str, exclude: tuple[str, ...], shared_from: str, hanging: tuple[str, ...]
) -> _Tree:
    """Breadth-first tree from the root: the joints between each body and the next."""
    adjacency: dict[str, list[tuple[str, str, bool]]] = {b: [] for b in bodies}
    for name, parent, child in scene.graph:
        adjacency[parent].append((child, name, False))
        adjacency[child].append((parent, name, True))  # traversed child -> parent: motion reversed
    tree = _Tree(root, shared_from)
    queue = deque([root])
    while queue:
        body = queue.popleft()
        for other, jname, reversed_ in adjacency[body]:
            if other in tree.attach or other in exclude:
                continue
            current = tree.attach[body]
            pivot = tree.pivot_of.get(body) or (other if other in hanging else None)
            if pivot is not None:
                # a pendulum: no joints, it rides on the pivot's parent as a point mass at the pivot
                tree.pivot_of[other] = pivot
            else:
                current = _add_joints(scene, tree, body, other, jname, reversed_, current)
            tree.attach_body(other, body, current)
            queue.append(other)
    return tree


def _add_joints(scene: _Scene, tree: _Tree, body: str, other: str, jname: str, reversed_: bool, current: int) -> int:
    """The pinocchio joints of OpenSim joint ``jname`` (from ``body`` to ``other``), one per pack coordinate that
    moves it (a 6-joint chain where its screw changes across the range). Returns the last joint's index."""
    spec, screws = scene.spec, scene.screws
    parent, child = _joint_ends(scene.graph, jname)
    for k in range(len(spec.coordinates)):
        if (jname, k) not in screws:
            continue
        if _is_nonlinear(scene.poser, spec, k, parent, child):
            movers = [spec.coordinates[kk].name for kk in range(len(spec.coordinates)) if (jname, kk) in screws]
            if len(movers) > 1:
                # the polynomial chain replays one coordinate's path; two would need a 2-D surface
                raise ConfigError(
                    f"joint {jname!r} has a moving axis and is driven by several pack "
                    f"coordinates {movers}; lock all but one",
                    path=spec.path,
                    field="coordinates",
                    value=movers,
                )
            current = _add_chain(scene, tree, body, other, jname, k, current)
            continue
        sign = -1.0 if reversed_ else 1.0
        joint = _screw_joint(spec, jname, k, screws[(jname, k)], sign, scene.t0[child][1], current)
        current = tree.add_joint(joint, body)
    return current


def _add_chain(scene: _Scene, tree: _Tree, body: str, other: str, jname: str, k: int, current: int) -> int:
    """The 6-joint polynomial chain (x, y, z translations, X, Y, Z rotations) of a joint with a moving axis."""
    spec = scene.spec
    origin, functions = _chain(scene.poser, spec, k, body, other)
    axes = np.eye(3)
    for j, function in enumerate(functions):
        joint = {
            "name": f"{jname}:{spec.coordinates[k].name}:{'xyzXYZ'[j]}",
            "parent": current,
            "position": origin.tolist(),
            "axis": axes[j % 3].tolist(),
            "kind": "prismatic" if j < 3 else "revolute",
            "gains_row": [0.0] * len(spec.coordinates),
            "function": function,
        }
        current = tree.add_joint(joint, body)
    return current


def _screw_joint(
    spec: PackSpec,
    jname: str,
    k: int,
    screw: tuple[np.ndarray, np.ndarray],
    sign: float,
    child_origin: np.ndarray,
    parent: int,
) -> dict:
    """The revolute (or, without rotation, prismatic) joint of coordinate k's constant screw, riding on joint
    ``parent``. The axis line of a pure translation may pass anywhere: it is put through the child's origin."""
    omega, v = screw
    w = np.linalg.norm(omega)
    gains = np.zeros(len(spec.coordinates))
    if w > 1e-7:
        point = child_origin + np.cross(omega, v) / w**2
        axis, kind, gains[k] = sign * omega / w, "revolute", w
    else:
        point = child_origin
        axis, kind, gains[k] = sign * v / np.linalg.norm(v), "prismatic", np.linalg.norm(v)
    return {
        "name": f"{jname}:{spec.coordinates[k].name}",
        "parent": parent,
        "position": point.tolist(),
        "axis": axis.tolist(),
        "kind": kind,
        "gains_row": gains.tolist(),
    }


def _body_entries(model: Any, tree: _Tree, t0: Transforms, share: float) -> list[dict]:
    """Mass, centre of mass and inertia (ground frame, reference pose) of every body that moves with a joint; shared
    bodies scaled by ``share``; hanging ones as point masses at their pivot."""
    body_list = []
    bs = model.getBodySet()
    for i in range(bs.getSize()):
        b = bs.get(i)
        name = b.getName()
        if tree.attach.get(name, -1) < 0:
            continue  # fixed to the root (or excluded): no effect on any pack torque
        r0, p0 = t0[name]
        inertia = b.getInertia()
        mom, prod = inertia.getMoments().to_numpy(), inertia.getProducts().to_numpy()
        i_body = np.array([[mom[0], prod[0], prod[1]], [prod[0], mom[1], prod[2]], [prod[1], prod[2], mom[2]]])
        scale = share if tree.in_shared[name] else 1.0
        entry = {
            "name": name,
            "joint": tree.attach[name],
            "mass": scale * b.getMass(),
            "com": (r0 @ b.getMassCenter().to_numpy() + p0).tolist(),
            "inertia": (scale * r0 @ i_body @ r0.T).tolist(),
        }
        if name in tree.pivot_of:  # hanging plumb: its weight acts through the pivot (point mass, no rotary inertia)
            pivot = tree.pivot_of[name]
            entry.update(com=t0[pivot][1].tolist(), inertia=np.zeros((3, 3)).tolist(), hanging_from=pivot)
        body_list.append(entry)
    return body_list


def _load_entries(spec: PackSpec, tree: _Tree, t0: Transforms) -> list[dict]:
    """Every load point in ground coordinates at the reference pose, with the joint it rides on (-1: the root)."""
    loads = []
    for lp in spec.dynamics.load_points:
        r0, p0 = t0[lp.body]
        point = r0 @ np.array(lp.point) + p0
        load = {"body": lp.body, "joint": tree.attach.get(lp.body, -1), "point": point.tolist()}
        if lp.body in tree.pivot_of:  # held in a hanging hand: same line of action as a force at the pivot
            load.update(point=t0[tree.pivot_of[lp.body]][1].tolist(), hanging_from=tree.pivot_of[lp.body])
        loads.append(load)
    return loads


def _torque_scale(spec: PackSpec, tree: _Tree, shared_from: str, share: float) -> np.ndarray:
    """Per coordinate, 1 / share where it moves only shared bodies (their torque is reported for the whole), else 1;
    a coordinate moving joints on both sides of ``shared_from`` is refused."""
    n = len(spec.coordinates)
    torque_scale = np.ones(n)
    if not shared_from:
        return torque_scale
    for k in range(n):
        sides = {
            tree.joint_distal_shared[i]
            for i, j in enumerate(tree.joints)
            if j["gains_row"][k] != 0 or j.get("function", {}).get("coordinate") == k
        }
        if sides == {True}:
            torque_scale[k] = 1.0 / share
        elif len(sides) > 1:
            raise ConfigError(
                f"coordinate {spec.coordinates[k].name!r} moves joints on both sides of shared_from={shared_from!r}",
                path=spec.path,
                field="dynamics.shared_from",
            )
    return torque_scale


def _joint_ends(graph: Graph, jname: str) -> tuple[str, str]:
    """(parent body, child body) of joint ``jname``."""
    for name, parent, child in graph:
        if name == jname:
            return parent, child
    raise KeyError(jname)
