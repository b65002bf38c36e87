"""The agent's turn hands a copy its node's state before it serves (agent/turn.py with
agent/state.py), without ROS: a hand-written clock, real short processes, lifecycle services
that answer at once and a restore channel of the test's own."""

import dataclasses

import pytest

from anyscale_manager import protocol as p
from anyscale_manager.agent import lifecycle as lc
from anyscale_manager.agent.turn import (AgentInputs, AgentTurn, FIRST_STATE_WAIT_S,
                                         IDLE_TICK_S, STOPPING_TICK_S)
from anyscale_manager.model.loader import load_mapping
from test_agent_supervisor import deployment_dict
from test_agent_turn import WALL_OFFSET, layout, lifecycle_entry

STATE = {'topic': '/lc/out', 'restore': '/lc_restore', 'msg_type': 'std_msgs/msg/Int64'}


class Channel:
    """The restore topics of the copies: whether each copy subscribes, what was sent, and
    whether the copy acknowledged it."""

    def __init__(self):
        self.subscribed = False
        self.acked = False
        self.sent = []
        self.topics = []          # each topic asked for, in order

    def ready(self, name, topic):
        if topic not in self.topics:
            self.topics.append(topic)
        return self.subscribed

    def send(self, name, topic, data):
        self.sent.append((name, data))
        if topic not in self.topics:
            self.topics.append(topic)

    def delivered(self, name, topic):
        return self.acked


class Agent:
    def __init__(self, make_sup, timeout_s=5.0):
        d = load_mapping(deployment_dict({
            'lc': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0, 'lifecycle': True,
                   'standby': True, 'state': STATE},
            'other': {'launch': {'command': ['sleep', '5']}, 'cpu': 1.0},
        }, names=['lc', 'other']))
        d = dataclasses.replace(d, agent=dataclasses.replace(d.agent,
                                                             lifecycle_timeout_s=timeout_s))
        entry = dataclasses.replace(lifecycle_entry(), state_topic=STATE['topic'],
                                    restore_topic='/lc/a/restore')
        self.now = 100.0
        self.sup = make_sup([entry])
        self.turn = AgentTurn(d, 'a', {'lc': entry}, self.sup, instance='me',
                              wall_offset=WALL_OFFSET)
        self.turn.begin(self.now)
        self.channel = Channel()
        self.heard = []
        self.labels = {}

    def label(self):
        return self.labels.get(self.sup.pids().get('lc', 0), 'unconfigured')

    def poll(self, name):
        driver = self.turn.drivers[name]
        request = driver.next_request(self.now, reachable=True)
        if request is None:
            return
        if request.kind == 'get':
            driver.answered_state(request.serial, self.label(), self.now)
        else:
            self.labels[self.sup.pids().get(name, 0)] = lc.TRANSITIONS[request.transition][1]
            driver.answered_change(request.serial, True, self.now)

    def step(self, dt=0.1):
        self.now += dt
        heard, self.heard = self.heard, []
        return self.turn.step(self.now, AgentInputs(wall=self.now + WALL_OFFSET, poll=self.poll,
                                                    heard=heard, restore=self.channel))

    def until(self, cond, what, steps=300):
        outs = []
        for _ in range(steps):
            out = self.step()
            outs.append(out)
            if cond(out):
                return outs
        raise AssertionError(f'{what}: not within {steps} steps')


def lines(outs):
    return [text for out in outs for _, text in out.logs]


