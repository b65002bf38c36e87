"""The package builds with colcon and installs what `ros2 run` needs."""

import os
import shutil
import subprocess
import sys

import pytest

from conftest import REPO


def colcon_path():
    here = os.path.join(os.path.dirname(sys.executable), 'colcon')
    return here if os.path.exists(here) else shutil.which('colcon')


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    colcon = colcon_path()
    if colcon is None:
        pytest.skip('colcon is not installed (pip install colcon-core colcon-ros)')
    root = tmp_path_factory.mktemp('colcon')
    # Build from a copy of the tracked sources, as a clone would have them.
    src = root / 'src' / 'anyscale_manager'
    files = subprocess.run(['git', 'ls-files', '--cached', '--others', '--exclude-standard'],
                           cwd=REPO, capture_output=True, text=True, check=True).stdout.split()
    for rel in files:
        if not os.path.exists(os.path.join(REPO, rel)):
            continue
        dest = src / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(os.path.join(REPO, rel), dest)
    env = dict(os.environ)
    result = subprocess.run(
        [colcon, 'build', '--base-paths', str(root / 'src'), '--build-base', str(root / 'build'),
         '--install-base', str(root / 'install'), '--event-handlers', 'console_direct-'],
        cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return root / 'install'


def test_executables_are_where_ros2_run_looks(install):
    lib = install / 'anyscale_manager' / 'lib' / 'anyscale_manager'
    for exe in ('decider', 'agent', 'workload', 'anyscale-manager'):
        path = lib / exe
        assert path.is_file(), f'{path} missing'
        assert os.access(path, os.X_OK), f'{path} is not executable'


def test_package_is_in_the_ament_index_with_its_config(install):
    prefix = install / 'anyscale_manager'
    code = ('from ament_index_python.packages import get_package_prefix, '
            'get_package_share_directory as share\n'
            "print(get_package_prefix('anyscale_manager'))\n"
            "print(share('anyscale_manager'))\n")
    env = dict(os.environ, AMENT_PREFIX_PATH=str(prefix))
    out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True, text=True,
                         check=True, timeout=60).stdout.split()
    assert out[0] == str(prefix)
    share = out[1]
    assert os.path.isfile(os.path.join(share, 'package.xml'))
    assert os.path.isfile(os.path.join(share, 'config', 'icar2015_testbed.yaml'))
    for n in range(1, 11):
        assert os.path.isfile(os.path.join(share, 'config', 'iros2016', f'instance_{n}.yaml'))


def test_installed_command_validates_the_installed_config(install):
    prefix = install / 'anyscale_manager'
    site = next((prefix / 'lib').glob('python3*/site-packages'))
    env = dict(os.environ, AMENT_PREFIX_PATH=str(prefix), PYTHONPATH=str(site))
    config = prefix / 'share' / 'anyscale_manager' / 'config' / 'icar2015_testbed.yaml'
    r = subprocess.run([sys.executable, str(prefix / 'lib' / 'anyscale_manager' /
                                            'anyscale-manager'), 'validate', str(config)],
                       env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert 'migratable: amcl, ar' in r.stdout
