"""Least-squares regression of node profiles: CPU -> performance, parameter -> CPU and back.

The IROS 2016 paper fits each configurable node's few profiling samples with a simple curve and
plans on the curve. CPU -> performance curves use x = CPU / 100 (a share of one reference core),
which is the scale of the coefficients the paper publishes; parameter curves use the raw value.
"""

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np

from ..model.types import Settings

FORMS = ('linear', 'log', 'poly2', 'poly3', 'quadratic')
DEGREE = {'linear': 1, 'poly2': 2, 'quadratic': 2, 'poly3': 3, 'log': 1}
CPU_SCALE = 100.0
_INVERSE_GRID = 512


class Regression:
    """One fitted curve ``y = f(x / x_scale)``; scikit-learn style: ``fit`` returns self.

    Forms: ``linear`` (a x + b), ``poly2``/``quadratic`` and ``poly3`` (polynomials, highest
    power first) and ``log`` (a ln x + b). Learned values: ``coef_`` (highest power first; for
    ``log`` the pair (a, b)), ``r2_`` and ``x_range_`` (the smallest and largest raw sample).
    """

    def __init__(self, form: str = 'linear', x_scale: float = 1.0):
        if form not in FORMS:
            raise ValueError(f'unknown regression form {form!r} (expected one of '
                             f'{", ".join(FORMS)})')
        if not (x_scale > 0 and math.isfinite(x_scale)):
            raise ValueError(f'x_scale must be a positive number, got {x_scale!r}')
        self.form = form
        self.x_scale = float(x_scale)
        self.coef_: Optional[Tuple[float, ...]] = None
        self.r2_: Optional[float] = None
        self.x_range_: Optional[Tuple[float, float]] = None

    @property
    def degree(self) -> int:
        return DEGREE[self.form]

    def _features(self, x: np.ndarray) -> np.ndarray:
        z = np.asarray(x, dtype=float) / self.x_scale
        if self.form == 'log':
            if np.any(z <= 0):
                raise ValueError('a log form needs positive x values')
            return np.log(z)
        return z

    def fit(self, x: Sequence[float], y: Sequence[float]) -> 'Regression':
        xs = np.asarray(x, dtype=float)
        ys = np.asarray(y, dtype=float)
        if xs.shape != ys.shape or xs.ndim != 1:
            raise ValueError(f'x and y must be equally long lists, got {xs.shape} and {ys.shape}')
        if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))):
            raise ValueError('samples must be finite numbers')
        needed = self.degree + 1
        if len(set(xs.tolist())) < needed:
            raise ValueError(f'a {self.form} fit needs at least {needed} distinct x values, '
                             f'got {len(set(xs.tolist()))}')
        coef = np.polyfit(self._features(xs), ys, self.degree)
        self.coef_ = tuple(float(c) for c in coef)
        residual = ys - np.polyval(coef, self._features(xs))
        total = float(np.sum((ys - ys.mean()) ** 2))
        ss_res = float(np.sum(residual ** 2))
        self.r2_ = 1.0 if total == 0.0 else 1.0 - ss_res / total
        self.x_range_ = (float(xs.min()), float(xs.max()))
        return self

    def _fitted(self) -> Tuple[Tuple[float, ...], Tuple[float, float]]:
        """The learned ``(coef_, x_range_)``; a RuntimeError before ``fit``."""
        if self.coef_ is None or self.x_range_ is None:
            raise RuntimeError('this Regression is not fitted yet: call fit() first')
        return self.coef_, self.x_range_

    def predict(self, x):
        """Fitted y at raw x (a number or an array)."""
        coef, _ = self._fitted()
        out = np.polyval(coef, self._features(np.asarray(x, dtype=float)))
        return float(out) if np.ndim(out) == 0 else out

    def inverse(self, y: float, low: Optional[float] = None, high: Optional[float] = None
                ) -> float:
        """The smallest raw x in [low, high] with f(x) = y; the nearer end when none exists.

        The range defaults to the fitted samples' range: a fit is not trusted outside it.
        """
        _, x_range = self._fitted()
        lo = x_range[0] if low is None else float(low)
        hi = x_range[1] if high is None else float(high)
        if lo > hi:
            raise ValueError(f'empty range [{lo}, {hi}]')
        if lo == hi:
            return lo
        grid = np.linspace(lo, hi, _INVERSE_GRID + 1)
        values = np.asarray(self.predict(grid)) - y
        exact = np.flatnonzero(values == 0.0)
        crossing = np.flatnonzero(np.signbit(values[:-1]) != np.signbit(values[1:]))
        if exact.size and (not crossing.size or exact[0] <= crossing[0]):
            return float(grid[exact[0]])
        if not crossing.size:
            return float(grid[int(np.argmin(np.abs(values)))])
        a, b = float(grid[crossing[0]]), float(grid[crossing[0] + 1])
        fa = float(self.predict(a)) - y
        for _ in range(80):
            mid = 0.5 * (a + b)
            fm = float(self.predict(mid)) - y
            if fm == 0.0:
                return mid
            if (fm < 0) == (fa < 0):
                a, fa = mid, fm
            else:
                b = mid
        return 0.5 * (a + b)

    def formula(self, var: str = 'x') -> str:
        """The fitted curve as text, e.g. ``66.62 ln x + 56.31``."""
        coef, _ = self._fitted()
        if self.form == 'log':
            a, b = coef
            return f'{a:.5g} ln {var} {"+" if b >= 0 else "-"} {abs(b):.5g}'
        terms = []
        for power, c in zip(range(self.degree, -1, -1), coef):
            suffix = f' {var}' if power == 1 else f' {var}^{power}' if power > 1 else ''
            term = f'{abs(c):.5g}{suffix}'
            sign = '-' if c < 0 else '+'
            terms.append((sign, term))
        text = ('-' if terms[0][0] == '-' else '') + terms[0][1]
        return text + ''.join(f' {s} {t}' for s, t in terms[1:])

    def __repr__(self) -> str:
        if self.coef_ is None:
            return f'Regression(form={self.form!r}, x_scale={self.x_scale:g})'
        return (f'Regression({self.form}: y = {self.formula()}, x = raw / {self.x_scale:g}, '
                f'R2 = {self.r2_:.4f})')


