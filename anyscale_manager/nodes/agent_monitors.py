"""The monitors an agent hosts (nodes/monitors): its scale's CPU, its links, and the probes of
the connections its serving nodes subscribe to. A broken install, or a monitor that cannot
start, never takes the supervision down: what is missing is said and the agent goes on."""

from typing import Any, Callable, Dict, List

from rclpy.node import Node

from ..protocol_auth import Sealer

try:
    from . import monitors as _monitors
    _MONITORS_MISSING = ''
except ImportError as exc:   # a broken install: the agent still supervises without monitors
    _monitors = None
    _MONITORS_MISSING = str(exc)


class AgentMonitors:
    def __init__(self, node: Node, deployment: Any, scale: str, sealer: Sealer,
                 serving_pids: Callable[[], Dict[str, int]],
                 own_pids: Callable[[], List[int]], shared_with: Callable[[], tuple]):
        self._node = node
        self.monitors: List[Any] = []
        self.probes: Any = None               # the ProbeManager, if it runs
        log = node.get_logger()
        if _monitors is None:
            log.warn(f'monitors not available ({_MONITORS_MISSING}); '
                     'this agent supervises nodes only')
            return
        d = deployment
        builders = (('ScaleMonitor', lambda cls: cls(node, d, scale, pids=serving_pids,
                                                     own_pids=own_pids,
                                                     shared_with=shared_with, sealer=sealer)),
                    ('LinkMonitor', lambda cls: cls(node, d, scale, sealer=sealer)),
                    ('ProbeManager', lambda cls: cls(node, d, scale,
                                                     handovers=True,
                                                     sealer=sealer)))
        for name, build in builders:
            cls = getattr(_monitors, name, None)
            if cls is None:
                log.warn(f'monitors.{name} not available; not hosted')
                continue
            try:
                monitor = build(cls)
            except Exception as e:   # a monitor must never take the supervision down
                log.error(f'cannot start {name}: {e!r}')
                continue
            self.monitors.append(monitor)
            if name == 'ProbeManager':
                self.probes = monitor

    def destroy(self) -> None:
        for monitor in self.monitors:
            try:
                monitor.destroy()
            except Exception as e:
                self._node.get_logger().error(f'destroying {type(monitor).__name__}: {e!r}')
        self.monitors = []
        self.probes = None
