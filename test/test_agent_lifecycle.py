"""The lifecycle driver: which service call the agent makes, and what it does with answers."""

import pytest

from anyscale_manager import protocol
from anyscale_manager import protocol_auth as auth
from anyscale_manager.agent import lifecycle as lc
from anyscale_manager.agent.catalogue import build_catalogue
from anyscale_manager.agent.reconcile import Reconciler
from anyscale_manager.model.loader import load_mapping

from test_agent_supervisor import deployment_dict


def driver(**kw):
    kw.setdefault('change_timeout_s', 2.0)
    return lc.Driver('amcl', backoff_s=0.5, backoff_max_s=4.0, max_failures=3, **kw)


def answer(d, now, state=None, success=None):
    """Make the pending call come back: a get_state label or a change_state result."""
    request = d.pending
    assert request is not None
    if request.kind == 'get':
        d.answered_state(request.serial, state, now)
    else:
        d.answered_change(request.serial, success, now)
    return request


@pytest.mark.parametrize('state,goal,transition', [
    ('unconfigured', 'active', 'configure'), ('inactive', 'active', 'activate'),
    ('active', 'active', None), ('unconfigured', 'inactive', 'configure'),
    ('active', 'inactive', 'deactivate'), ('inactive', 'inactive', None),
    ('active', 'finalized', 'deactivate'), ('inactive', 'finalized', 'cleanup'),
    ('unconfigured', 'finalized', 'unconfigured_shutdown'), ('finalized', 'active', None)])
def test_next_transition(state, goal, transition):
    assert lc.next_transition(state, goal) == transition


def test_unknown_goal_is_refused():
    with pytest.raises(ValueError, match='unknown lifecycle goal'):
        driver().set_goal('asleep')


def test_reachability_is_looked_up_only_when_a_call_is_due():
    """Looking the services up reads the ROS graph: a copy at its goal, one whose call is out
    and one in its backoff make none."""
    asked = []

    def reachable():
        asked.append(1)
        return True
    d = driver()
    d.set_goal(lc.ACTIVE)
    assert d.next_request(0.0, reachable).kind == 'get' and len(asked) == 1
    assert d.next_request(0.1, reachable) is None and len(asked) == 1       # the call is out
    answer(d, 0.1, state='active')
    for t in (0.2, 0.3, 5.0):
        assert d.next_request(t, reachable) is None
    assert len(asked) == 1 and d.at_goal
    d.set_goal(lc.INACTIVE)
    assert d.next_request(6.0, reachable).transition == 'deactivate' and len(asked) == 2
    assert d.next_request(6.1, lambda: False) is None


def test_a_new_copy_is_read_then_configured_then_activated():
    d = driver()
    d.set_goal(lc.ACTIVE)
    assert d.next_request(0.0, reachable=False) is None      # its services not up yet
    r = d.next_request(0.1, reachable=True)
    assert r.kind == 'get'
    assert d.next_request(0.2, reachable=True) is None       # one call at a time
    answer(d, 0.2, state='unconfigured')
    r = d.next_request(0.2, True)
    assert (r.kind, r.transition, r.transition_id) == ('change', 'configure', 1)
    answer(d, 0.3, success=True)
    assert d.state == lc.INACTIVE
    r = d.next_request(0.3, True)
    assert (r.transition, r.transition_id) == ('activate', 3)
    answer(d, 0.31, success=True)
    assert d.at_goal and d.next_request(0.4, True) is None
    # Moved away: deactivated, and nothing more.
    d.set_goal(lc.INACTIVE)
    assert d.next_request(1.0, True).transition == 'deactivate'
    answer(d, 1.0, success=True)
    assert d.state == lc.INACTIVE and d.next_request(1.1, True) is None


def test_a_copy_may_be_serving_from_the_activation_asked_until_it_is_seen_inactive():
    """What a shared scale's claim counts as serving (turn._may_serve): a copy mid-transition
    or whose activation timed out may be active; one never asked to activate is not."""
    d = driver()
    assert not d.may_be_active                               # started, nothing known
    d.set_goal(lc.INACTIVE)
    d.next_request(0.0, True)
    answer(d, 0.0, state='unconfigured')
    d.next_request(0.0, True)
    answer(d, 0.1, success=True)
    assert d.state == lc.INACTIVE and not d.may_be_active    # a standby
    d.set_goal(lc.ACTIVE)
    assert d.next_request(0.2, True).transition == 'activate'
    assert d.may_be_active                                   # asked: it may be active now
    assert d.next_request(2.3, True).kind == 'get'           # timed out: checked at once
    assert d.may_be_active
    answer(d, 2.4, state='activating')                       # mid-transition: still may be
    assert d.state != lc.ACTIVE and d.may_be_active
    d.next_request(3.3, True)
    answer(d, 3.3, state='active')
    d.set_goal(lc.INACTIVE)
    assert d.next_request(3.4, True).transition == 'deactivate'
    assert d.may_be_active                                   # until the answer
    assert d.next_request(5.5, True).kind == 'get'
    answer(d, 5.6, state='deactivating')
    assert d.may_be_active
    d.next_request(6.5, True)
    answer(d, 6.5, state='inactive')
    assert not d.may_be_active
    d.reset()                                                # a new process
    d.next_request(7.0, True)
    answer(d, 7.0, state='errorprocessing')
    assert not d.may_be_active                               # never asked to activate
    d.reset()                                                # adopted, mid-transition
    d.next_request(8.0, True)
    answer(d, 8.0, state='deactivating')
    assert d.may_be_active


