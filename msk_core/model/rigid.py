"""Reduced rigid-body model of a pack, rebuilt with pinocchio from the description stored in the pack.

Every joint frame is aligned with the OpenSim ground frame at the pack's reference pose, so a stored joint is just a
point, an axis and its gains (joint angle = gains · (q - q_ref)): linear couplings (lumbar levels following the
driver coordinate) become several pinocchio joints sharing one pack coordinate, and torques are projected back with
the transposed gains (virtual work).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

from msk_core.errors import ModelError

if TYPE_CHECKING:  # the module itself is imported lazily (numba): see compiled_kernels
    from msk_core.model.kernels import RigidTables


def compiled_kernels() -> ModuleType:
    """:mod:`msk_core.model.kernels`, imported (numba with it, ~0.5 s) only when a compiled evaluator is asked for."""
    try:
        kernels = importlib.import_module("msk_core.model.kernels")
    except ImportError as exc:
        raise ModelError(
            f"the compiled model evaluator needs numba ({exc}); install numba or use the numpy evaluator"
        ) from exc
    return kernels


def _pinocchio_model(joints: list[dict], bodies: list[dict]) -> tuple[pin.Model, list[np.ndarray]]:
    """The joint tree (every joint frame aligned with ground, at its stored point) carrying the bodies' inertias;
    also the joints' points."""
    model = pin.Model()
    positions = [np.asarray(j["position"], dtype=float) for j in joints]
    for i, (j, pos) in enumerate(zip(joints, positions)):
        parent = int(j["parent"])
        parent_pos = positions[parent] if parent >= 0 else np.zeros(3)
        axis = np.asarray(j["axis"], dtype=float)
        if j["kind"] == "revolute":
            jm = pin.JointModelRevoluteUnaligned(axis)
        elif j["kind"] == "prismatic":
            jm = pin.JointModelPrismaticUnaligned(axis)
        else:
            raise ModelError(
                f"rigid model: joint {j['name']!r} (dynamics.joints[{i}].kind) is {j['kind']!r}; "
                "expected 'revolute' or 'prismatic'"
            )
        model.addJoint(parent + 1, jm, pin.SE3(np.eye(3), pos - parent_pos), j["name"])
    for body in bodies:
        joint = int(body["joint"])
        origin = positions[joint]
        inertia = pin.Inertia(
            float(body["mass"]),
            np.asarray(body["com"], dtype=float) - origin,
            np.asarray(body["inertia"], dtype=float).reshape(3, 3),
        )
        model.appendBodyToJoint(joint + 1, inertia, pin.SE3.Identity())
    return model, positions


def _load_model(model: pin.Model, load_points: list[dict], positions: list[np.ndarray]) -> pin.Model:
    """Hand load: the same tree carrying only unit point masses at the load points; its generalized gravity is the
    torque that holds 1 kg at every load point (one cheap call instead of a Jacobian per point)."""
    load_model = pin.Model(model)
    for k in range(1, load_model.njoints):
        load_model.inertias[k] = pin.Inertia.Zero()
    for load in load_points:
        joint = int(load["joint"])
        point = np.asarray(load["point"], dtype=float) - positions[joint]
        load_model.appendBodyToJoint(joint + 1, pin.Inertia(1.0, point, np.zeros((3, 3))), pin.SE3.Identity())
    return load_model


