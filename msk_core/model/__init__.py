"""Musculoskeletal model packs: compiled moment-arm / length surrogates and reduced inverse dynamics.

Runtime use needs only numpy and pinocchio::

    from msk_core.model import load_pack
    pack = load_pack("arm26")
    r = pack.moment_arms(q)          # (n_coordinates, n_groups), metres
    tau = pack.inverse_dynamics(q, qd, qdd, hand_load_newton=200.0)
    fast = load_pack("deadlift", evaluator=Evaluator.COMPILED)  # one numba call per frame() (needs numba)

Compiling and checking packs (``msk model compile|check|scale``) needs the opensim package.
"""

from msk_core.model.pack import Evaluator, ModelPack, OutOfRange, available_packs, load_pack

__all__ = ["Evaluator", "ModelPack", "OutOfRange", "available_packs", "load_pack"]
