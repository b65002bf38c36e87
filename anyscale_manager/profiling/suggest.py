"""The documented rule that turns a measured rate into suggested ICAR thresholds.

Only suggestions: the profile sees what a connection did, not what its subscriber needs. The
rule (docs/profile.md) is chosen so that the run that was watched never violates it, while a
connection that falls below half its usual rate for longer than Δ does:

- ``freq_opt_hz``: the median (p50) reading, to 2 significant digits when that is within 1 %
  of it (10.1 Hz reads 10 Hz), else to 3;
- ``freq_min_hz``: half of ``freq_opt_hz``, to 2 significant digits (the shipped test-bed's
  minimums are about half their optimal rates: 5 of 10 Hz, 2 of 5 Hz);
- ``tolerance_s`` (Δ): the largest of 2 s (above what a cold move of a plain node costs after a
  link cut, about 1.55 s with the default heartbeats: ``model.advice.cold_move_budget_s``, so
  validate has nothing to warn about), 3 periods at ``freq_min_hz`` (three missed messages of a
  slow topic are not an outage), and twice the longest stretch the watched run itself spent
  below ``freq_min_hz``; rounded up to 0.5 s. Never 0: Δ = 0 pins both ends to the master
  (critical), a decision the profile leaves to the user;
- ``bandwidth_kbps``: p50 rate x mean serialized message size, rounded up to 3 significant
  digits (the payload only: RTPS, UDP and IP headers come on top).

A connection with fewer than 3 readings (a latched or one-shot topic, a topic that started at
the end of the watch) or a median of 0 gets no thresholds: it stays unmonitored.

A node's launch (``suggest_launch``) is the command line its process ran, less what an agent
adds when it starts a copy itself: the remaps that move a lifecycle node's services and
transition topic under the scale's name (``-r ~/change_state:=~/robot/change_state``, ...). The
agent adds them again on whichever scale it starts the node, so a launch that carried them
would serve the lifecycle twice under one scale's name. A ``--ros-args`` left empty goes too.
The node is a lifecycle node when it publishes its transition events
(``lifecycle_msgs/msg/TransitionEvent``) or its command line carries those remaps.
"""

import math
import re
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

from ..agent.catalogue import LIFECYCLE_SERVICES, LIFECYCLE_TOPICS
from .stats import RateSummary, round_sig

MIN_READINGS = 3
MIN_FRACTION = 0.5           # freq_min_hz = this x freq_opt_hz
OPT_ROUNDING = 0.01          # freq_opt_hz to 2 significant digits when that moves it this little
TOLERANCE_FLOOR_S = 2.0      # above model.advice.cold_move_budget_s with default monitoring
MISSED_AT_MIN = 3            # Δ covers this many periods at freq_min_hz
TOLERANCE_STEP_S = 0.5


@dataclass(frozen=True)
class Suggestion:
    """Suggested thresholds of one connection; None where none is suggested."""

    freq_min_hz: Optional[float]
    freq_opt_hz: Optional[float]
    tolerance_s: Optional[float]
    bandwidth_kbps: float
    why: Tuple[str, ...] = ()          # how each figure came, for the file's comments
    unmonitored: str = ''              # why there are no thresholds ('' when there are)

    @property
    def monitored(self) -> bool:
        return self.freq_min_hz is not None


def bandwidth_kbps(rate_hz: float, mean_bytes: float) -> float:
    """kbit/s of ``rate_hz`` messages of ``mean_bytes``, rounded up to 3 significant digits."""
    return round_sig(rate_hz * mean_bytes * 8.0 / 1000.0, 3, 'up') if rate_hz > 0 else 0.0


