"""Exercise definitions: which pack, the top and bottom poses, timing warps, EMG electrode sites and default loads.

Poses are given per coordinate *role* (matched against the pack's coordinate names) in the pack's own sign
convention, degrees. Coordinates that match no role are held at the pack's reference pose.

Pose sources (sagittal-plane joint angles):
* Bench press, arms extended vs. bar low over the chest: shoulder flexion ≈ 85° -> slightly extended, elbow flexion
  ≈ 15° -> 90–130° (e.g. Barnett, Kippers & Turner 1995, J Strength Cond Res 9:222; Lehman 2005, J Strength Cond
  Res 19:587); a sagittal model without abduction needs the upper end of the elbow range to bring the bar down.
* Deadlift: a conventional start has hip flexion ≈ 70–85°, knee flexion ≈ 60–70°, lumbar flexion ≈ 15–25°, ankle
  dorsiflexion ≈ 10–20° (Escamilla et al. 2000, Med Sci Sports Exerc 32:1265; Cholewicki, McGill & Norman 1991,
  Med Sci Sports Exerc 23:1179). The deadlift pack (1.1) lets the arms hang plumb from the shoulders, so the bar
  stays over the mid-foot: lift-off at hip 75°, knee 60°, ankle 15°, lumbar −3.5° per level (21° in total; flexion
  is negative in the pack); 4° forward lean at lockout.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass, field

import numpy as np

from msk_core.errors import ConfigError


class Exercise(enum.Enum):
    BENCH_PRESS = "bench_press"
    DEADLIFT = "deadlift"


@dataclass(frozen=True)
class Role:
    pattern: str  # regex searched in the coordinate name (case-insensitive)
    top_deg: float
    bottom_deg: float
    warp: float = 0.0  # time-warp k of the concentric move (>0: this joint leads)


@dataclass(frozen=True)
class ElectrodeSite:
    """Where an EMG sensor sits: on which pack body, and where on it. A Trigno Avanti sensor's accelerometer measures
    the motion of that point (``msk_core.synth.imu.simulate_electrode_acc``)."""

    body: str | None  # regex of the pack body under the electrode; None: a part the pack keeps still (its ground)
    along: float = 1.0  # on the line from the body's joint centre (0) to its centre of mass (1)


@dataclass(frozen=True)
class ExerciseSpec:
    exercise: Exercise
    pack: str
    roles: tuple[Role, ...]
    emg_groups: tuple[str, ...]  # electrode sites, named after the group they record (channel label = group)
    loads_kg: tuple[float, ...]
    segments: dict[str, str]  # IMU tracker label -> regex of the pack body it is strapped to
    # electrode site (group) -> where its sensor sits; a site not listed, or whose body the pack lacks, lies still
    electrode_sites: dict[str, ElectrodeSite] = field(default_factory=dict)

    def poses(self, coordinates: list[str], reference: np.ndarray, ranges: np.ndarray):
        """(top, bottom, warp) arrays over the pack's coordinates, clipped into the fitted ranges."""
        top = np.asarray(reference, dtype=float).copy()
        bottom = top.copy()
        warp = np.zeros(len(coordinates))
        used = set()
        for i, name in enumerate(coordinates):
            for role in self.roles:
                if re.search(role.pattern, name, flags=re.IGNORECASE):
                    top[i], bottom[i], warp[i] = np.radians(role.top_deg), np.radians(role.bottom_deg), role.warp
                    used.add(role.pattern)
                    break
        if not used:
            raise ConfigError(
                f"no coordinate of the pack matches the {self.exercise.value} roles",
                field="coordinates",
                value=coordinates,
            )
        # keep a small margin inside the fitted range so depth jitter never leaves it
        margin = np.minimum(np.radians(4.0), 0.1 * (ranges[:, 1] - ranges[:, 0]))
        lo, hi = ranges[:, 0] + margin, ranges[:, 1] - margin
        return np.clip(top, lo, hi), np.clip(bottom, lo, hi), warp

    def channels(self, groups: list[str]) -> list[str]:
        chosen = [g for g in self.emg_groups if g in groups]
        return chosen if chosen else list(groups)