def test_a_copy_is_handed_the_latest_state_and_activated_only_once_it_took_it(make_sup):
    agent = Agent(make_sup)
    agent.heard = [('lc', b'old', 1), ('lc', b'latest', 2)]
    agent.step()
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    outs = agent.until(lambda out: agent.label() == lc.INACTIVE, 'the copy configured')
    assert agent.channel.sent == []              # its restore input is not there yet
    outs += agent.until(lambda out: True, 'one step')
    assert any('waiting for its restore input (/lc/a/restore/i' in t for t in lines(outs))
    agent.channel.subscribed = True
    out = agent.step()
    assert agent.channel.sent == [('lc', b'latest')]
    assert out.goals == {'lc': lc.INACTIVE} and out.tick_s == STOPPING_TICK_S
    assert any('lc: state of ' in t and 'handed to the copy (pid ' in t for t in lines([out]))
    for _ in range(3):                           # not acknowledged: still held, sent once
        assert agent.step().goals == {'lc': lc.INACTIVE}
    assert len(agent.channel.sent) == 1 and agent.label() == lc.INACTIVE
    agent.channel.acked = True
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    assert len(agent.channel.sent) == 1
    # Serving: nothing more is sent, and the next spell of serving is handed the state anew.
    agent.heard = [('lc', b'newer', 3)]
    agent.step()
    assert len(agent.channel.sent) == 1
    agent.turn.on_layout(layout(2, lc='b'), agent.now)          # moved away: standby here
    agent.until(lambda out: agent.label() == lc.INACTIVE, 'the copy deactivated')
    agent.turn.on_layout(layout(3, lc='a'), agent.now)          # and back
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated again')
    assert agent.channel.sent[-1] == ('lc', b'newer')


def test_a_state_kept_asks_for_no_step_and_one_heard_between_steps_is_handed_on(make_sup):
    """The states are taken between steps (hear_states, the agent's own job): a settled
    agent that keeps a node's state steps at IDLE_TICK_S like any other, and what it heard
    meanwhile is what the next serving copy gets."""
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy active')
    agent.step(dt=31.0)                  # past the look for its DDS ports (test_agent_turn)
    assert agent.step().tick_s == IDLE_TICK_S
    assert agent.turn.hear_states([('lc', b'between 1', 8), ('lc', b'between 2', 9)],
                                  agent.now) == []
    agent.turn.on_layout(layout(2, lc='b'), agent.now)          # moved away: standby here
    agent.until(lambda out: agent.label() == lc.INACTIVE, 'the copy deactivated')
    agent.turn.on_layout(layout(3, lc='a'), agent.now)          # and back
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated again')
    assert agent.channel.sent[-1] == ('lc', b'between 2')


def test_a_restarted_copy_is_handed_the_state_of_the_one_that_died(make_sup):
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the first copy active')
    first = agent.sup.pids()['lc']
    agent.heard = [('lc', b'count 41', 7)]
    agent.step()
    agent.sup.restart('lc', agent.now, 'a test')         # as a crash would
    agent.until(lambda out: agent.sup.pids().get('lc', 0) not in (0, first)
                and agent.label() == lc.ACTIVE, 'the restarted copy active')
    assert agent.channel.sent[-1] == ('lc', b'count 41')
    # Each process has a restore topic of its own: the killed one's reader, which DDS counts
    # until its lease ends, cannot hold up the acknowledgement of the next.
    topics = agent.channel.topics
    assert len(topics) == 2 and all(t.startswith('/lc/a/restore/i') for t in topics), topics


def test_with_no_state_heard_a_copy_starts_from_its_own_and_that_is_said(make_sup):
    agent = Agent(make_sup)
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    outs = agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    assert agent.channel.sent == []
    assert any('no state heard yet on /lc/out' in t for t in lines(outs))


def test_a_copy_that_never_takes_its_state_serves_without_it_after_the_timeout(make_sup):
    agent = Agent(make_sup, timeout_s=1.0)
    agent.heard = [('lc', b'x', 1)]
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    outs = agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    warned = [t for out in outs for level, t in out.logs if level == 'warn']
    assert any('did not take its state on /lc_restore' in t and 'within 1 s' in t
               for t in warned), warned
    assert agent.channel.sent == []


@pytest.mark.parametrize('size, kept', [(10, True), (100000, False)])
def test_the_state_kept_is_bounded(make_sup, size, kept):
    agent = Agent(make_sup)
    agent.heard = [('lc', b'x' * size, 1)]
    out = agent.step()
    assert (agent.turn.states.latest('lc') is not None) == kept
    assert any('state_max_bytes' in t for _, t in out.logs) != kept


