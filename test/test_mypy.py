"""Type checks of the pure core: mypy on model/, planning/ and runtime/, as setup.cfg sets it.

The configuration ([mypy] in setup.cfg) is the one an editor's mypy reads too.
"""

import os
import subprocess
import sys

import pytest

from conftest import REPO

PACKAGES = ('anyscale_manager/model', 'anyscale_manager/planning', 'anyscale_manager/runtime')


def mypy(*args, cwd=REPO):
    try:
        import mypy  # noqa: F401
    except ImportError:
        pytest.skip('mypy is not installed (pip install mypy types-PyYAML)')
    return subprocess.run([sys.executable, '-m', 'mypy', '--config-file',
                           os.path.join(REPO, 'setup.cfg'), *args],
                          cwd=cwd, capture_output=True, text=True, timeout=600)


def test_the_core_type_checks():
    r = mypy(*PACKAGES)
    assert r.returncode == 0, r.stdout[-8000:] + r.stderr[-2000:]


def test_the_configuration_names_the_core():
    """A bare `mypy` (an editor's, a developer's) checks the same packages."""
    import configparser
    config = configparser.ConfigParser()
    config.read(os.path.join(REPO, 'setup.cfg'))
    files = {f.strip() for f in config['mypy']['files'].split(',')}
    assert files == set(PACKAGES)


def test_a_type_error_fails_the_check(tmp_path):
    bad = tmp_path / 'bad.py'
    bad.write_text('from typing import Optional\n\n\n'
                   'def half(x: Optional[float]) -> float:\n'
                   '    return x / 2\n')
    r = mypy('--cache-dir', str(tmp_path / 'cache'), str(bad), cwd=str(tmp_path))
    assert r.returncode == 1, r.stdout + r.stderr
    assert 'bad.py:5: error' in r.stdout and 'operator' in r.stdout