def test_finalizing_goes_through_deactivate_cleanup_and_shutdown():
    d = driver()
    d.set_goal(lc.FINALIZED)
    assert d.next_request(0.0, True).kind == 'get'
    answer(d, 0.0, state='active')
    seen = []
    for t in range(5):
        r = d.next_request(float(t), True)
        if r is None:
            break
        seen.append(r.transition)
        answer(d, float(t), success=True)
    assert seen == ['deactivate', 'cleanup', 'unconfigured_shutdown']
    assert d.state == lc.FINALIZED and d.at_goal


def test_a_refused_transition_is_checked_retried_with_backoff_then_given_up():
    d = driver()
    d.set_goal(lc.ACTIVE)
    d.next_request(0.0, True)
    answer(d, 0.0, state='inactive')
    assert d.next_request(0.0, True).transition == 'activate'
    answer(d, 0.0, success=False)
    assert d.failures == 1 and 'activate refused by the node' in d.problem
    assert d.events[-1][0] == 'warn' and 'retry 1 of 2 in 0.5 s' in d.events[-1][1]
    # Checked at once with get_state; the retry waits for its backoff.
    assert d.next_request(0.0, True).kind == 'get'
    answer(d, 0.0, state='inactive')
    assert d.next_request(0.4, True) is None
    assert d.next_request(0.5, True).transition == 'activate'
    answer(d, 0.5, success=False)
    d.next_request(0.5, True)
    answer(d, 0.5, state='inactive')
    assert d.next_request(1.4, True) is None                  # 1 s backoff now
    assert d.next_request(1.5, True).transition == 'activate'
    answer(d, 1.5, success=False)
    assert d.failed and d.events[-1][0] == 'error' and 'giving up' in d.events[-1][1]
    assert d.next_request(100.0, True) is None
    # A new process starts afresh.
    d.reset()
    assert not d.failed and d.next_request(100.0, True).kind == 'get'


def test_a_timed_out_change_is_checked_with_get_state_and_may_have_happened():
    d = driver(change_timeout_s=2.0)
    d.set_goal(lc.ACTIVE)
    d.next_request(0.0, True)
    answer(d, 0.0, state='inactive')
    late = d.next_request(0.0, True)
    assert late.transition == 'activate'
    assert d.next_request(1.9, True) is None
    r = d.next_request(2.0, True)         # not answered within 2 s: look
    assert r.kind == 'get' and 'not answered within 2 s' in d.problem and d.failures == 1
    d.answered_change(late.serial, True, 2.05)    # the late answer is ignored...
    assert d.state == lc.INACTIVE
    answer(d, 2.1, state='active')                # ...get_state says it did happen
    assert d.at_goal and d.failures == 0 and d.problem == ''


def test_an_unanswered_get_state_is_asked_again_without_counting():
    d = driver()
    d.set_goal(lc.INACTIVE)
    d.next_request(0.0, True)
    assert d.next_request(0.99, True) is None
    assert d.next_request(1.0, True).kind == 'get'
    assert d.failures == 0


def test_a_transition_in_progress_is_looked_at_again_later():
    d = driver()
    d.set_goal(lc.ACTIVE)
    d.next_request(0.0, True)
    answer(d, 0.0, state='activating')
    assert d.next_request(0.1, True) is None
    assert d.next_request(0.5, True).kind == 'get'


def test_a_finalized_copy_with_a_live_goal_gives_up_at_once():
    d = driver()
    d.set_goal(lc.ACTIVE)
    d.next_request(0.0, True)
    answer(d, 0.0, state='finalized')
    assert d.next_request(0.0, True) is None
    assert d.failed and 'cannot become active' in d.problem


def test_a_lost_call_is_a_failure_for_a_change_only():
    d = driver()
    d.set_goal(lc.ACTIVE)
    r = d.next_request(0.0, True)
    d.lost(r.serial, 'client gone', 0.0)
    assert d.failures == 0 and d.next_request(0.1, True) is None
    assert d.next_request(0.5, True).kind == 'get'
    answer(d, 0.5, state='inactive')
    r = d.next_request(0.5, True)
    d.lost(r.serial, 'RCLError: x', 0.5)
    assert d.failures == 1 and 'activate failed: RCLError' in d.problem


