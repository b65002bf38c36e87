"""The test suite with the whole machine paused now and then: robustness to a stalled host.

    sudo .venv/bin/python bench/pause_suite.py [--pause 1.0] [--every 15] [-- COMMAND ...]

A loaded CI host or a paused virtual machine stops every process at once for a moment. On
wake-up each one may run a timer before it reads what arrived meanwhile; a judge that takes its
own silence for the others' (a link declared down, an agent declared lost) then acts on nothing.
This runs COMMAND (default: the README's test command, `./run.sh test`) in a cgroup of its own
and freezes that cgroup (everything the command started, ROS nodes included) for ``--pause``
seconds every ``--every`` seconds, through the cgroup v1 freezer, which stops processes without
a signal (SIGSTOP would thaw the agents' frozen standby copies). It prints how many pauses
there were and exits with the command's status.

Needs root and the v1 freezer hierarchy (/sys/fs/cgroup/freezer). Under cgroup v2 a process
lives in one cgroup only, and the test-bed moves the robot's processes into its own: the pause
would miss them, so this refuses to run there.
"""

import argparse
import os
import subprocess
import sys
import time

FREEZER = '/sys/fs/cgroup/freezer'
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _write(path, text):
    with open(path, 'w') as f:
        f.write(text)


def _members(group):
    with open(os.path.join(group, 'cgroup.procs')) as f:
        return [line for line in f.read().split() if line]


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--pause', type=float, default=1.0, help='seconds frozen each time')
    parser.add_argument('--every', type=float, default=15.0, help='seconds between pauses')
    parser.add_argument('command', nargs=argparse.REMAINDER,
                        help='the command to run (after --); default ./run.sh test')
    args = parser.parse_args()
    command = [a for a in args.command if a != '--'] or ['./run.sh', 'test']
    if not 0 < args.pause < args.every:
        parser.error('need 0 < --pause < --every')
    if os.geteuid() != 0 or not os.path.isdir(FREEZER):
        print(f'pause_suite: needs root and the cgroup v1 freezer ({FREEZER})', file=sys.stderr)
        return 2
    group = os.path.join(FREEZER, f'anyscale-pause-{os.getpid()}')
    os.mkdir(group)
    state = os.path.join(group, 'freezer.state')
    pauses, code = 0, 1
    try:
        proc = subprocess.Popen(command, cwd=REPO, preexec_fn=lambda: _write(
            os.path.join(group, 'cgroup.procs'), str(os.getpid())))
        next_pause = time.monotonic() + args.every
        while proc.poll() is None:
            if time.monotonic() < next_pause:
                time.sleep(0.05)
                continue
            _write(state, 'FROZEN')
            time.sleep(args.pause)
            _write(state, 'THAWED')
            pauses += 1
            next_pause = time.monotonic() + args.every
        code = proc.returncode
    finally:
        _write(state, 'THAWED')
        deadline = time.monotonic() + 30.0
        while _members(group) and time.monotonic() < deadline:
            time.sleep(0.1)
        try:
            os.rmdir(group)
        except OSError as e:
            print(f'pause_suite: could not remove {group}: {e}', file=sys.stderr)
    print(f'pause_suite: {pauses} pauses of {args.pause:g} s every {args.every:g} s; '
          f'{" ".join(command)} exited with {code}')
    return code


if __name__ == '__main__':
    sys.exit(main())
