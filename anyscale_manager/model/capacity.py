"""What of a scale's CPU its nodes may use: one rule for the planners and the runtime alike."""

from .types import DeciderSettings, Deployment


def usable_cpu(capacity_cpu: float, settings: DeciderSettings) -> float:
    """The CPU of a scale that its nodes may use: its capacity times ``cpu_headroom``.

    The one definition, used by the CPU rule, the migration policy and the planners alike, so
    that a first layout the planners make is one the decider accepts.
    """
    return capacity_cpu * settings.cpu_headroom


def claim_lease_s(deployment: Deployment) -> float:
    """How long a claim on a shared host outlives its agent's last renewal (agent/ledger.py):
    past the time a dead agent's warden takes to stop its copies, or a restarted agent to adopt
    them, so that room is never handed on while they may still run."""
    a = deployment.agent
    return max(a.adopt_grace_s, a.restart_grace_s) + a.fence_grace_s + 2.0
