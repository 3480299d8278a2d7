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
        self.load_frames = []
        for k, load in enumerate(description["load_points"]):
            joint = int(load["joint"])
            placement = pin.SE3(np.eye(3), np.asarray(load["point"], dtype=float) - positions[joint])
            self.load_frames.append(model.addFrame(pin.Frame(f"load{k}_{load['body']}", joint + 1, placement,
                                                             pin.FrameType.OP_FRAME)))
        self.gravity = np.asarray(description["gravity"], dtype=float)
        model.gravity.linear = self.gravity
        self.model = model
        self.data = model.createData()
        self.gains = np.asarray(description["gains"], dtype=float).reshape(len(joints), n_coordinates)
        self.torque_scale = np.asarray(description["torque_scale"], dtype=float)
        self.load_share = float(description["load_share"])
        self._projection = self.gains.T * self.torque_scale[:, None]  # (n_coordinates, n_joints)

    def inverse_dynamics(
        self, dq: np.ndarray, qd: np.ndarray, qdd: np.ndarray, hand_load: float, gravity: np.ndarray | None
    ) -> np.ndarray:
        """Torques at pack coordinates for offsets dq = q - q_ref, velocities and accelerations."""
        qp = self.gains @ dq
        vp = self.gains @ np.asarray(qd, dtype=float)
        ap = self.gains @ np.asarray(qdd, dtype=float)
        g = self.gravity if gravity is None else np.asarray(gravity, dtype=float)
        if gravity is not None:
            self.model.gravity.linear = g
        try:
            tau = pin.rnea(self.model, self.data, qp, vp, ap).copy()
        finally:
            if gravity is not None:
                self.model.gravity.linear = self.gravity
        if hand_load and self.load_frames:
            norm = np.linalg.norm(g)
            force = (self.load_share * hand_load / len(self.load_frames)) * (g / norm if norm > 0 else g)
            for frame in self.load_frames:
                jac = pin.computeFrameJacobian(self.model, self.data, qp, frame, pin.LOCAL_WORLD_ALIGNED)
                tau -= jac[:3].T @ force
        return self._projection @ tau

    def body_masses(self) -> dict[str, float]:
        return {b["name"]: float(b["mass"]) for b in self.description["bodies"]}