def fit_curve(form: str, x: Sequence[float], y: Sequence[float], x_scale: float = 1.0
              ) -> Regression:
    """Fit ``form``; with too few distinct samples for it, the richest polynomial they allow.

    Two samples and a ``poly2`` form give the line through them rather than an error, so that a
    node profiled at few points still plans.
    """
    try:
        return Regression(form, x_scale).fit(x, y)
    except ValueError:
        distinct = len(set(float(v) for v in x))
        if form == 'log' or distinct < 2:
            raise
        fallback = {1: 'linear', 2: 'poly2'}.get(min(distinct - 1, 2), 'linear')
        return Regression(fallback, x_scale).fit(x, y)


@dataclass(frozen=True)
class NodeProfile:
    """The fitted curves of one configurable node."""

    parameter: str
    cpu_to_performance: Regression
    parameter_to_cpu: Optional[Regression]        # None when the samples carry no values
    parameter_to_performance: Optional[Regression]
    values: Tuple[float, ...]
    cpu: Tuple[float, ...]

    def performance(self, cpu: float) -> float:
        return float(self.cpu_to_performance.predict(cpu))

    def parameter_for_cpu(self, cpu: float) -> Optional[float]:
        """The parameter value to set so that the node uses ``cpu`` (None: not known).

        A CPU share equal to a profiled sample gives that sample's value exactly.
        """
        for v, c in zip(self.values, self.cpu):
            if c == cpu:
                return float(v)
        if self.parameter_to_cpu is None:
            return None
        return self.parameter_to_cpu.inverse(cpu)


def fit_profile(settings: Settings) -> NodeProfile:
    """Fit CPU -> performance (``settings.form``, x = CPU/100), parameter -> CPU and
    parameter -> performance (both ``settings.parameter_form``)."""
    to_perf = fit_curve(settings.form, settings.cpu, settings.performance, CPU_SCALE)
    to_cpu = to_param_perf = None
    if settings.values and len(set(settings.values)) > 1:
        to_cpu = fit_curve(settings.parameter_form, settings.values, settings.cpu)
        to_param_perf = fit_curve(settings.parameter_form, settings.values,
                                  settings.performance)
    return NodeProfile(parameter=settings.parameter, cpu_to_performance=to_perf,
                       parameter_to_cpu=to_cpu, parameter_to_performance=to_param_perf,
                       values=tuple(settings.values), cpu=tuple(settings.cpu))
