"""Physical constants shared by every layer. A leaf module (it imports nothing), so drivers/ may use it too."""

#: Gravitational acceleration in m/s²: what ``load_kg`` weighs at the hands (``load_kg * GRAVITY`` newtons, the trial
#: files' and the session's convention) and what a simulated accelerometer at rest reads. A model pack's own gravity
#: vector comes from its OpenSim model (``spec.dynamics.gravity``), not from here.
GRAVITY = 9.81
