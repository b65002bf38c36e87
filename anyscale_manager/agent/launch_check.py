"""Whether this machine can start each node: its launch resolved exactly as an agent here would.

It looks at the file system, the ament index and PATH of the machine it runs on. validate uses
it; the agent resolves the same way when it starts (agent/catalogue.py), so what validate
accepts is what the agent can start.
"""

import os
from typing import Callable, Dict, Mapping, Optional

from ..model import types as t
from .catalogue import build_argv


def launch_problems(d: t.Deployment, environ: Optional[Mapping[str, str]] = None,
                    ament_prefix: Optional[Callable[[str], Optional[str]]] = None
                    ) -> Dict[str, str]:
    """Node name -> why this machine cannot start it, for each managed node with a launch."""
    environ = os.environ if environ is None else environ
    extra = {} if ament_prefix is None else {'ament_prefix': ament_prefix}
    out = {}
    for node in d.nodes:
        if not node.managed or not node.launch.startable:
            continue
        # The agent's child gets the agent's PATH unless the launch sets its own.
        path = str(node.launch.env.get('PATH', environ.get('PATH', os.defpath)))
        argv, problem = build_argv(node, path, **extra)
        if not problem and node.launch.command and os.sep in node.launch.command[0]:
            # A command given as a path is run as written: nothing has looked at it yet.
            head = argv[0]
            where = '' if os.path.isabs(head) else \
                " (a relative path is taken from the agent's working directory)"
            if not os.path.isfile(head):
                problem = f'command {head!r} does not exist{where}'
            elif not os.access(head, os.X_OK):
                problem = f'command {head!r} is not executable'
        if problem:
            out[node.name] = problem
    return out
