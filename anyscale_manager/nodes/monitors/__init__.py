"""The monitors an agent hosts inside its own node: scale CPU, the link, connection probes.

Glue only: each class reads the world (psutil, cgroups, DDS arrivals, sockets), feeds the pure
statistics of ``runtime.rates`` and ``runtime.cpu`` with ``time.monotonic()`` and publishes the
results on the project's topics and on ``/diagnostics``. Each monitor runs its callbacks in its
own mutually exclusive callback group, so a multi-threaded executor never runs two of one
monitor's callbacks at once.

Each monitor has a module of its own: ``scale`` (ScaleMonitor), ``probes`` (ProbeManager),
``link`` (LinkMonitor) with ``throughput`` (its TCP probe), and ``common`` (what they share).
"""

from .common import (DIAGNOSTICS_QOS, LATCHED_QOS, PROBE_QOS, STATUS_QOS,
                     import_message_class)
from .link import LinkMonitor
from .probes import ProbeManager
from .scale import ScaleMonitor
from .throughput import ProbeServer, probe_throughput

__all__ = ['DIAGNOSTICS_QOS', 'LATCHED_QOS', 'PROBE_QOS', 'STATUS_QOS',
           'import_message_class', 'LinkMonitor', 'ProbeManager', 'ScaleMonitor', 'ProbeServer',
           'probe_throughput']
