"""Code style: the ament flake8 essentials (99 columns, single quotes, no unused names).

The rules live in setup.cfg's [flake8] section, where an editor's flake8 reads them too, so the
test and the editor agree.
"""

import os
import subprocess
import sys

import pytest

from conftest import REPO


def test_flake8_clean():
    try:
        import flake8  # noqa: F401
    except ImportError:
        pytest.skip('flake8 is not installed (pip install flake8 flake8-quotes)')
    paths = [p for p in ('anyscale_manager', 'test', 'bench', 'scripts', 'examples', 'setup.py')
             if os.path.exists(os.path.join(REPO, p))]
    r = subprocess.run([sys.executable, '-m', 'flake8', *paths],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-2000:]
