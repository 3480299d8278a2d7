"""Physical constants and device facts shared by every layer. A leaf module (it imports nothing), so drivers/ may use
it too."""

#: Gravitational acceleration in m/s²: what ``load_kg`` weighs at the hands (``load_kg * GRAVITY`` newtons, the trial
#: files' and the session's convention) and what a simulated accelerometer at rest reads. A model pack's own gravity
#: vector comes from its OpenSim model (``spec.dynamics.gravity``), not from here.
GRAVITY = 9.81

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
