"""The chaos soak, short: three minutes of faults on the test-bed, every count 0 (root only).

One fault of every kind from a fixed seed (7), one after the other with 3-5 s between them: a
link cut, a throttle, a flapping link, SIGKILL of the laptop's agent, of the robot's agent, of
the leading decider (a second one stands by throughout) and of a managed node (each restarted
after 1 s, as systemd would), the laptop's agent SIGKILLed and kept away for 15 s (its nodes
must stop by themselves), SIGHUP of each agent (a restart in place: nothing may move or
restart), a crash loop of one node (its serving copy SIGKILLed three times; no Δ is excused
where a standby copy could take over), SIGSTOP of the leading decider for a few seconds, a
hostile publisher (forged, replayed and malformed layouts and states; the deployment is
signed) and a third decider started. The judges (anyscale_manager/testbed/chaos.py and
verdict.py, rules in docs/testbed.md) read what the harness's observer heard at the robot and
what was left after the teardown. ``bench/soak.py`` runs the long version (10 minutes, any
seed)."""

import os

import pytest

from anyscale_manager.testbed import chaos, netns, soak

from conftest import TESTBED

SEED = 7
DURATION_S = 180.0     # seed 7: the same 14 faults as with more, the last one over at 179.6 s
OK, WHY = netns.available()
pytestmark = pytest.mark.skipif(not OK, reason=f'no test-bed here: {WHY}')


@pytest.mark.timeout(540)
def test_a_short_chaos_soak_loses_nothing_and_leaves_nothing():
    lines = []

    def log(text):
        lines.append(text)
        print(text, flush=True)
    report = soak.run(soak.SoakOptions(
        TESTBED, int(os.environ['ROS_DOMAIN_ID']), SEED, duration_s=DURATION_S,
        ensure_each=True, gap_s=(3.0, 5.0), log=log))
    text = soak.format_report(report)
    print(text)
    where = f'\n{text}\nrun folder: {report["run_dir"]}'
    assert sorted(r['kind'] for r in report['faults']) == sorted(chaos.KINDS), where
    assert report['counts'] == {k: 0 for k in report['counts']}, where
    # Every fault that left something to react to was reacted to.
    skipped = [r for r in report['faults'] if r['outcome'].startswith('skipped')]
    assert skipped == [], where
    timed = {k for k, row in report['reactions'].items() if row['timed']}
    assert {'kill_agent_laptop', 'kill_agent_robot', 'kill_decider', 'stop_decider',
            'kill_node', 'rival_decider'} <= timed, where
