"""HiGHS, optional and silent: the one place the solver is imported and built.

HiGHS writes a banner to file descriptor 1 when a solver object is built (1.16 and later),
below Python's sys.stdout, so a command printing JSON would print the banner first. The
banner and every later log line are kept off stdout here; nothing else in the package
builds a solver.
"""

import os
import sys
from typing import Any

try:
    import highspy
except ImportError:  # optional on a plain ROS install: only the exact solvers need it
    # None marks the package as missing: every user checks it (or available()) first.
    highspy = None  # type: ignore[assignment]


def available() -> bool:
    return highspy is not None


def quiet_highs() -> Any:
    """A new highspy.Highs that writes nothing to stdout or stderr."""
    if highspy is None:
        raise ImportError('the exact solvers need HiGHS: pip install highspy')
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, 'w') as devnull:
            os.dup2(devnull.fileno(), 1)
            h = highspy.Highs()
    finally:
        os.dup2(saved, 1)
        os.close(saved)
    h.setOptionValue('output_flag', False)
    return h
