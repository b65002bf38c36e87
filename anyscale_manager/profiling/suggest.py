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
"""

import math
from dataclasses import dataclass
from typing import Optional, Tuple

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
    if len(rate.readings) < MIN_READINGS or rate.p50_hz <= 0:
        return Suggestion(None, None, None, 0.0, unmonitored=(
            f'{rate.messages} message(s) and {len(rate.readings)} rate reading(s) in the watch '
            f'(a latched or one-shot topic, or one that was quiet): too few to suggest '
            f'thresholds; it stays unmonitored'))
    p50 = rate.p50_hz
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
                f'{rate.lowest_hz:.3g} Hz)',)
    return Suggestion(freq_min_hz=fmin, freq_opt_hz=opt, tolerance_s=tolerance,
                      bandwidth_kbps=bandwidth_kbps(p50, rate.mean_bytes), why=why)