def suggest(rate: Optional[RateSummary]) -> Suggestion:
    """The thresholds the rule gives for one measured topic (None: it was not measured)."""
    if rate is None:
        return Suggestion(None, None, None, 0.0, unmonitored='not measured')
    if len(rate.readings) < MIN_READINGS or rate.median <= 0:
        return Suggestion(None, None, None, 0.0, unmonitored=(
            f'{rate.messages} message(s) and {len(rate.readings)} rate reading(s) in the watch '
            f'(a latched or one-shot topic, or one that was quiet): too few to suggest '
            f'thresholds; it stays unmonitored'))
    p50 = rate.median
    opt = round_sig(p50, 2)
    if abs(opt - p50) > OPT_ROUNDING * p50:
        opt = round_sig(p50, 3)
    fmin = round_sig(MIN_FRACTION * opt, 2)
    below_s = rate.longest_below_s(fmin)
    tolerance = max(TOLERANCE_FLOOR_S, MISSED_AT_MIN / fmin, 2.0 * below_s)
    tolerance = math.ceil(tolerance / TOLERANCE_STEP_S - 1e-9) * TOLERANCE_STEP_S
    if tolerance == TOLERANCE_FLOOR_S:
        tol_why = f'the {TOLERANCE_FLOOR_S:g} s floor'
    elif MISSED_AT_MIN / fmin >= 2.0 * below_s:
        tol_why = f'{MISSED_AT_MIN} periods at freq_min'
    else:
        tol_why = f'twice the {below_s:g} s this run spent below freq_min'
    why = (f'freq_opt_hz: the p50 reading; freq_min_hz: half of it; tolerance_s: {tol_why}',)
    if below_s > 0:
        why += (f'this run fell below freq_min for {below_s:g} s at most (lowest reading '
                f'{rate.lowest:.3g} Hz)',)
    return Suggestion(freq_min_hz=fmin, freq_opt_hz=opt, tolerance_s=tolerance,
                      bandwidth_kbps=bandwidth_kbps(p50, rate.mean_bytes), why=why)


LIFECYCLE_EVENT_TYPE = 'lifecycle_msgs/msg/TransitionEvent'
ROS_ARGS, END_ROS_ARGS = '--ros-args', '--'
REMAP_FLAGS = ('-r', '--remap')
_LIFECYCLE_NAMES = frozenset(LIFECYCLE_SERVICES + LIFECYCLE_TOPICS)
NAME_REMAP_RE = re.compile(r'^(?:[^:]+:)?__(?:node|ns):=')


@dataclass(frozen=True)
class LaunchSuggestion:
    """What to write as a node's launch, from the command line its process ran."""

    command: Tuple[str, ...]          # launch.command; () when no command line was seen
    lifecycle: bool                   # a lifecycle node: ``lifecycle: true``, then ``standby``
    dropped: Tuple[str, ...] = ()     # the agent's own arguments left out of ``command``


def is_agent_remap(rule: str) -> bool:
    """``~/NAME:=~/SCALE/NAME`` for a lifecycle service or topic: what an agent adds."""
    source, sep, target = rule.partition(':=')
    if not sep or not source.startswith('~/'):
        return False
    name = source[2:]
    parts = target.split('/')
    return (name in _LIFECYCLE_NAMES and len(parts) == 3 and parts[0] == '~'
            and bool(parts[1]) and parts[2] == name)


def suggest_launch(cmdline: Sequence[str], lifecycle_seen: bool = False) -> LaunchSuggestion:
    """The launch command a user writes for a node seen running ``cmdline`` (see the module);
    ``lifecycle_seen``: the graph showed it publishing its transition events."""
    args = list(cmdline)
    # (section, index of the rule) of every remap: the section counts the --ros-args seen.
    remaps: List[Tuple[int, int]] = []
    section, inside = 0, False
    for i, arg in enumerate(args):
        if arg == ROS_ARGS:
            section, inside = section + 1, True
        elif arg == END_ROS_ARGS:
            inside = False
        elif inside and arg in REMAP_FLAGS and i + 1 < len(args):
            remaps.append((section, i + 1))
    agents = {sec for sec, i in remaps if is_agent_remap(args[i])}
    # The section an agent appended also names the node (__node, __ns), from the name the
    # deployment gives it: the agent adds those again.
    drop = {i for sec, i in remaps
            if is_agent_remap(args[i]) or sec in agents and NAME_REMAP_RE.match(args[i])}
    kept = [a for i, a in enumerate(args) if i not in drop and i + 1 not in drop]
    dropped = [a for i, a in enumerate(args) if i in drop or i + 1 in drop]
    return LaunchSuggestion(command=_without_empty_ros_args(kept),
                            lifecycle=lifecycle_seen or bool(agents), dropped=tuple(dropped))


def _without_empty_ros_args(args: Sequence[str]) -> Tuple[str, ...]:
    """``args`` without a ``--ros-args`` that opens nothing (and the ``--`` closing it)."""
    out = []
    i = 0
    while i < len(args):
        if args[i] == ROS_ARGS:
            following = args[i + 1] if i + 1 < len(args) else None
            if following in (None, ROS_ARGS):
                i += 1
                continue
            if following == END_ROS_ARGS:
                i += 2
                continue
        out.append(args[i])
        i += 1
    return tuple(out)
