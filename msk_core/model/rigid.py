"""Reduced rigid-body model of a pack, rebuilt with pinocchio from the description stored in the pack.

Every joint frame is aligned with the OpenSim ground frame at the pack's reference pose, so a stored joint is just a
point, an axis and its gains (joint angle = gains · (q - q_ref)): linear couplings (lumbar levels following the
driver coordinate) become several pinocchio joints sharing one pack coordinate, and torques are projected back with
the transposed gains (virtual work).
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin


class RigidModel:
    """Pinocchio model + projection between pack coordinates and pinocchio joints."""

    def __init__(self, description: dict, *, n_coordinates: int) -> None:
        self.description = description
        model = pin.Model()
        joints = description["joints"]
        positions = [np.asarray(j["position"], dtype=float) for j in joints]
        for j, pos in zip(joints, positions):
            parent = int(j["parent"])
            parent_pos = positions[parent] if parent >= 0 else np.zeros(3)
            axis = np.asarray(j["axis"], dtype=float)
            if j["kind"] == "revolute":
                jm = pin.JointModelRevoluteUnaligned(axis)
            elif j["kind"] == "prismatic":
                jm = pin.JointModelPrismaticUnaligned(axis)
            else:
                raise ValueError(f"unknown joint kind {j['kind']!r}")
            model.addJoint(parent + 1, jm, pin.SE3(np.eye(3), pos - parent_pos), j["name"])
        for body in description["bodies"]:
            joint = int(body["joint"])
            origin = positions[joint]
            inertia = pin.Inertia(
                float(body["mass"]),
                np.asarray(body["com"], dtype=float) - origin,
                np.asarray(body["inertia"], dtype=float).reshape(3, 3),
            )
            model.appendBodyToJoint(joint + 1, inertia, pin.SE3.Identity())
        # Hand load: the same tree carrying only unit point masses at the load points; its generalized gravity is
        # the torque that holds 1 kg at every load point (one cheap call instead of a Jacobian per point).
        load_model = pin.Model(model)
        for k in range(1, load_model.njoints):
            load_model.inertias[k] = pin.Inertia.Zero()
        self.n_load_points = len(description["load_points"])
        for load in description["load_points"]:
            joint = int(load["joint"])
            point = np.asarray(load["point"], dtype=float) - positions[joint]
            load_model.appendBodyToJoint(joint + 1, pin.Inertia(1.0, point, np.zeros((3, 3))), pin.SE3.Identity())
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
        # joints whose value is a polynomial of one coordinate (rolling knee, patella): q_j = f(dq_k), grouped by
        # coordinate so each group costs one power vector and three small matrix products per call
        self._nl_groups = []
        for k in sorted({j["function"]["coordinate"] for j in joints if "function" in j}):
            idx = [i for i, j in enumerate(joints) if j.get("function", {}).get("coordinate") == k]
            funcs = [joints[i]["function"] for i in idx]
            coef = np.array([f["coefficients"] for f in funcs], dtype=float)
            degree = coef.shape[1]
            d1 = coef[:, 1:] * np.arange(1, degree)[None, :]
            d2 = d1[:, 1:] * np.arange(1, degree - 1)[None, :]
            half, centre = float(funcs[0]["half_width"]), float(funcs[0]["centre"])
            m = len(idx)
            stacked = np.zeros((3 * m, degree))  # rows: f, f', f'' over the same power vector
            stacked[:m] = coef
            stacked[m : 2 * m, : degree - 1] = d1 / half
            stacked[2 * m :, : degree - 2] = d2 / half**2
            contiguous = idx == list(range(idx[0], idx[0] + m))
            self._nl_groups.append({
                "k": k, "idx": slice(idx[0], idx[0] + m) if contiguous else np.array(idx), "m": m,
                "centre": centre, "inv_half": 1.0 / half,
                "stacked": stacked, "powers": np.arange(degree).astype(float),
                "scale": float(self.torque_scale[k]),
            })
        self._load_factor = self.load_share / max(self.n_load_points, 1) / (self._g_norm or 1.0)
        self.joint_names = [j["name"] for j in joints]
        moved_by = [j["function"]["coordinate"] if "function" in j else int(np.argmax(np.abs(self.gains[i])))
                    for i, j in enumerate(joints)]
        self._joint_scale = self.torque_scale[moved_by]

    def _joint_motion(self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray):
        """Pinocchio q, v, a and the per-group derivatives f'(q) needed to project torques back."""
        gains = self.gains
        qp, vp, ap = gains @ dq, gains @ qd, gains @ qdd
        slopes = []
        for grp in self._nl_groups:
            k = grp["k"]
            x = (float(dq[k]) - grp["centre"]) * grp["inv_half"]
            values = grp["stacked"] @ np.power(x, grp["powers"])
            m = grp["m"]
            d1, d2 = values[m : 2 * m], values[2 * m :]
            v, a = float(qd[k]), float(qdd[k])
            idx = grp["idx"]
            qp[idx] = values[:m]
            vp[idx] = d1 * v
            ap[idx] = d1 * a + d2 * (v * v)
            slopes.append(d1)
        return qp, vp, ap, slopes

    def _project(self, tau: np.ndarray, slopes: list) -> np.ndarray:
        out = self._projection @ tau
        for grp, d1 in zip(self._nl_groups, slopes):
            out[grp["k"]] += grp["scale"] * (d1 @ tau[grp["idx"]])  # virtual work: tau_k += f'(q) . tau_j
        return out

    def inverse_dynamics(
        self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float, gravity: np.ndarray | None
    ) -> np.ndarray:
        """Torques at pack coordinates for offsets dq = q - q_ref, velocities and accelerations."""
        qp, vp, ap, slopes = self._joint_motion(dq, qd, qdd)
        if gravity is None:
            tau = pin.rnea(self.model, self.data, qp, vp, ap)
            if hand_load and self.n_load_points:
                # hand_load acts along gravity: hold (hand_load / |g|) kg, split over the load points
                tau = tau + (hand_load * self._load_factor) * pin.computeGeneralizedGravity(
                    self.load_model, self.load_data, qp)
            return self._project(tau, slopes)
        g = np.asarray(gravity, dtype=float)
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
        return self._project(tau, slopes)

    def joint_torques(self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float) -> np.ndarray:
        """Net torque (or force) about each reduced-model joint (n_joints,), before the virtual-work projection.

        Scaled like the coordinate it moves (torque_scale: e.g. a lumbar level of a foot-rooted, side-shared model
        reports the whole-trunk moment), so e.g. the L5/S1 level moment of a coupled lumbar spine can be read."""
        qp, vp, ap, _ = self._joint_motion(np.asarray(dq, dtype=float), np.asarray(qd, dtype=float),
                                           np.asarray(qdd, dtype=float))
        tau = pin.rnea(self.model, self.data, qp, vp, ap).copy()
        if hand_load and self.n_load_points:
            tau += (hand_load * self._load_factor) * pin.computeGeneralizedGravity(self.load_model, self.load_data, qp)
        return tau * self._joint_scale

    def body_masses(self) -> dict[str, float]:
        return {b["name"]: float(b["mass"]) for b in self.description["bodies"]}
