"""``anyscale-manager demo``: the ICAR 2015 test-bed with a link outage schedule, on one machine.

Builds the test-bed (network namespaces, a shaped link, CPU quotas; or loopback with the link
emulated when there are no rights), runs the default deployment, drives the link through a
schedule modelled on the paper's run while it shows a live status table, then writes the
timeline figure, the event log and a summary, prints where they are, and tears everything down.
``--three-scales`` runs the robot, laptop and edge server of config/three_scales_testbed.yaml
instead (namespaces only), with a schedule that throttles, cuts and restores each link.
``--fleet`` runs two robots sharing one server instead (testbed/fleet_demo.py).
"""

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import replace
from typing import List, Optional

from .. import config_files
from ..model.loader import DeploymentError, load_deployment
from ..view.screen import LiveScreen
from . import schedule as sched

CONFIG_NAME = 'icar2015_testbed.yaml'
THREE_SCALES_NAME = 'three_scales_testbed.yaml'


def default_config(name: str = CONFIG_NAME) -> Optional[str]:
    """The installed share/anyscale_manager/config file, else the source tree's config/."""
    return config_files.find(name)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--duration', type=float, default=None, metavar='SECONDS',
                        help='length of the scheduled run once every node runs (default 60; '
                             'with --fleet 85)')
    parser.add_argument('--out', default='', metavar='FOLDER',
                        help='where to write timeline.png, events.jsonl/txt and summary.json '
                             '(default ./anyscale_demo_<time>)')
    parser.add_argument('--config', default='', metavar='DEPLOYMENT.yaml',
                        help=f'deployment to run (default: the packaged {CONFIG_NAME})')
    parser.add_argument('--three-scales', action='store_true',
                        help=f'run the packaged {THREE_SCALES_NAME} (robot, laptop on '
                             'Ethernet, edge server on WiFi) with a schedule for each link; '
                             'needs network namespaces')
    parser.add_argument('--fleet', action='store_true',
                        help='two robots, each its own deployment, decider and ROS domain, '
                             "share one server (--graph: each robot's graph, the server with "
                             "room for one robot's share of it); the schedule starts "
                             'robots and cuts or restores their links: "0:start@robot_a,'
                             '25:cut@robot_a,40:restore@robot_a,60:start=1@robot_b" (the '
                             'default; start=N: priority N); needs network namespaces')
    parser.add_argument('--graph', choices=('icar', 'worker'), default=None,
                        help='with --fleet, what each robot runs: its own copy of the ICAR '
                             "2015 graph (the default; the server has room for one robot's "
                             'AMCL and AR) or a sensor -> worker -> consumer graph (room for '
                             'one worker)')
    parser.add_argument('--schedule', default='', metavar='STEPS',
                        help='link schedule instead of the paper-like default, e.g. '
                             '"20:cut,35:restore,40:throttle=4000" (seconds after start); '
                             "with several links, name each step's link after @: "
                             '"20:cut@wifi,30:restore@wifi"')
    parser.add_argument('--mode', choices=('auto', 'netns', 'loopback'), default='auto',
                        help='netns needs root; auto falls back to loopback and says so')
    parser.add_argument('--discovery', choices=('multicast', 'server'), default='multicast',
                        help="server: the deployment's discovery.mode server (each scale's "
                             'warden runs a discovery server) on links that carry no '
                             'multicast; needs network namespaces')
    parser.add_argument('--no-migration', action='store_true',
                        help='run the same schedule with decider.migration false (baseline)')
    parser.add_argument('--domain-id', type=int, default=None,
                        help='ROS_DOMAIN_ID for the run (default: $ROS_DOMAIN_ID or 0)')
    parser.add_argument('--refresh', type=float, default=1.0, metavar='SECONDS',
                        help='status table refresh period (default 1)')


