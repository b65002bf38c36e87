"""What of a scale's CPU its nodes may use: one rule for the planners and the runtime alike."""

from .types import DeciderSettings


def usable_cpu(capacity_cpu: float, settings: DeciderSettings) -> float:
    """The CPU of a scale that its nodes may use: its capacity times ``cpu_headroom``.

    The one definition, used by the CPU rule, the migration policy and the planners alike, so
    that a first layout the planners make is one the decider accepts.
    """
    return capacity_cpu * settings.cpu_headroom