BENCH_PRESS = ExerciseSpec(
    exercise=Exercise.BENCH_PRESS,
    pack="bench_press",
    roles=(
        # bench_press pack: elv_angle_r is sagittal shoulder flexion (0 = arm along the trunk), lying supine. The
        # bottom pose is the lowest bar position this sagittal (elbows-tucked) arm reaches: the bar ~20 cm caudal
        # of the shoulder and the elbow just below the shoulder; top: arm vertical over the shoulder.
        Role(r"elv_angle|shoulder|arm_flex|elev", 85.0, -10.0, warp=0.1),
        Role(r"elbow", 15.0, 120.0, warp=-0.1),
    ),
    # superficial sites a Trigno set-up can reach (BRA, BicSho and PMCos are covered by other muscles)
    emg_groups=("PMCla", "PMSte", "DelAnt", "DelMed", "DelPos", "BicLong", "TriLong", "TriLat", "BRD", "LD"),
    loads_kg=(20.0, 40.0, 50.0, 60.0),
    segments={"upper_arm_r": r"humerus|upper", "forearm_r": r"radius|ulna|forearm|hand"},
    # lying on the bench, the trunk is the pack's ground: the chest and back sensors (PMCla, PMSte, LD) lie still;
    # the deltoid bellies are proximal on the upper arm, biceps and triceps at its middle (the tracker sits at the
    # centre of mass, a little distal of them), brachioradialis proximal on the forearm
    electrode_sites={
        **{g: ElectrodeSite(r"humerus|upper", 0.4) for g in ("DelAnt", "DelMed", "DelPos")},
        **{g: ElectrodeSite(r"humerus|upper", 0.8) for g in ("BicLong", "TriLong", "TriLat")},
        "BRD": ElectrodeSite(r"radius|forearm", 0.5),
        **{g: ElectrodeSite(None) for g in ("PMCla", "PMSte", "LD")},
    },
)

DEADLIFT = ExerciseSpec(
    exercise=Exercise.DEADLIFT,
    pack="deadlift",
    roles=(
        # fullbody.osim: L5_S1_FE drives six lumbar levels (total flexion = 6 x value), flexion NEGATIVE
        # (checked: T12 moves anterior for L5_S1_FE < 0)
        Role(r"^L5_S1_FE$", 0.0, -3.5, warp=-0.2),
        # lumbar_scaled.osim (lumbar_lift pack): one level, flexion negative
        Role(r"L5_S1_Flex_Ext|lumbar", 0.0, -15.0, warp=-0.2),
        Role(r"hip", 0.0, 75.0, warp=-0.15),
        Role(r"knee", 0.0, 60.0, warp=0.15),  # Rajagopal/Lai knee_angle_r: flexion positive
        Role(r"ankle", 4.0, 15.0, warp=0.1),
    ),
    emg_groups=("ESL", "ESI", "MUL", "RA", "EO", "IO", "Gmax", "Gmed", "TFL", "BF", "ST", "RF", "VL", "VM", "GM", "TA"),
    loads_kg=(35.0, 45.0, 65.0, 75.0),
    segments={
        "torso": r"torso|thorax|lumbar1|trunk",
        "pelvis": r"pelvis|sacrum",
        "thigh_r": r"femur|thigh",
        "shank_r": r"tibia|shank",
        "foot_r": r"calcn|talus|foot",
    },
    # erector spinae and multifidus over the lumbar vertebrae, the abdominal wall at mid-lumbar level, gluteals and
    # TFL on the pelvis, thigh and shank muscles at the middle of their segments
    electrode_sites={
        "ESL": ElectrodeSite(r"lumbar1", 0.6),
        "ESI": ElectrodeSite(r"lumbar2"),
        "MUL": ElectrodeSite(r"lumbar5"),
        **{g: ElectrodeSite(r"lumbar3") for g in ("RA", "EO", "IO")},
        **{g: ElectrodeSite(r"pelvis", 0.7) for g in ("Gmax", "Gmed", "TFL")},
        **{g: ElectrodeSite(r"femur|thigh", 0.8) for g in ("BF", "ST", "RF", "VL", "VM")},
        **{g: ElectrodeSite(r"tibia|shank", 0.8) for g in ("GM", "TA")},
    },
)

SPECS: dict[Exercise, ExerciseSpec] = {Exercise.BENCH_PRESS: BENCH_PRESS, Exercise.DEADLIFT: DEADLIFT}


def parse_exercise(text: str) -> Exercise:
    try:
        return Exercise(text)
    except ValueError:
        raise ConfigError(
            f"unknown exercise; choose from {', '.join(e.value for e in Exercise)}", field="exercise", value=text
        ) from None