def test_no_goal_means_only_looking():
    d = driver()
    r = d.next_request(0.0, True)
    answer(d, 0.0, state='active')
    assert r.kind == 'get' and d.next_request(0.1, True) is None and d.state == lc.ACTIVE


@pytest.mark.parametrize('state,goal,proc,want', [
    ('active', lc.ACTIVE, 'running', ('running', True)),
    ('inactive', lc.ACTIVE, 'running', ('starting', False)),
    ('inactive', lc.INACTIVE, 'running', ('standby', False)),
    ('unconfigured', lc.INACTIVE, 'starting', ('standby', False)),
    ('active', lc.INACTIVE, 'running', ('running', True)),    # serves until deactivated
    ('inactive', None, 'running', ('standby', False)),        # adopted, not yet told
    ('unknown', None, 'starting', ('starting', False)),
    ('inactive', lc.FINALIZED, 'running', ('stopping', False)),
    ('active', lc.FINALIZED, 'running', ('stopping', False)),
    ('inactive', lc.ACTIVE, 'backoff', ('backoff', False)),
])
def test_what_the_agent_reports_of_a_lifecycle_copy(state, goal, proc, want):
    d = driver()
    d.state = state
    d.goal = goal
    got = lc.report(proc, proc == 'running', '', d)
    assert got[:2] == want
    assert got[3] == (state if proc in ('starting', 'running') else None)


def standby_deployment():
    return load_mapping(deployment_dict({
        'loc': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'lifecycle': True,
                'standby': True},
        'rec': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'lifecycle': True,
                'standby': ['b']},
        'plain': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0},
    }))


def test_lifecycle_copies_get_their_services_remapped_per_scale():
    d = standby_deployment()
    for scale in ('a', 'b'):
        cat = build_catalogue(d, scale, {'PATH': '/usr/bin'})
        loc = cat['loc']
        assert loc.lifecycle and loc.services == f'/loc/{scale}'
        for name in ('change_state', 'get_state', 'get_available_states',
                     'get_available_transitions', 'get_transition_graph', 'transition_event'):
            i = loc.argv.index(f'~/{name}:=~/{scale}/{name}')
            assert loc.argv[i - 1] == '-r'
        plain = cat['plain']
        assert not plain.lifecycle and not plain.services
        assert not any(a.startswith('~/') for a in plain.argv)


def test_standby_copies_are_kept_where_listed_and_moves_keep_the_handover():
    d = standby_deployment()
    a = Reconciler(d, 'a', ['loc', 'rec', 'plain'], readiness_timeout_s=10.0,
                   agent_timeout_s=3.0)
    b = Reconciler(d, 'b', ['loc', 'rec', 'plain'], readiness_timeout_s=10.0,
                   agent_timeout_s=3.0)
    assert a.standby_here == {'loc'} and b.standby_here == {'loc', 'rec'}
    layout = protocol.Layout(generation=1, deployment='unit', reason='', stamp=0.0,
                             assignments={'loc': 'b', 'rec': 'a', 'plain': 'a'})
    a.apply_layout(layout, 0.0)
    # 'a' serves loc (active) until b reports it running and ready; a standby copy on b
    # reported as 'standby' is not a live copy there.
    assert a.desired(0.1, {'loc', 'plain'}) == {'loc', 'plain', 'rec'}
    a.peer_state(protocol.AgentState(scale='b', generation=1, stamp=0.0, nodes={
        'loc': protocol.NodeReport(state='standby', pid=9, since=0.0, restarts=0, ready=False,
                                   exit_reason='', lifecycle='inactive')}), 0.2)
    assert 'loc' in a.desired(0.2, {'loc', 'plain'})
    assert a.copies_elsewhere('loc', 0.2) == 0
    a.peer_state(protocol.AgentState(scale='b', generation=1, stamp=0.0, nodes={
        'loc': protocol.NodeReport(state='running', pid=9, since=0.0, restarts=0, ready=True,
                                   exit_reason='', lifecycle='active')}), 0.3)
    assert a.desired(0.3, {'loc', 'plain'}, heard_here=lambda n, s: True) == {'plain', 'rec'}


