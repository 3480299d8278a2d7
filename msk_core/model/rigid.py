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
        # joints whose value is a polynomial of one coordinate (rolling knee, patella): q_j = f(dq_k)
        nonlinear = [(i, j["function"]) for i, j in enumerate(joints) if "function" in j]
        self._nl = np.array([i for i, _ in nonlinear], dtype=np.int64)
        self._nl_coord = np.array([f["coordinate"] for _, f in nonlinear], dtype=np.int64)
        self._nl_centre = np.array([f["centre"] for _, f in nonlinear], dtype=float)
        self._nl_half = np.array([f["half_width"] for _, f in nonlinear], dtype=float)
        coef = (np.array([f["coefficients"] for _, f in nonlinear], dtype=float) if nonlinear
                else np.zeros((0, 1)))
        degree = coef.shape[1]
        self._nl_coef = coef
        self._nl_d1 = coef[:, 1:] * np.arange(1, degree)[None, :] if degree > 1 else np.zeros((len(nonlinear), 1))
        self._nl_d2 = (self._nl_d1[:, 1:] * np.arange(1, degree - 1)[None, :] if degree > 2
                       else np.zeros((len(nonlinear), 1)))
        self._nl_powers = np.arange(max(degree, 1))
        self._load_factor = self.load_share / max(self.n_load_points, 1) / (self._g_norm or 1.0)

    def inverse_dynamics(
        self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float, gravity: np.ndarray | None
    ) -> np.ndarray:
        """Torques at pack coordinates for offsets dq = q - q_ref, velocities and accelerations."""
        qp = self.gains @ dq
        vp = self.gains @ qd
        ap = self.gains @ qdd
        projection = self._projection
        if len(self._nl):
            k = self._nl_coord
            x = (dq[k] - self._nl_centre) / self._nl_half
            powers = x[:, None] ** self._nl_powers[None, :]
            d1 = (self._nl_d1 * powers[:, : self._nl_d1.shape[1]]).sum(axis=1) / self._nl_half
            d2 = (self._nl_d2 * powers[:, : self._nl_d2.shape[1]]).sum(axis=1) / self._nl_half**2
            qp[self._nl] = (self._nl_coef * powers[:, : self._nl_coef.shape[1]]).sum(axis=1)
            vp[self._nl] = d1 * qd[k]
            ap[self._nl] = d1 * qdd[k] + d2 * qd[k] ** 2
            projection = projection.copy()
            projection[k, self._nl] = d1 * self.torque_scale[k]  # virtual work: tau_k += f'(q) tau_j
        if gravity is None:
            tau = pin.rnea(self.model, self.data, qp, vp, ap)
            if hand_load and self.n_load_points:
                # hand_load acts along gravity: hold (hand_load / |g|) kg, split over the load points
                tau = tau + (hand_load * self._load_factor) * pin.computeGeneralizedGravity(
                    self.load_model, self.load_data, qp)
            return projection @ tau
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
        return projection @ tau

    def body_masses(self) -> dict[str, float]:
        return {b["name"]: float(b["mass"]) for b in self.description["bodies"]}
