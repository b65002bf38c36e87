"""anyscale-manager profile --duration S --output FILE: a deployment skeleton from a live graph.

Exit 0: the file is written and validates. Exit 1: no node to keep was seen (nothing written).
Exit 2: bad arguments (nothing started).
"""

import argparse
import math
import os
import sys
import tempfile

import yaml

from ..model.loader import DeploymentError, load_mapping
from .skeleton import counts, render

MAX_DURATION_S = 86400.0
FEW_READINGS_S = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--duration', type=float, required=True, metavar='S',
                        help='how long to watch the graph, in seconds (10-60 is usual; under '
                             f'{FEW_READINGS_S:g} s, too few rate readings to suggest thresholds)')
    parser.add_argument('--output', required=True, metavar='FILE',
                        help='the deployment YAML to write (replaced if it exists)')
    parser.add_argument('--name', metavar='NAME',
                        help="the deployment's name (default: the output file's name without "
                             'its extension)')


def _argument_problems(args: argparse.Namespace) -> list:
    problems = []
    if not math.isfinite(args.duration) or not 0 < args.duration <= MAX_DURATION_S:
        problems.append(f'--duration: expected seconds in (0, {MAX_DURATION_S:g}], got '
                        f'{args.duration:g}')
    out = args.output
    parent = os.path.dirname(os.path.abspath(out))
    if not out or out.endswith(os.sep) or os.path.isdir(out):
        problems.append(f'--output: {out!r} is a folder; name the file to write')
    elif not os.path.isdir(parent):
        problems.append(f'--output: folder {parent} does not exist')
    elif not os.access(parent, os.W_OK):
        problems.append(f'--output: folder {parent} is not writable')
    elif os.path.exists(out) and not os.access(out, os.W_OK):
        problems.append(f'--output: {out} exists and is not writable')
    if args.name is not None and (not args.name.strip() or '\n' in args.name
                                  or len(args.name) > 200):
        problems.append(f'--name: expected one line of text, got {args.name!r:.60}')
    return problems


def default_name(output: str) -> str:
    stem = os.path.splitext(os.path.basename(output))[0]
    return stem or 'profiled'


def _write(path: str, text: str) -> None:
    """Write ``text`` whole or not at all (a Ctrl-C or a full disk never leaves half a file)."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix='.profile-', suffix='.yaml', dir=folder)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def run(args: argparse.Namespace) -> int:
    problems = _argument_problems(args)
    if problems:
        for p in problems:
            print(f'anyscale-manager profile: {p}', file=sys.stderr)
        return 2
    name = args.name if args.name is not None else default_name(args.output)
    domain = os.environ.get('ROS_DOMAIN_ID', '0')
    if args.duration < FEW_READINGS_S:
        print(f'anyscale-manager profile: a {args.duration:g} s watch gives fewer than 3 rate '
              'readings per topic: connections will get no suggested thresholds',
              file=sys.stderr)
    print(f'profile: watching the ROS 2 graph on ROS_DOMAIN_ID={domain} for {args.duration:g} s '
          '(Ctrl-C ends the watch early and writes what was seen)', file=sys.stderr)
    from .watch import watch    # rclpy only once the arguments are good

    def progress(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    try:
        result = watch(args.duration, progress)
    except Exception as e:      # rclpy's errors (a bad ROS_DOMAIN_ID...) are plain RuntimeErrors
        print(f'anyscale-manager profile: cannot watch the graph: {e}', file=sys.stderr)
        return 2
    if result.interrupted:
        print(f'profile: stopped after {result.duration_s:.1f} s (Ctrl-C): writing what was '
              'seen', file=sys.stderr)
    profile = result.profile(name, domain)
    if not profile.nodes:
        own = f'anyscale_profile_{os.getpid()}'
        left_out = sorted(n for n in result.graph.nodes if not n.endswith('/' + own))
        print(f'anyscale-manager profile: no node to profile was seen in '
              f'{result.duration_s:.1f} s on ROS_DOMAIN_ID={domain} (ROS_AUTOMATIC_DISCOVERY_'
              f'RANGE={os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "unset")}): is the '
              'system running, with the same ROS_DOMAIN_ID and discovery settings as this '
              'shell?' + (f' Left out (hidden or the project\'s own): {", ".join(left_out)}'
                          if left_out else ''), file=sys.stderr)
        print(f'anyscale-manager profile: {args.output} not written', file=sys.stderr)
        return 1
    text = render(profile)
    try:
        load_mapping(yaml.safe_load(text), args.output)
        valid = True
    except DeploymentError as e:    # a bug of the profile: say so, keep the file to look at
        print(f'anyscale-manager profile: the skeleton does not validate (a bug, please '
              f'report it):\n{e}', file=sys.stderr)
        valid = False
    _write(args.output, text)
    c = counts(profile)
    print(f'wrote {args.output}: {c["nodes"]} nodes ({c["cpu"]} with CPU measured on this '
          f'host), {c["connections"]} connections ({c["monitored"]} with suggested '
          f'thresholds). Next: the TODOs in it, then anyscale-manager validate {args.output}')
    return 0 if valid else 1