def test_what_others_publish_on_the_restore_topic_is_the_state_from_then_on(make_sup):
    """A pose set in RViz on /initialpose: the copies' inputs are remapped, so the agent hands it
    over. A standby copy gets nothing at once; it is the node's latest state, so the copy that
    takes over is handed it, not what the serving copy published before it took the set one;
    once serving, the copy gets what is set at once."""
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='b'), agent.now)         # standby here
    agent.until(lambda out: agent.label() == lc.INACTIVE, 'the standby copy configured')
    agent.heard = []
    agent.now += 0.1
    agent.turn.step(agent.now, AgentInputs(wall=0.0, poll=agent.poll,
                                           requests=[('lc', b'set by a person')],
                                           restore=agent.channel))
    assert agent.channel.sent == []
    assert agent.turn.states.latest('lc').data == b'set by a person'
    # The serving copy elsewhere has not taken it yet: what it publishes meanwhile is not kept.
    agent.heard = [('lc', b'its old track', 7)]
    agent.turn.on_layout(layout(2, lc='a'), agent.now)         # serving here
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    assert agent.channel.sent == [('lc', b'set by a person')]   # its hand-over
    agent.now += 0.1
    out = agent.turn.step(agent.now, AgentInputs(wall=0.0, poll=agent.poll,
                                                 requests=[('lc', b'set again')],
                                                 restore=agent.channel))
    assert agent.channel.sent[-1] == ('lc', b'set again')
    assert any('a message on /lc_restore handed to its copy here' in t for _, t in out.logs)


def test_a_pose_set_before_the_serving_copys_restore_input_is_matched_reaches_it_then(
        make_sup):
    """The copy serves (it started from its own: nothing was heard yet), and its restore input
    is not matched yet when a pose is set (a busy robot at a boot): the pose goes to it as
    soon as it is, not never."""
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='a'), agent.now)         # serving here
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    agent.channel.subscribed = False
    agent.now += 0.1
    agent.turn.step(agent.now, AgentInputs(wall=0.0, poll=agent.poll,
                                           requests=[('lc', b'set by a person')],
                                           restore=agent.channel))
    assert agent.channel.sent == []
    agent.step()
    assert agent.channel.sent == []
    agent.channel.subscribed = True
    agent.step()
    assert agent.channel.sent == [('lc', b'set by a person')]
    agent.step()
    assert agent.channel.sent == [('lc', b'set by a person')]      # once


def test_a_pose_set_while_a_copy_waits_for_its_hand_over_reaches_that_copy(make_sup):
    """Set after the copy was sent the last state, before it took it and was activated: it is
    sent the set pose too (it would otherwise serve on the old track beside the copy that took
    the set pose)."""
    agent = Agent(make_sup)
    agent.channel.subscribed = True
    agent.channel.acked = False                                 # the hand-over waits
    agent.heard = [('lc', b'pose 1', 1)]
    agent.turn.on_layout(layout(1, lc='a'), agent.now)
    agent.until(lambda out: agent.channel.sent == [('lc', b'pose 1')], 'the state sent')
    assert agent.label() == lc.INACTIVE
    agent.heard = []
    agent.now += 0.1
    agent.turn.step(agent.now, AgentInputs(wall=0.0, poll=agent.poll,
                                           requests=[('lc', b'set by a person')],
                                           restore=agent.channel))
    assert agent.channel.sent == [('lc', b'pose 1'), ('lc', b'set by a person')]


@pytest.mark.parametrize('there, waits', [
    (p.ProcState.RUNNING, True), (p.ProcState.STARTING, True), (p.ProcState.BACKOFF, False),
    (p.ProcState.STANDBY, False)])
