"""anyscale-manager: the one command for people, with a subcommand per task."""

import argparse
import importlib
import os
import sys
from typing import List, Optional
from .interrupt import restore_ctrl_c

# name -> (module with add_arguments(parser) and run(args) -> int, one-line help)
SUBCOMMANDS = {
    'validate': ('anyscale_manager.validate', 'check deployment files and summarise them'),
    'plan': ('anyscale_manager.planning.cli',
             'choose node settings and the first layout (IROS 2016 Problems 1 and 2)'),
    'simulate': ('anyscale_manager.sim.cli', 'reproduce the ICAR 2015 evaluation in simulation'),
    'demo': ('anyscale_manager.testbed.cli',
             'run the ICAR 2015 test-bed with a link outage schedule and draw its timeline'),
    'status': ('anyscale_manager.nodes.status', 'show the live state of a running deployment'),
    'keygen': ('anyscale_manager.keygen', 'write a new deployment key for signed layouts'),
    'profile': ('anyscale_manager.profiling.cli', 'a deployment skeleton from a live ROS 2 graph'),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='anyscale-manager',
        description='Place ROS 2 nodes on the computers (scales) of a robot system and move '
                    'them while it runs.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        try:
            importlib.import_module(module).add_arguments(p)
        except ImportError as e:
            p.set_defaults(_missing=str(e))
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    restore_ctrl_c()
    args = build_parser().parse_args(argv)
    missing = getattr(args, '_missing', None)
    if missing:
        print(f'anyscale-manager {args.command}: not available in this install ({missing})',
              file=sys.stderr)
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (e.g. `| head`): not an error of ours.
        sys.stdout = open(os.devnull, 'w')
        return 0


if __name__ == '__main__':
    sys.exit(main())
