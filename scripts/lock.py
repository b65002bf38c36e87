#!/usr/bin/env python3
"""Refresh requirements.lock from requirements.txt.

Resolves requirements.txt in a clean virtual environment and pins every package it would
install (pip, setuptools and wheel included, since the package itself is built without
isolation) with the sha256 of the file this platform installs, so that `pip install
--require-hashes -r requirements.lock` gets exactly what was tested or nothing. The lock is
for the platform it was made on (Linux x86_64, CPython 3.11 in CI); run this again after
changing requirements.txt and commit both files:

    python3 scripts/lock.py             # add what requirements.txt newly asks for
    python3 scripts/lock.py --upgrade   # resolve everything afresh

A refresh keeps every version the lock already pins: those `name==version` lines are passed to
pip as constraints (`-c`), so adding a requirement adds its packages and moves no other pin
(an upgrade of a tested package is a decision of its own, made with --upgrade). A pin that
requirements.txt no longer needs drops out, since a constraint installs nothing by itself.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from typing import List, Optional, Sequence

HERE = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LOCK = os.path.join(HERE, 'requirements.lock')
HEADER = '''\
# Every package the tests and the demo run with, pinned with the hashes of the files installed.
# Made by `python3 scripts/lock.py` from requirements.txt ({where}); ./run.sh
# installs from this file with --require-hashes. Edit requirements.txt, never this file.
'''


def current_pins() -> List[str]:
    """The `name==version` of every package the lock pins now (none when there is no lock)."""
    try:
        with open(LOCK) as f:
            return re.findall(r'^([A-Za-z0-9_.-]+==\S+) \\$', f.read(), re.M)
    except FileNotFoundError:
        return []


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--upgrade', action='store_true',
                        help='resolve afresh instead of keeping the versions the lock pins')
    args = parser.parse_args(argv)
    pins = [] if args.upgrade else current_pins()
    with tempfile.TemporaryDirectory() as tmp:
        venv = os.path.join(tmp, 'venv')
        python = os.path.join(venv, 'bin', 'python')
        subprocess.run([sys.executable, '-m', 'venv', venv], check=True)
        report = os.path.join(tmp, 'report.json')
        constraints = []
        if pins:
            path = os.path.join(tmp, 'constraints.txt')
            with open(path, 'w') as f:
                f.write('\n'.join(pins) + '\n')
            constraints = ['-c', path]
        # pip's installation report names each file it would install with its hash, under the
        # name it is published as (the ROS wheels also carry an inner egg-info that
        # `pip freeze` would list as a second, unpublished name).
        subprocess.run([python, '-m', 'pip', 'install', '-q', '--dry-run', '--ignore-installed',
                        '--report', report, '-r', os.path.join(HERE, 'requirements.txt'),
                        *constraints, 'pip', 'setuptools', 'wheel'], check=True)
        with open(report) as f:
            installs = json.load(f)['install']
        where = subprocess.run(
            [python, '-c', 'import platform; print(platform.python_implementation(), '
             'platform.python_version(), platform.machine())'],
            check=True, capture_output=True, text=True).stdout.strip()
    lines = [HEADER.format(where=where)]
    for item in sorted(installs, key=lambda i: i['metadata']['name'].lower()):
        name, version = item['metadata']['name'], item['metadata']['version']
        digest = item['download_info'].get('archive_info', {}).get('hashes', {}).get('sha256')
        if not digest:
            print(f'lock: pip reported no sha256 for {name} {version}', file=sys.stderr)
            return 1
        lines.append(f'{name}=={version} \\\n    --hash=sha256:{digest}\n')
    with open(LOCK, 'w') as f:
        f.write(''.join(lines))
    print(f'requirements.lock: {len(installs)} packages pinned')
    return 0


if __name__ == '__main__':
    sys.exit(main())
