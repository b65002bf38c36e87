"""Ports for the deployments that tests and benches write on this machine's loopback.

A deployment's wardens and probe servers listen on ``monitoring.bandwidth_probe_port`` and the
ports after it (Deployment.scale_port). On one machine those must be ports nothing else takes:
not Linux's ephemeral range (32768-60999 by default, /proc/sys/net/ipv4/ip_local_port_range),
from which every socket bound to port 0 gets one at random (a DDS participant's, a link
monitor's echo socket), nor the DDS ports of the test domains (7400 + 250 x domain and the 250
after it: below 58000 for the domains 1-201 the tests use, a fleet's second robot at the test's
domain + 100). A warden that found its port taken said so and exited, and its scale's link
never came up (a CI run). ``port_base`` draws from 61000-64999, past both.
"""

import os

LOW = 61000
SPAN = 4000
# Ports a base leaves for its deployments: a scale's port is the base + 1 + its index, and a
# fleet gives each robot its own stride.
STRIDE_ROOM = 64


def port_base(salt: int = 0) -> int:
    """A base port for this process's deployments (``salt``: another one of the same process,
    e.g. a second deployment, so that the two never share ports)."""
    return LOW + (os.getpid() + salt) % (SPAN - STRIDE_ROOM)


__all__ = ['port_base']
