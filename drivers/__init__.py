"""Device protocols (Delsys Trigno TCP SDK, Xsens Xbus) and faithful simulators of the devices.

Drivers turn device bytes into plain Python/numpy records; the Zenoh nodes in ``services`` publish them.
"""

from msk_core.errors import InputError


def parse_synthetic_spec(text: str) -> tuple[float, int] | None:
    """``synthetic[:SECONDS[:SEED]]`` (the simulators' built-in sources) -> (seconds, seed); None for a file path."""
    if not text.startswith("synthetic"):
        return None
    parts = text.split(":")
    try:
        seconds = float(parts[1]) if len(parts) > 1 and parts[1] else 30.0
        seed = int(parts[2]) if len(parts) > 2 else 0
    except ValueError:
        raise InputError("synthetic source is synthetic[:SECONDS[:SEED]]", field="--from", value=text) from None
    return seconds, seed
