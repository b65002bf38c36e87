"""Link schedules: when the test-bed's links are cut, restored or throttled. Pure.

A step names its link after ``@`` (``20:cut@wifi``); without one it means the test-bed's only
link (the two-scale test-bed's WiFi)."""

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

ACTIONS = ('cut', 'restore', 'throttle')


@dataclass(frozen=True)
class Step:
    at_s: float                       # seconds after the schedule starts
    action: str                       # cut | restore | throttle
    rate_kbps: Optional[float] = None  # throttle only
    link: str = ''                    # '' = the only link

    def __str__(self) -> str:
        extra = f'={self.rate_kbps:g}' if self.rate_kbps is not None else ''
        where = f'@{self.link}' if self.link else ''
        return f'{self.at_s:g}:{self.action}{extra}{where}'


def check(steps: Sequence[Step], links: Optional[Sequence[str]] = None) -> Tuple[Step, ...]:
    """Validate and sort; ValueError names the bad step. ``links``: the names a step may give
    (with '' among them when a step may name none)."""
    for i, s in enumerate(steps):
        if s.action not in ACTIONS:
            raise ValueError(f'step {i + 1} ({s}): unknown action {s.action!r}; expected one '
                             f'of {", ".join(ACTIONS)}')
        if not math.isfinite(s.at_s) or s.at_s < 0:
            raise ValueError(f'step {i + 1} ({s}): time must be a number >= 0')
        if s.action == 'throttle':
            if s.rate_kbps is None or not math.isfinite(s.rate_kbps) or s.rate_kbps <= 0:
                raise ValueError(f'step {i + 1} ({s}): throttle needs a rate > 0 kbit/s, '
                                 'e.g. 30:throttle=4000')
        elif s.rate_kbps is not None:
            raise ValueError(f'step {i + 1} ({s}): only throttle takes a rate')
        if links is not None and s.link not in links:
            known = ', '.join(links)
            raise ValueError(f'step {i + 1} ({s}): ' + (
                f'name a link after @ (this test-bed has {known})' if not s.link else
                f'unknown link {s.link!r}; this test-bed has {known}'))
    return tuple(sorted(steps, key=lambda s: s.at_s))


def parse(text: str, links: Optional[Sequence[str]] = None) -> Tuple[Step, ...]:
    """'20:cut,35:restore,40:throttle=4000' (or '20:cut@wifi', ...) -> steps."""
    steps = []
    for i, item in enumerate(x.strip() for x in text.split(',')):
        if not item:
            continue
        at, sep, rest = item.partition(':')
        rest, _, link = rest.partition('@')
        action, _, rate = rest.partition('=')
        if not sep:
            raise ValueError(f'schedule item {i + 1} {item!r}: expected SECONDS:ACTION')
        try:
            at_s = float(at)
            rate_kbps = float(rate) if rate else None
        except ValueError:
            raise ValueError(f'schedule item {i + 1} {item!r}: not a number') from None
        steps.append(Step(at_s, action.strip(), rate_kbps, link.strip()))
    return check(steps, links)


def paper_schedule(duration_s: float, full_kbps: float = 54000.0,
                   throttle_kbps: float = 5000.0) -> Tuple[Step, ...]:
    """An outage pattern modelled on the ICAR run: the link is usable for about half the time.

    Up at full rate, then throttled below AR's 6 Mbit/s (AR must come back, AMCL may stay), then
    out of coverage, back at full rate, and out again: up (at any rate) for 58 % of the run.
    """
    if not duration_s > 0:
        raise ValueError(f'duration must be > 0 s, got {duration_s!r}')
    d = duration_s
    return check([Step(0.30 * d, 'throttle', throttle_kbps), Step(0.38 * d, 'cut'),
                  Step(0.62 * d, 'throttle', full_kbps), Step(0.62 * d, 'restore'),
                  Step(0.82 * d, 'cut')])


def three_scales_schedule(duration_s: float, full_kbps: float = 54000.0,
                          throttle_kbps: float = 5000.0) -> Tuple[Step, ...]:
    """A run for the three-scale test-bed: the server's WiFi throttled below AR's need (AR to
    the next-best scale, the laptop), cut (AMCL there too), restored (both return to the server
    once the hysteresis has passed), then the laptop-server backhaul cut and restored, and the
    robot's Ethernet to the laptop cut and restored."""
    if not duration_s > 0:
        raise ValueError(f'duration must be > 0 s, got {duration_s!r}')
    d = duration_s
    return check([Step(0.10 * d, 'throttle', throttle_kbps, 'wifi'),
                  Step(0.22 * d, 'cut', None, 'wifi'),
                  Step(0.36 * d, 'throttle', full_kbps, 'wifi'),
                  Step(0.36 * d, 'restore', None, 'wifi'),
                  Step(0.70 * d, 'cut', None, 'backhaul'),
                  Step(0.78 * d, 'restore', None, 'backhaul'),
                  Step(0.86 * d, 'cut', None, 'ethernet'),
                  Step(0.94 * d, 'restore', None, 'ethernet')])


def up_fraction(steps: Sequence[Step], duration_s: float, link: str = '') -> float:
    """Fraction of [0, duration] a link (the only one, or the one named) is up (starting up)."""
    up, last, total = True, 0.0, 0.0
    for s in check(steps):
        if s.link != link:
            continue
        at = min(s.at_s, duration_s)
        if up:
            total += at - last
        last = at
        if s.action == 'cut':
            up = False
        elif s.action == 'restore':
            up = True
    if up:
        total += duration_s - last
    return total / duration_s if duration_s > 0 else 0.0


__all__ = ['ACTIONS', 'Step', 'check', 'paper_schedule', 'parse', 'three_scales_schedule',
           'up_fraction']