class RigidModel:
    """Pinocchio model + projection between pack coordinates and pinocchio joints."""

    def __init__(self, description: dict, *, n_coordinates: int, compiled: bool = False) -> None:
        """compiled: evaluate with the numba kernels (:mod:`msk_core.model.kernels`) instead of numpy + pinocchio."""
        self.description = description
        joints = description["joints"]
        model, positions = _pinocchio_model(joints, description["bodies"])
        load_model = _load_model(model, description["load_points"], positions)
        self.n_load_points = len(description["load_points"])
        self.gravity = np.asarray(description["gravity"], dtype=float)
        self._g_norm = float(np.linalg.norm(self.gravity))
        model.gravity.linear = self.gravity
        load_model.gravity.linear = self.gravity
        self.model, self.load_model = model, load_model
        self.data, self.load_data = model.createData(), load_model.createData()
        self.gains = np.asarray(description["gains"], dtype=float).reshape(len(joints), n_coordinates)
        self.torque_scale = np.asarray(description["torque_scale"], dtype=float)
        self.load_share = float(description["load_share"])
        self._projection = self.gains.T * self.torque_scale[:, None]  # (n_coordinates, n_joints)
        n_joints = len(joints)
        self._gains_t = np.ascontiguousarray(self.gains.T)  # (n_coordinates, n_joints)
        self._motion_in = np.zeros((3, n_coordinates))  # rows dq, qd, qdd (preallocated: one matmul per frame)
        self._motion = np.zeros((3, n_joints))  # rows: pinocchio q, v, a (contiguous rows for pinocchio)
        # projection back to the coordinates; the columns of polynomial joints are refreshed with f'(q) each frame
        self._frame_projection = self._projection.copy()
        # joints whose value is a polynomial of one coordinate (rolling knee, patella): q_j = f(dq_k), grouped by
        # coordinate so each group costs one power vector and one small matrix product per call
        self._nl_groups = [
            self._polynomial_group(k, joints)
            for k in sorted({j["function"]["coordinate"] for j in joints if "function" in j})
        ]
        self._load_factor = self.load_share / max(self.n_load_points, 1) / (self._g_norm or 1.0)
        self._scaled_load: float | None = None  # hand load the load model's gravity is currently scaled for
        self.joint_names = [j["name"] for j in joints]
        moved_by = [
            j["function"]["coordinate"] if "function" in j else int(np.argmax(np.abs(self.gains[i])))
            for i, j in enumerate(joints)
        ]
        self._joint_scale = self.torque_scale[moved_by]
        self._kernels = compiled_kernels() if compiled else None
        self.tables: RigidTables | None = None if self._kernels is None else self._tables(self._kernels, joints)

    def _polynomial_group(self, k: int, joints: list[dict]) -> tuple[Any, ...]:
        """The per-frame state of coordinate k's polynomial joints, as the tuple :meth:`_joint_motion` unpacks
        (a tuple, unpacked once per frame, is cheaper than dict look-ups on the hot path)."""
        idx = [i for i, j in enumerate(joints) if j.get("function", {}).get("coordinate") == k]
        funcs = [joints[i]["function"] for i in idx]
        coef = np.array([f["coefficients"] for f in funcs], dtype=float)
        degree = coef.shape[1]
        d1 = coef[:, 1:] * np.arange(1, degree)[None, :]
        d2 = d1[:, 1:] * np.arange(1, degree - 1)[None, :]
        half, centre = float(funcs[0]["half_width"]), float(funcs[0]["centre"])
        m = len(idx)
        scale = float(self.torque_scale[k])
        # rows: f, f', f'' and scale * f' (the projection column) over the same power vector
        stacked = np.zeros((4 * m, degree))
        stacked[:m] = coef
        stacked[m : 2 * m, : degree - 1] = d1 / half
        stacked[2 * m : 3 * m, : degree - 2] = d2 / half**2
        stacked[3 * m :, : degree - 1] = scale * d1 / half
        contiguous = idx == list(range(idx[0], idx[0] + m))
        sel = slice(idx[0], idx[0] + m) if contiguous else np.array(idx)
        mix = np.zeros((3, 3))  # [f, f'v, f'a + f''v²] = mix @ [f, f', f'']: one product per frame
        mix[0, 0] = 1.0
        values = np.empty(4 * m)  # preallocated product: its views below need no per-frame slicing
        return (
            k,
            sel,
            m,
            centre,
            1.0 / half,
            stacked,
            np.arange(degree).astype(float),
            np.empty(degree),
            mix,
            self._motion[:, sel] if contiguous else None,
            self._frame_projection[k, sel] if contiguous else None,
            values,
            values[: 3 * m].reshape(3, m),
            values[3 * m :],
        )

    @property
    def compiled_tables(self) -> RigidTables:
        """:attr:`tables`, which only a model built with ``compiled=True`` has."""
        if self.tables is None:
            raise ModelError("rigid model: built with compiled=False, it has no compiled tables")
        return self.tables

    def _tables(self, kernels: ModuleType, joints: list[dict]) -> RigidTables:
        """The compiled kernels' view of this model: read back from the pinocchio models (same placements and
        aggregated inertias), plus the polynomial joints."""
        n_joints = len(joints)
        joint_int = np.zeros((n_joints, 3), dtype=np.int64)
        joint_float = np.zeros((n_joints, kernels.JOINT_FLOAT_COLUMNS))
        width = max([len(j["function"]["coefficients"]) for j in joints if "function" in j], default=1)
        poly_coef = np.zeros((n_joints, width))
        for i, joint in enumerate(joints):
            placement = self.model.jointPlacements[i + 1]
            if not np.array_equal(placement.rotation, np.eye(3)) or int(self.model.parents[i + 1]) >= i + 1:
                parent = int(self.model.parents[i + 1]) - 1
                raise ModelError(
                    f"rigid model: joint {joint['name']!r} (dynamics.joints[{i}]) needs an unrotated "
                    f"placement and a parent listed before it (parent {parent}); the compiled evaluator "
                    "reads the tree in that order"
                )
            joint_int[i, kernels.PARENT] = int(joint["parent"])
            joint_int[i, kernels.KIND] = kernels.REVOLUTE if joint["kind"] == "revolute" else kernels.PRISMATIC
            row = joint_float[i]
            row[kernels.OFFSET : kernels.OFFSET + 3] = placement.translation
            row[kernels.AXIS : kernels.AXIS + 3] = np.asarray(joint["axis"], dtype=float)
            body, load = self.model.inertias[i + 1], self.load_model.inertias[i + 1]
            row[kernels.MASS] = body.mass
            row[kernels.LEVER : kernels.LEVER + 3] = body.lever
            row[kernels.INERTIA : kernels.INERTIA + 9] = np.asarray(body.inertia).reshape(9)
            row[kernels.LOAD_MASS] = load.mass
            row[kernels.LOAD_LEVER : kernels.LOAD_LEVER + 3] = load.lever
            function = joint.get("function")
            if function is None:
                joint_int[i, kernels.POLY_COORD] = -1
                continue
            k = int(function["coordinate"])
            joint_int[i, kernels.POLY_COORD] = k
            row[kernels.POLY_CENTRE] = float(function["centre"])
            row[kernels.POLY_HALF] = float(function["half_width"])
            row[kernels.POLY_SCALE] = float(self.torque_scale[k])
            coef = np.asarray(function["coefficients"], dtype=float)
            poly_coef[i, : len(coef)] = coef
        return kernels.RigidTables.build(
            joint_int=joint_int,
            joint_float=joint_float,
            poly_coef=poly_coef,
            gains=np.ascontiguousarray(self.gains),
            projection=np.ascontiguousarray(self._projection),
            load_per_point=self.load_share / self.n_load_points if self.n_load_points else 0.0,
        )

    def _compiled(self, dq, qd, qdd, hand_load: float, gravity) -> tuple[np.ndarray, np.ndarray]:
        t, kernels = self.tables, self._kernels
        if t is None or kernels is None:
            raise ModelError("rigid model: built with compiled=False, it has no compiled evaluator")
        n = t.n
        dq, qd, qdd = (np.ascontiguousarray(a, dtype=np.float64) for a in (dq, qd, qdd))
        if dq.shape != (n,) or qd.shape != (n,) or qdd.shape != (n,):
            bad, value = next((name, a) for name, a in zip(("dq", "qd", "qdd"), (dq, qd, qdd)) if a.shape != (n,))
            raise ModelError(f"rigid model: {bad} must have shape ({n},) (one value per coordinate), got {value.shape}")
        g = self.gravity if gravity is None else np.ascontiguousarray(gravity, dtype=np.float64)
        if g.shape != (3,):
            raise ModelError(f"rigid model: gravity must be a 3-vector (m/s²), got shape {g.shape}")
        out = np.empty(n + t.n_joints)
        kernels.rigid(dq, qd, qdd, float(hand_load), g, t.ints, t.floats, out)
        return out[:n], out[n:]

    def _joint_motion(self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> np.ndarray:
        """Pinocchio q, v, a as the rows of the (3, n_joints) motion buffer; refreshes the frame projection."""
        motion_in = self._motion_in
        motion_in[0] = dq
        motion_in[1] = qd
        motion_in[2] = qdd
        motion = np.dot(motion_in, self._gains_t, out=self._motion)
        for (
            k,
            idx,
            _m,
            centre,
            inv_half,
            stacked,
            powers,
            power_buf,
            mix,
            motion_view,
            projection_view,
            values,
            f_rows,
            slope,
        ) in self._nl_groups:
            dq_k, v, a = motion_in[:, k].tolist()
            np.dot(stacked, np.power((dq_k - centre) * inv_half, powers, out=power_buf), out=values)
            mix[1, 1] = v
            mix[2, 1] = a
            mix[2, 2] = v * v
            if motion_view is not None and projection_view is not None:  # views of a contiguous group's columns
                np.matmul(mix, f_rows, out=motion_view)
                # virtual work: tau_k += f'(q) . tau_j, folded into the projection matrix
                projection_view[...] = slope
            else:
                motion[:, idx] = mix @ f_rows
                self._frame_projection[k, idx] = slope
        return motion

    def inverse_dynamics(
        self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float, gravity: np.ndarray | None
    ) -> np.ndarray:
        """Torques at pack coordinates for offsets dq = q - q_ref, velocities and accelerations."""
        if self.tables is None:
            return self.inverse_dynamics_numpy(dq, qd, qdd, hand_load, gravity)
        return self._compiled(dq, qd, qdd, hand_load, gravity)[0]

    def inverse_dynamics_numpy(
        self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float, gravity: np.ndarray | None
    ) -> np.ndarray:
        """:meth:`inverse_dynamics` with numpy + pinocchio (the numpy evaluator; the benchmark's baseline)."""
        motion = self._joint_motion(dq, qd, qdd)
        qp, vp, ap = motion
        if gravity is None:
            tau = pin.rnea(self.model, self.data, qp, vp, ap)
            if hand_load and self.n_load_points:
                tau += self._load_torque(hand_load, qp)
            return self._frame_projection @ tau
        g = np.asarray(gravity, dtype=float)
        self._scaled_load = None  # the load model's gravity is reset below
        self.model.gravity.linear = g
        self.load_model.gravity.linear = g
        try:
            tau = pin.rnea(self.model, self.data, qp, vp, ap)
            if hand_load and self.n_load_points:
                # along the given gravity, still hand_load newtons
                factor = self.load_share / self.n_load_points / float(np.linalg.norm(g))
                tau = tau + (hand_load * factor) * pin.computeGeneralizedGravity(self.load_model, self.load_data, qp)
        finally:
            self.model.gravity.linear = self.gravity
            self.load_model.gravity.linear = self.gravity
        return self._frame_projection @ tau

    def joint_torques(self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float) -> np.ndarray:
        """Net torque (or force) about each reduced-model joint (n_joints,), before the virtual-work projection.

        Scaled like the coordinate it moves (torque_scale: e.g. a lumbar level of a foot-rooted, side-shared model
        reports the whole-trunk moment), so e.g. the L5/S1 level moment of a coupled lumbar spine can be read."""
        if self.tables is not None:
            return self._compiled(dq, qd, qdd, hand_load, None)[1] * self._joint_scale
        qp, vp, ap = self._joint_motion(dq, qd, qdd)
        tau = pin.rnea(self.model, self.data, qp, vp, ap).copy()
        if hand_load and self.n_load_points:
            tau += self._load_torque(hand_load, qp)
        return tau * self._joint_scale

    def _load_torque(self, hand_load: float, qp: np.ndarray) -> np.ndarray:
        """Torque holding hand_load newtons along the pack gravity, split over the load points.

        The load model carries unit masses; its gravity is pre-scaled by hand_load / |g| / points and rescaled only
        when the load changes (a live stream keeps one load for many frames): one pinocchio call per frame."""
        if hand_load != self._scaled_load:
            self.load_model.gravity.linear = self.gravity * (hand_load * self._load_factor)
            self._scaled_load = hand_load
        return pin.computeGeneralizedGravity(self.load_model, self.load_data, qp)

    def body_masses(self) -> dict[str, float]:
        return {b["name"]: float(b["mass"]) for b in self.description["bodies"]}
