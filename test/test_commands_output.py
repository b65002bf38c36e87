"""Every command that offers --json prints exactly one JSON object on stdout, as a separate
process sees it: a C library writing below sys.stdout (HiGHS's banner) breaks this, and
capsys would not see it."""

import json
import re
import os
import subprocess
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
IROS = os.path.join(HERE, '..', 'config', 'iros2016')


def run_json(args, tmp_path):
    proc = subprocess.run([sys.executable, '-m', 'anyscale_manager.cli', *args],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    try:
        return json.loads(proc.stdout)
    except json.JSONDecodeError as e:
        raise AssertionError(f'stdout of {args} is not one JSON object ({e}):\n'
                             f'{proc.stdout[:400]}') from e


@pytest.mark.parametrize('solver', ['greedy', 'paper-greedy', 'exact'])
@pytest.mark.parametrize('problem', ['1', '2'])
def test_plan_json_parses(tmp_path, solver, problem):
    path = os.path.join(IROS, 'instance_3.yaml')
    data = run_json(['plan', path, '--json', '--solver', solver, '--problem', problem], tmp_path)
    assert data['solver'] == solver and data['problem'] == int(problem)
    assert data['layout']


def test_simulate_json_parses(tmp_path):
    data = run_json(['simulate', '--json', '--runs', '1', '--systems', '6x2x2',
                     '--out', str(tmp_path / 'sim')], tmp_path)
    assert data['runs'] == 1 and data['systems']


def canonical(name):
    return re.sub(r'[-_.]+', '-', name).lower()


def test_lock_pins_every_requirement():
    """requirements.lock is what ./run.sh installs: it must pin each package requirements.txt
    asks for, with a hash (refresh it with scripts/lock.py)."""
    root = os.path.join(HERE, '..')
    with open(os.path.join(root, 'requirements.lock')) as f:
        lock = f.read()
    pins = re.finditer(r'^([A-Za-z0-9_.-]+)==\S+ \\$', lock, re.M)
    pinned = {canonical(m.group(1)) for m in pins}
    assert lock.count('--hash=sha256:') == len(pinned) > 0
    with open(os.path.join(root, 'requirements.txt')) as f:
        wanted = {canonical(re.split(r'[\[<>=~; ]', line.strip())[0]) for line in f
                  if line.strip() and not line.startswith('#')}
    assert wanted <= pinned, f'not in requirements.lock: {sorted(wanted - pinned)}'
