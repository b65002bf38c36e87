"""Does every reader hear a thawed standby writer? A reproducer for the e2e test 5 fault.

    .venv/bin/python bench/bench_thaw_readers.py --domain-id N [--freeze 25] [--rounds 6]
        [--readers 3] [--readers-lease default|long] [--talker-lease long|default]
        [--busy 1]

A 10 Hz talker (the agent tests' fixture) runs with the agent's standby profile (its participant
announces a 24 h lease; ``--talker-lease default``: without it), beside ``--readers`` listener
processes, each its own participant with the default lease (or, with ``--readers-lease long``,
the standby profile too). Each round the
talker's group is frozen (SIGSTOP) for ``--freeze`` seconds, thawed, and the time from the thaw
to each reader's first message is taken; a reader that hears nothing within 8 s is reported as
``None``. ``--busy`` busy-loop processes load the machine meanwhile. On the test-bed, a thawed
AMCL was once heard by one reader on the robot and not by another (docs/testbed.md); this asks
whether a plain freeze and thaw does it. Loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)
sys.path.insert(0, REPO)
from anyscale_manager.agent.catalogue import standby_profile_xml  # noqa: E402

TALKER = os.path.join(REPO, 'test', 'fixtures', 'agent_talker.py')
LISTENER = '''
import sys, time
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from std_msgs.msg import String
rclpy.init()
node = Node(sys.argv[1])
node.create_subscription(String, sys.argv[2], lambda m: print(time.monotonic(), flush=True), 10)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
'''
HEAR_TIMEOUT_S = 8.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--domain-id', type=int, required=True)
    ap.add_argument('--freeze', type=float, default=25.0)
    ap.add_argument('--rounds', type=int, default=6)
    ap.add_argument('--readers', type=int, default=3)
    ap.add_argument('--readers-lease', choices=('default', 'long'), default='default')
    ap.add_argument('--talker-lease', choices=('long', 'default'), default='long')
    ap.add_argument('--busy', type=int, default=1, help='busy-loop processes beside')
    ap.add_argument('--out', default='')
    args = ap.parse_args()
    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    folder = tempfile.mkdtemp(prefix='anyscale-thaw-')
    profile = os.path.join(folder, 'standby.xml')
    with open(profile, 'w') as f:
        f.write(standby_profile_xml())
    long_env = dict(env, FASTDDS_DEFAULT_PROFILES_FILE=profile,
                    FASTRTPS_DEFAULT_PROFILES_FILE=profile)
    topic = f'/bench_thaw_{os.getpid()}'
    procs = [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                              start_new_session=True) for _ in range(args.busy)]
    talker = subprocess.Popen([sys.executable, TALKER, '--ros-args', '-r',
                               f'__node:=bench_thaw_talker_{os.getpid()}', '-p',
                               f'topic:={topic}', '-p', 'rate_hz:=10.0'],
                              env=long_env if args.talker_lease == 'long' else env,
                              start_new_session=True, stdout=subprocess.DEVNULL,
                              stderr=subprocess.STDOUT)
    procs.append(talker)
    heard = {i: [] for i in range(args.readers)}
    for i in range(args.readers):
        reader = subprocess.Popen(
            [sys.executable, '-c', LISTENER, f'bench_thaw_reader_{i}_{os.getpid()}', topic],
            env=long_env if args.readers_lease == 'long' else env, stdout=subprocess.PIPE,
            text=True, start_new_session=True)
        procs.append(reader)

        def read(reader=reader, i=i):
            for line in reader.stdout:
                try:
                    heard[i].append(float(line))
                except ValueError:
                    pass
        threading.Thread(target=read, daemon=True).start()

    def all_heard(since, timeout):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if all(any(t > since for t in heard[i]) for i in heard):
                return True
            time.sleep(0.02)
        return False

    rounds = []
    try:
        if not all_heard(0.0, 30.0):
            print('bench_thaw_readers: the talker never reached every reader', file=sys.stderr)
            return 1
        for r in range(args.rounds):
            os.killpg(talker.pid, signal.SIGSTOP)
            time.sleep(args.freeze)             # the freeze itself, not a wait
            thawed = time.monotonic()
            os.killpg(talker.pid, signal.SIGCONT)
            all_heard(thawed, HEAR_TIMEOUT_S)
            firsts = []
            for i in heard:
                after = [t for t in heard[i] if t > thawed]
                firsts.append(round(after[0] - thawed, 3) if after else None)
            rounds.append(firsts)
            print(f'round {r + 1}: first message after the thaw, per reader (s): {firsts}',
                  flush=True)
    finally:
        for proc in procs:
            for sig in (signal.SIGCONT, signal.SIGINT):
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + 5.0
        for proc in procs:
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        os.remove(profile)
        os.rmdir(folder)
    unheard = sum(1 for firsts in rounds for f in firsts if f is None)
    print(f'{unheard} of {len(rounds) * args.readers} reader-rounds heard nothing within '
          f'{HEAR_TIMEOUT_S:g} s of the thaw (freeze {args.freeze:g} s, lease of the talker: '
          f'{args.talker_lease}, of the readers: {args.readers_lease}, {args.busy} busy '
          f'process(es))')
    if args.out:
        with open(args.out, 'w') as f:
            json.dump({'freeze_s': args.freeze, 'readers_lease': args.readers_lease,
                       'talker_lease': args.talker_lease,
                       'busy': args.busy, 'rounds': rounds, 'unheard': unheard}, f, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
