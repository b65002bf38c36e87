"""The master scale's agent and the decider as two nodes of one process.

    ros2 run anyscale_manager master --ros-args --params-file DEPLOYMENT.yaml -p scale:=NAME

NAME must be the deployment's master scale. The process is the agent's (nodes/agent.py: its
signals, its warden, its restart in place on SIGHUP, its final report) with the decider
(nodes/decider.py) as a second node on the same executor: one Python interpreter, one rclpy
context and one DDS participant's worth of memory less on the robot than ``agent`` and
``decider`` run apart (docs/agent.md, the manager's own footprint).

What two processes give and one keeps: an exception in any callback of either node is logged
and the process goes on (the agent's loop); a stop (SIGINT, SIGTERM) destroys the decider first,
so it does not answer the nodes' stop with a new layout. What it gives up: a crash of the
interpreter ends both; the warden keeps the nodes running and the agent's restart adopts them
(as after the agent's own crash), and a standby decider on another scale, if the deployment runs
one, leads meanwhile. The two nodes read the topics they share (the agents' reports, the
layout, the connection readings) through one subscription each (nodes/readers.py).
"""
import faulthandler
import signal
import sys
from typing import List, Optional

from rclpy.node import Node

from . import agent
from .decider import DeciderNode
from .readers import Readers
from .. import protocol_auth as auth
from ..model.loader import DeploymentError

PROGRAM = 'master'


def decider_of(scale: str, readers: Readers) -> Node:
    """The decider for the agent of ``scale``, reading through the process's shared
    subscriptions; refused (AgentError) unless ``scale`` is the deployment's master."""
    try:
        node = DeciderNode(readers=readers)
    except (DeploymentError, ValueError, auth.KeyFileError) as e:
        raise agent.AgentError(f'the decider: {e}') from None
    master = node.deployment.master.name
    if scale != master:
        node.destroy_node()
        raise agent.AgentError(f'scale {scale!r} is not the master of deployment '
                               f'{node.deployment.name!r} ({master!r}): run `agent` there')
    return node


def main(args: Optional[List[str]] = None) -> int:
    # SIGUSR1 writes every thread's stack to stderr (the log): what a process that does not
    # stop is doing.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    return agent.run(args, PROGRAM, guest=decider_of)


if __name__ == '__main__':
    sys.exit(main())
