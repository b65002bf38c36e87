"""``anyscale-manager status``: a live view of a running deployment, read from its topics.

Scales' CPU, the link's state and bandwidth, each connection's rate against its freq_min with
its Δ timer (as the probe reports it), where each node should run and where it runs, the layout
generation and the objective (the text: ``view.status``). On a terminal one screen is redrawn in
place every ``--interval`` until Ctrl-C (``view.screen``); piped, plain snapshots are appended.
``--once`` prints one snapshot and exits. This module is the rclpy glue: subscribe, hand each
message to the book with its arrival time (and the leading decider's diagnostic values, which
say its layout's age), render.
"""

import argparse
import os
import signal
import sys
import time

from .. import protocol as p
from .. import protocol_auth as auth
from ..model.loader import DeploymentError, load_deployment
from ..view.screen import LiveScreen
from ..view.status import StatusBook, listening_text, render


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--params-file', required=True, metavar='DEPLOYMENT.yaml',
                        help='the deployment file the decider and agents were started with')
    parser.add_argument('--once', action='store_true',
                        help='print one snapshot and exit')
    parser.add_argument('--wait', type=float, default=3.0, metavar='S',
                        help='with --once: listen at most this long before printing '
                             '(default 3; stops early once the layout and every agent '
                             'have been heard)')
    parser.add_argument('--interval', type=float, default=1.0, metavar='S',
                        help='refresh period of the live view (default 1)')


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt     # SIGINT, SIGTERM, SIGHUP: leave as Ctrl-C does, terminal restored


def run(args: argparse.Namespace) -> int:
    try:
        deployment = load_deployment(args.params_file)
    except DeploymentError as e:
        print(f'anyscale-manager status: {e}', file=sys.stderr)
        return 2
    if not (args.wait > 0 and args.interval > 0):
        print('anyscale-manager status: --wait and --interval must be > 0', file=sys.stderr)
        return 2
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from diagnostic_msgs.msg import DiagnosticArray
    from std_msgs.msg import String

    from .shutdown import shut_rclpy_down

    from .decider import NODE_NAME as DECIDER
    from .qos import BEAT as beat, LATCHED_READER as latched, MONITOR_READER as sensor
    key = None
    if deployment.security.key_file:
        try:
            key = auth.load_key(deployment.security.key_file)
        except auth.KeyFileError as e:
            print(f'anyscale-manager status: {e}: messages shown unverified', file=sys.stderr)
    book = StatusBook(deployment, key=key, environ=dict(os.environ))
    # discovery.mode server: a client of the deployment's servers, as its processes are.
    from ..agent.discovery import client_environment
    os.environ.update(client_environment(deployment, os.environ)[0])
    ctx = rclpy.Context()
    # Python's own handlers: Ctrl-C is a KeyboardInterrupt in the loop below, which gives the
    # terminal back before the process ends.
    rclpy.init(context=ctx, signal_handler_options=SignalHandlerOptions.NO)
    # SIGINT too: a view started from a script in the background inherits it ignored.
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, _interrupt)
    node = rclpy.create_node(f'anyscale_status_{os.getpid()}', context=ctx)
    topics = {p.TOPIC_LAYOUT: latched, p.TOPIC_AGENT_STATE: latched,
              p.TOPIC_EVENTS: 50, p.TOPIC_OBJECTIVE: 10, p.TOPIC_SCALE_STATUS: sensor,
              p.TOPIC_LINK_STATUS: sensor, p.TOPIC_CONNECTION_STATUS: sensor,
              p.TOPIC_DECIDER: beat}
    for topic, qos in topics.items():
        node.create_subscription(
            String, topic, lambda m, t=topic: book.take(t, m.data, time.monotonic()), qos)
    leader = f'{DECIDER}: {deployment.name}'      # the leading decider's diagnostics

    def diagnostics(msg) -> None:
        for st in msg.status:
            if st.name == leader:
                book.take_decider_values({kv.key: kv.value for kv in st.values},
                                         time.monotonic())
    node.create_subscription(DiagnosticArray, p.TOPIC_DIAGNOSTICS, diagnostics, sensor)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)

    def listen(until: float) -> None:
        while time.monotonic() < until:
            executor.spin_once(timeout_sec=min(0.05, max(0.0, until - time.monotonic())))

    try:
        if args.once:
            deadline = time.monotonic() + args.wait
            while time.monotonic() < deadline and not book.complete():
                executor.spin_once(timeout_sec=0.05)
            # a little more so the monitors' periodic readings arrive too
            listen(time.monotonic() + min(1.0, args.wait))
            print(render(book, time.monotonic()))
            if not book.heard_anything:
                print(f'nothing heard within {args.wait:g} s on {listening_text(os.environ)}',
                      file=sys.stderr)
                return 1
            return 0
        with LiveScreen(sys.stdout) as screen:
            while True:
                listen(time.monotonic() + args.interval)
                now = time.monotonic()
                screen.show(render(book, now), now)
    except KeyboardInterrupt:
        return 0
    finally:
        executor.shutdown()
        node.destroy_node()
        shut_rclpy_down(context=ctx)


# The pure view, where it lived before it was split out.
__all__ = ['StatusBook', 'add_arguments', 'render', 'run']
