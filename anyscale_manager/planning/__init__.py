"""Offline planning (IROS 2016): node settings and the first layout.

``solve(deployment, problem=1, solver='greedy', settings='continuous', time_limit_s=10.0)``
returns a frozen ``Plan``. Regression of node profiles, the shared feasibility checker, the
paper's greedy planners, our local search and the exact MILP live in the submodules.
"""

from .feasibility import Violation, check_layout
from .instance import Instance, Option
from .plan import SOLVERS, Placement, Plan, solve
from .regression import NodeProfile, Regression, fit_profile

__all__ = [
    'Instance', 'NodeProfile', 'Option', 'Placement', 'Plan', 'Regression', 'SOLVERS',
    'Violation', 'check_layout', 'fit_profile', 'solve',
]