def test_goals_follow_the_layout_and_keep_live_copies_before_the_first_one():
    names = ['amcl', 'ar', 'old']
    goals, run = lc.goals(names, {'amcl'}, ['ar'], has_layout=True, live=['old'])
    assert goals == {'amcl': lc.ACTIVE, 'ar': lc.INACTIVE, 'old': lc.FINALIZED}
    assert run == {'amcl', 'ar'}                       # the standby copy's process runs too
    # A restarted agent before its first layout: the live copies keep what they report.
    goals, run = lc.goals(names, set(), ['ar'], has_layout=False, live=['amcl', 'old'])
    assert goals == {'amcl': None, 'ar': lc.INACTIVE, 'old': None}
    assert run == {'amcl', 'ar', 'old'}


# An agent's report as every reader has decoded it, byte for byte: the states are words of the
# wire, whatever type the agent holds them in.
AGENT_STATE_JSON = (
    '{"decider":"d1","generation":7,"host":"robot-1","host_id":"h",'
    '"instance":"0123456789abcdef","nodes":{'
    '"amcl":{"exit_reason":"","lifecycle":"inactive","pid":4242,"ready":false,"restarts":1,'
    '"since":1700000000.25,"state":"standby"},'
    '"planner":{"exit_reason":"","lifecycle":"active","pid":4343,"ready":true,"restarts":0,'
    '"since":1700000001.5,"state":"running"},'
    '"talker":{"exit_reason":"killed by SIGKILL (Killed)","lifecycle":null,"pid":0,'
    '"ready":false,"restarts":3,"since":1700000002.0,"state":"backoff"}},'
    '"scale":"robot","seq":12,"stamp":1700000003.125,"term":2}')


def pinned_report():
    d = driver()
    d.state, d.goal = lc.INACTIVE, lc.INACTIVE
    standby = lc.report(protocol.ProcState.RUNNING, True, '', d)
    d.state, d.goal = lc.ACTIVE, lc.ACTIVE
    serving = lc.report(protocol.ProcState.RUNNING, True, '', d)
    nodes = {name: protocol.NodeReport(state=state, pid=pid, since=since, restarts=restarts,
                                       ready=ready, exit_reason=reason, lifecycle=label)
             for name, (state, ready, reason, label), pid, since, restarts in [
                 ('amcl', standby, 4242, 1700000000.25, 1),
                 ('planner', serving, 4343, 1700000001.5, 0),
                 ('talker', (protocol.ProcState.BACKOFF, False, 'killed by SIGKILL (Killed)',
                             None), 0, 1700000002.0, 3)]}
    return protocol.AgentState(scale='robot', generation=7, stamp=1700000003.125, nodes=nodes,
                               decider='d1', instance='0123456789abcdef', seq=12, host_id='h',
                               host='robot-1', term=2)


def test_an_agent_state_report_is_the_same_json_and_reads_back_as_states():
    report = pinned_report()
    assert report.to_json() == AGENT_STATE_JSON
    key = b'k' * 32
    assert auth.seal(key, report) == auth.seal(key, protocol.AgentState.from_json(
        AGENT_STATE_JSON))
    back = protocol.AgentState.from_json(AGENT_STATE_JSON)
    assert back.to_json() == AGENT_STATE_JSON
    amcl = back.nodes['amcl']
    assert amcl.state is protocol.ProcState.STANDBY and amcl.state == 'standby'
    assert amcl.lifecycle is protocol.LifecycleState.INACTIVE
    assert back.nodes['talker'].lifecycle is None
    assert set(back.running()) == {'planner'}


@pytest.mark.parametrize('field,word,expected', [
    ('state', 'zombie', 'AgentState.nodes.talker.state: expected one of starting, running, '
                        "stopping, stopped, crashed, backoff, failed, standby, got 'zombie'"),
    ('state', 'Running', 'AgentState.nodes.talker.state: expected one of starting'),
    ('state', 3, 'AgentState.nodes.talker.state: expected a string, got 3'),
    ('lifecycle', 'asleep', 'AgentState.nodes.talker.lifecycle: expected one of unknown, '
                            'unconfigured, inactive, active, finalized, configuring'),
])
def test_an_unknown_state_from_the_wire_is_refused_with_the_words_it_may_be(
        field, word, expected):
    import json
    data = json.loads(AGENT_STATE_JSON)
    data['nodes']['talker'][field] = word
    with pytest.raises(protocol.ProtocolError) as caught:
        protocol.AgentState.from_json(json.dumps(data))
    assert str(caught.value).startswith(expected)


def test_a_label_outside_the_lifecycle_state_machine_is_read_again():
    d = driver()
    d.set_goal(lc.ACTIVE)
    assert d.next_request(0.0, True).kind == 'get'
    answer(d, 0.0, state='dozing')
    assert d.state is lc.UNKNOWN and not d.known
    assert d.next_request(0.4, True) is None
    assert d.next_request(0.5, True).kind == 'get'
    answer(d, 0.5, state='configuring')
    assert d.next_request(0.6, True) is None
    assert d.state is protocol.LifecycleState.CONFIGURING and d.known