def test_with_no_state_heard_yet_a_move_waits_for_the_first_state_of_the_copy_it_replaces(
        make_sup, there, waits):
    """This agent has heard no state yet (it just started, or its link just came up, as at the
    test-bed's first move out): the copy the layout moves the node from serves on meanwhile and
    its state is on its way, so the copy here waits for it instead of serving from its own (a
    stale pose beside the right one). So does a copy still starting there (a layout that moved
    the node away while that copy was being activated, as at a boot with the link up): its agent
    activates it and keeps it serving until this copy is heard there, so serving from its own
    here would leave two copies serving two states. A copy its agent reports crashed, or kept
    as a standby, sends nothing, and the copy here serves at once."""
    from test_agent_turn import peer_report
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='b'), agent.now)            # a standby copy here
    agent.until(lambda out: agent.label() == lc.INACTIVE, 'the standby copy configured')
    agent.turn.on_agent_state(peer_report('b', 1, lc=there), agent.now)
    agent.turn.on_layout(layout(2, lc='a'), agent.now)            # moved here from b
    outs = []
    for _ in range(5):
        agent.turn.on_agent_state(peer_report('b', 1, lc=there), agent.now)
        outs.append(agent.step())
    if not waits:
        assert agent.label() == lc.ACTIVE and agent.channel.sent == []
        assert any('no state heard yet' in t for t in lines(outs))
        return
    assert agent.label() == lc.INACTIVE
    assert any('waiting for the first state of its copy on b' in t for t in lines(outs))
    agent.heard = [('lc', b'from b', 1)]                          # its first state arrives
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    assert agent.channel.sent == [('lc', b'from b')]


def test_while_the_copy_it_replaces_is_reported_serving_a_move_waits_longer_for_its_state(
        make_sup):
    """A move out as a link opens (the three-scale test-bed: both master links at once, the
    robot saturated): the copy there serves on, reported so by its agent, and its state writer
    may take seconds to be found across the link. The copy here waits past FIRST_STATE_WAIT_S
    for it, up to half of readiness_timeout_s, then serves from its own and says so."""
    from test_agent_turn import peer_report
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(1, lc='b'), agent.now)
    agent.until(lambda out: agent.label() == lc.INACTIVE, 'the standby copy configured')
    agent.turn.on_layout(layout(2, lc='a'), agent.now)            # moved here from b
    moved = agent.now
    limit = agent.turn.deployment.agent.readiness_timeout_s / 2.0
    assert limit > FIRST_STATE_WAIT_S + 1.0
    outs = []
    while agent.now - moved < FIRST_STATE_WAIT_S + 1.0:
        agent.turn.on_agent_state(peer_report('b', 2, lc=p.ProcState.RUNNING), agent.now)
        outs.append(agent.step())
    assert agent.label() == lc.INACTIVE, 'served from its own while the copy there serves'
    while agent.label() != lc.ACTIVE:
        assert agent.now - moved < limit + 1.0, 'still waiting past half the readiness timeout'
        agent.turn.on_agent_state(peer_report('b', 2, lc=p.ProcState.RUNNING), agent.now)
        outs.append(agent.step())
    assert agent.now - moved >= limit
    assert any('no state heard yet' in t for t in lines(outs)) and agent.channel.sent == []


def test_an_agent_whose_first_layout_is_not_the_first_waits_for_the_state_of_the_serving_copy(
        make_sup):
    """The laptop's agent whose link came up after the first layouts hears generation 2 first,
    which places the node here: where it served before is not known here, and a copy serving
    there (the robot's, with the user's pose) sends its state within a discovery round. The copy
    here waits for it instead of serving from its own start pose beside it (seen on the
    three-scale test-bed: the robot's and the laptop's copies served poses 0.2 m apart for
    2.5 s). Nothing heard within FIRST_STATE_WAIT_S: it serves from its own, and says so."""
    agent = Agent(make_sup)
    agent.channel.subscribed = agent.channel.acked = True
    agent.turn.on_layout(layout(2, lc='a'), agent.now)
    outs = agent.until(lambda out: agent.label() == lc.INACTIVE, 'the copy configured')
    outs += [agent.step() for _ in range(5)]
    assert agent.label() == lc.INACTIVE
    assert any('waiting for the first state of its copy serving before this agent heard a '
               'layout' in t for t in lines(outs))
    agent.heard = [('lc', b'from the robot', 1)]
    agent.until(lambda out: agent.label() == lc.ACTIVE, 'the copy activated')
    assert agent.channel.sent == [('lc', b'from the robot')]

    late = Agent(make_sup)
    late.turn.on_layout(layout(2, lc='a'), late.now)
    outs = late.until(lambda out: late.label() == lc.ACTIVE, 'the copy activated', steps=60)
    assert any('no state heard yet' in t for t in lines(outs))
    assert late.now - 100.0 >= FIRST_STATE_WAIT_S
