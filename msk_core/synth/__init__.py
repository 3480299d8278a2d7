"""Synthetic gym sessions with known truth (bench press, deadlift): kinematics, inverse dynamics, true activations
from a recruitment that is not static optimisation, raw EMG, IMU streams, load events and optional hidden effects.

Entry points: :func:`generate_session` / :func:`generate_exercise` build in memory; :mod:`msk_core.synth.files`
writes trial TOMLs, OpenSim storage files and the truth JSON. MCAP export lives in ``services.sessions.synth_export``.
"""

from msk_core.synth.effects import Effects, parse_effects
from msk_core.synth.exercises import SPECS, Exercise, ExerciseSpec, parse_exercise
from msk_core.synth.session import (
    ExerciseSession,
    MvcTrial,
    Session,
    SynthConfig,
    Trial,
    generate_exercise,
    generate_mvc,
    generate_session,
    generate_trial,
)
from msk_core.synth.subject import Subject, make_subject

__all__ = [
    "Effects",
    "Exercise",
    "ExerciseSession",
    "ExerciseSpec",
    "MvcTrial",
    "SPECS",
    "Session",
    "Subject",
    "SynthConfig",
    "Trial",
    "generate_exercise",
    "generate_mvc",
    "generate_session",
    "generate_trial",
    "make_subject",
    "parse_effects",
    "parse_exercise",
]