def domain_of(args: argparse.Namespace) -> int:
    """The run's ROS domain: --domain-id, else $ROS_DOMAIN_ID, else 0; ValueError saying
    what is wrong."""
    domain = args.domain_id
    if domain is None:
        try:
            domain = int(os.environ.get('ROS_DOMAIN_ID', '0') or 0)
        except ValueError:
            raise ValueError(f'ROS_DOMAIN_ID={os.environ["ROS_DOMAIN_ID"]!r} is not a '
                             'number') from None
    if not 0 <= domain <= 232:
        raise ValueError(f'domain id {domain} out of range 0..232')
    return domain


def _say(text: str, file=None) -> None:
    """Print ``text`` wrapped at words to the terminal's width (99 columns when piped), the
    rest of a long line indented."""
    from .report import wrap_lines
    out = file or sys.stdout
    width = shutil.get_terminal_size((100, 24)).columns - 1 if out.isatty() else 99
    print(wrap_lines(text, max(40, width)), file=out, flush=True)


def _fail(message: str) -> int:
    print(f'anyscale-manager demo: {message}', file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    if args.fleet:
        if args.three_scales or args.config or args.no_migration or args.mode == 'loopback' \
                or args.discovery != 'multicast':
            return _fail('--fleet runs its own two robots in namespaces: leave out '
                         '--three-scales, --config, --no-migration, --discovery and --mode '
                         'loopback')
        from . import fleet_demo
        return fleet_demo.run(args)
    if args.graph is not None:
        return _fail('--graph is what each robot of --fleet runs: add --fleet, or leave it out')
    if args.discovery != 'multicast' and args.mode == 'loopback':
        return _fail('--discovery server runs in network namespaces only: leave out --mode '
                     'loopback')
    from .harness import HarnessError, Options, Testbed
    from .report import draw_timeline, status_table, with_own_reports, write_event_log

    if args.duration is None:
        args.duration = 60.0
    if not args.duration > 0 or args.duration > 24 * 3600:
        return _fail(f'--duration must be between 0 and 86400 s, got {args.duration:g}')
    if not args.refresh > 0:
        return _fail('--refresh must be > 0')
    if args.three_scales and args.config:
        return _fail('--three-scales runs the packaged three-scale file: leave out --config')
    name = THREE_SCALES_NAME if args.three_scales else CONFIG_NAME
    config = args.config or default_config(name)
    if not config:
        return _fail(f'cannot find {name} (not installed, not in a source tree); '
                     'pass --config')
    try:
        deployment = load_deployment(config)
    except DeploymentError as e:
        return _fail(str(e))
    links = [link.name for link in deployment.links]
    many = len(links) > 1
    if many and args.mode == 'loopback':
        return _fail(f'{config} has {len(links)} links: loopback emulates one; use '
                     '--mode netns (root)')
    try:
        if args.schedule:
            steps = sched.parse(args.schedule, links if many else ['', links[0]])
        elif many:
            steps = sched.three_scales_schedule(args.duration)
            sched.check(steps, links)
        else:
            steps = sched.paper_schedule(args.duration)
    except ValueError as e:
        return _fail(f'--schedule: {e}')
    try:
        domain = domain_of(args)
    except ValueError as e:
        return _fail(str(e))
    out = os.path.abspath(args.out or f'anyscale_demo_{time.strftime("%Y%m%d_%H%M%S")}')
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        return _fail(f'cannot create {out}: {e.strerror}')

    parameters = {'decider.migration': 'false'} if args.no_migration else {}
    # Boot with the link cut so every node starts on the robot; the schedule opens the link.
    options = Options(config, domain, mode=args.mode, decider_parameters=parameters,
                      run_dir=os.path.join(out, 'run'), keep_run_dir=True,
                      link_up_at_start=False, discovery=args.discovery)
    try:
        testbed = Testbed(options)
    except (HarnessError, DeploymentError) as e:
        return _fail(str(e))
    print(f'anyscale-manager demo: {config}')
    if any(s.action == 'throttle' for s in steps) and args.mode == 'loopback':
        print('note: throttle steps are skipped on loopback (no bandwidth shaping there)')
    print('starting the test-bed (link down until every node runs on the robot) ...',
          flush=True)
    code = 0
    t0 = t1 = time.monotonic()
    try:
        testbed.start()
        _say(f'mode: {testbed.mode}: {testbed.mode_reason}')
        if testbed.mode == 'netns':
            quotas = ', '.join(f'{s} {c:.2f}' for s, c in testbed.cpu_cores.items())
            rates = ', '.join(f'{link} {testbed.link_state(link)[1] / 1000:g}'
                              for link in links)
            _say(f'CPU quotas: {quotas} cores of this machine (one reference core = '
                 f'{options.reference_core:g} core); links (Mbit/s): {rates}')
            # The agents report one kernel, so the decider says single-machine mode; what it
            # says of scales no quota confines applies to none here.
            _say("each scale's CPU is its own cgroup's usage against its quota, also when "
                 'the decider says single-machine mode (the scales share this kernel)')
        # The run is judged from a steady start: every probe on the robot reports its
        # connection within limits (right after the boot they read 0 Hz until discovery).
        monitored = [c.name for c in testbed.deployment.connections if c.monitored]
        try:
            testbed.wait_for(lambda r: r.settled(time.monotonic(), monitored, 'robot', 0.0),
                             30.0, "every connection within its limits at the robot's probes")
        except HarnessError as e:
            _say(f'note: starting the schedule anyway: {e}')
        up = ', '.join(f'{link} {_up_fraction(steps, args.duration, link, many):.0%}'
                       for link in links)
        _say('schedule: ' + ', '.join(str(s) for s in steps) +
             f' (up: {up} of the run)')
        t0 = time.monotonic()
        testbed.mark('schedule started')
        for link in testbed.master_links():
            testbed.restore(link)
        pending = list(steps)
        next_show = t0
        # One screen redrawn in place on a terminal (left, also on an error or Ctrl-C, with
        # its last frame printed); a plain snapshot every 5 s when piped.
        with LiveScreen(sys.stdout, plain_every_s=5.0) as screen:
            while True:
                now = time.monotonic()
                while pending and now - t0 >= pending[0].at_s:
                    step = pending.pop(0)
                    testbed.apply(step)
                if now - t0 >= args.duration:
                    break
                if now >= next_show:
                    # Wrapped to the screen (one column spare), else to 99 columns.
                    width = screen.size()[0] - 1 if screen.terminal else 99
                    with testbed.lock:
                        table = status_table(testbed.record, now, t0, testbed.mode, width)
                    screen.show(table, now)
                    next_show = now + args.refresh
                time.sleep(0.05)
        t1 = time.monotonic()
        testbed.mark('schedule ended')
        testbed.wait_heard(t1)          # the observers' last lines: the whole run is judged
    except HarnessError as e:
        print(f'anyscale-manager demo: {e}', file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        print('\ninterrupted: tearing down', file=sys.stderr)
        code = 130
        t1 = time.monotonic()
    finally:
        print('stopping every node and tearing the test-bed down ...', flush=True)
        notes = testbed.stop()
    for note in notes:
        _say(f'teardown: {note}', file=sys.stderr)

    record = testbed.record
    # Where each copy runs as its own scale's observer heard its agent: behind a cut link
    # the master's observer no longer hears it.
    seen = with_own_reports(record, testbed.views)
    files = []
    if t1 > t0:
        title = (f'{"three-scale" if many else "ICAR 2015"} test-bed, {testbed.mode}, '
                 f'{"migration disabled" if args.no_migration else "migration on"}')
        files.append(draw_timeline(seen, os.path.join(out, 'timeline.png'), t0, t1, title))
    files.extend(write_event_log(record, out, t0))
    summary = _summary(testbed, seen, t0, t1, steps, args, notes)
    summary_path = os.path.join(out, 'summary.json')
    with open(summary_path, 'w') as f:
        json.dump(summary, f, indent=2, sort_keys=True)
    files.append(summary_path)
    print('')
    _say(f'moves: {summary["moves"]}; time per layout: ' + ', '.join(
        f'{k} {v:.0%}' for k, v in summary['placement_shares'].items()))
    if summary['objective_integral'] is not None:
        _say(f'time-integrated performance (decider objective): '
             f'{summary["objective_integral"]:.1f}')
    where = 'every scale' if many else testbed.deployment.master.name
    _say(f'connections past their Δ: {summary["violations"]} reported by the probes, '
         f'{summary["observed_violations"]} heard by the observer at {where}')
    _say(allowed_dips_text(summary['allowed_dips']))
    print('written:')
    for path in files:
        print(f'  {path}')
    print(f'  node and process logs: {os.path.join(out, "run")}')
    if notes:
        code = code or 1
    return code


def allowed_dips_text(rows: List[dict]) -> str:
    """One line: the connections that went below freq_min within Δ (no violation), how often
    and the longest, as the probe beside the serving subscriber read them."""
    if not rows:
        return 'below freq_min within Δ (allowed): none'
    by: dict = {}
    for row in rows:
        by.setdefault(row['connection'], []).append(row)
    return 'below freq_min within Δ (allowed, shaded in the figure): ' + ', '.join(
        f'{name} {len(found)} time(s), longest {max(r["below_s"] for r in found):.1f} s '
        f'(Δ {found[0]["tolerance_s"]:g} s), down to {min(r["min_rate_hz"] for r in found):g} Hz'
        for name, found in by.items())


def _summary(testbed, seen, t0: float, t1: float, steps, args, notes: List[str]) -> dict:
    from .report import connection_dips, placement_shares
    record = testbed.record
    deployment = testbed.deployment
    with testbed.lock:
        allowed = [x for x in connection_dips(seen, t0, t1) if x.allowed]
        objective = [o for t, o in record.objectives if t0 <= t <= t1]
        violations = record.reported_violations(t0, t1, serving_only=True)
        # The same rule judged on what the harness's observers heard at each scale (readers no
        # agent started: the master's hears every connection into it, another scale's those
        # whose publisher may run there).
        observed = sorted((v for scale, view in testbed.views.items()
                           for v in view.delta_violations(t0, t1, scale)),
                          key=lambda v: v.start)
        return {
            'mode': testbed.mode, 'mode_reason': testbed.mode_reason,
            'duration_s': round(t1 - t0, 2), 'schedule': [str(s) for s in steps],
            'link_up_fraction': {
                link.name: round(_up_fraction(steps, args.duration, link.name,
                                              len(testbed.deployment.links) > 1), 3)
                for link in testbed.deployment.links},
            'migration': not args.no_migration,
            'moves': len(record.moves(t0, t1)),
            'placement_shares': {k: round(v, 3) for k, v in
                                 placement_shares(seen, t0, t1).items()},
            'objective_integral': (objective[-1].integral - objective[0].integral
                                   if len(objective) > 1 else None),
            'violations': len(violations),
            'violation_details': [
                {'connection': v.connection, 'start_s': round(v.start - t0, 2),
                 'end_s': round(v.end - t0, 2), 'tolerance_s': v.tolerance_s,
                 'reported_by': v.source} for v in violations],
            'allowed_dips': [
                {'connection': x.connection, 'start_s': round(x.start - t0, 2),
                 'end_s': round(x.end - t0, 2), 'min_rate_hz': round(x.min_rate_hz, 2),
                 'below_s': round(x.below_s, 2),
                 'tolerance_s': deployment.connection(x.connection).tolerance_s}
                for x in allowed],
            'observed_violations': len(observed),
            'observed_violation_details': [
                {'connection': v.connection, 'start_s': round(v.start - t0, 2),
                 'end_s': round(v.end - t0, 2), 'tolerance_s': v.tolerance_s}
                for v in observed],
            'teardown_notes': notes,
            'observer_problems': record.problems[:20],
        }


def _up_fraction(steps, duration_s: float, link: str, many: bool) -> float:
    """A link's share of the run up: steps name it, or (one link) may name none."""
    if many:
        return sched.up_fraction(steps, duration_s, link)
    return sched.up_fraction([replace(s, link='') for s in steps], duration_s)
