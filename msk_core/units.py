"""Physical constants and device facts shared by every layer. A leaf module (it imports nothing of the project), so
drivers/ may use it too."""

import math

#: Gravitational acceleration in m/s²: what ``load_kg`` weighs at the hands (``load_kg * GRAVITY`` newtons, the trial
#: files' and the session's convention) and what a simulated accelerometer at rest reads. A model pack's own gravity
#: vector comes from its OpenSim model (``spec.dynamics.gravity``), not from here.
GRAVITY = 9.81

#: The heaviest external load a lift may hold, kg: above every barbell lift's record (about 500 kg), far below what a
#: load in grams reads. Beyond it a load is refused: the estimate would chase torques no muscle makes, and report
#: them "solved" (a new user's `msk load 60000`: 99 % of the shoulder torque unexplained, no flag).
MAX_LOAD_KG = 1000.0
#: The body masses a subject may have, kg; outside, the number is most likely in other units (grams).
BODY_MASS_RANGE_KG = (20.0, 400.0)


def load_problem(load_kg: float) -> str | None:
    """Why ``load_kg`` is not a load a lifter holds (None: it is one)."""
    if not (math.isfinite(load_kg) and load_kg >= 0):
        return "must be a finite mass >= 0 kg"
    if load_kg > MAX_LOAD_KG:
        return (
            f"{load_kg:g} kg is more than any lift's load (at most {MAX_LOAD_KG:g} kg here): "
            f"is it in grams ({load_kg / 1000:g} kg)?"
        )
    return None


def body_mass_problem(body_mass_kg: float) -> str | None:
    """Why ``body_mass_kg`` is not a subject's mass (None: it is one)."""
    low, high = BODY_MASS_RANGE_KG
    if not (math.isfinite(body_mass_kg) and low <= body_mass_kg <= high):
        return f"must be a body mass in kg, within {low:g}-{high:g} (grams? pounds?)"
    return None


#: Delsys Trigno EMG input range: about +-11 mV in volts on the SDK stream (+-5.5 mV in the low range):
#: shared/protocols/trigno-tcp.md; the Trigno sensors' user guides (MAN-039) list an 11 mV input range, 16 bits. The
#: rail the quality monitor judges saturation against (msk_core.signal.quality) and where the simulated Trigno's
#: converter clips (drivers/trigno/simulator.py).
TRIGNO_EMG_RANGE_V = 0.011

#: volts per unit of the voltage units analog files use (C3D ANALOG:UNITS; lower case)
VOLTS_PER_UNIT = {"v": 1.0, "volt": 1.0, "volts": 1.0, "mv": 1e-3, "uv": 1e-6, "µv": 1e-6, "μv": 1e-6}


def volts_per_unit(unit: str) -> float | None:
    """Volts per ``unit`` (``"mV"`` -> 1e-3); None for a unit that is not a voltage (N, N.mm, ...) or unknown."""
    return VOLTS_PER_UNIT.get(unit.strip().lower())
