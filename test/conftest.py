"""Test-wide settings and fixtures: DDS stays on loopback, in a domain of this run's own."""

import os
import random
import signal
import sys

import pytest

from anyscale_manager import config_files

# Pin discovery to this machine's loopback before anything imports rclpy, and pick a domain of
# our own so concurrent runs on one machine never see each other's nodes.
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_LOCALHOST_ONLY', None)
os.environ.pop('ROS_STATIC_PEERS', None)
if 'ANYSCALE_TEST_DOMAIN_ID' not in os.environ:
    os.environ['ANYSCALE_TEST_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 100))
os.environ['ROS_DOMAIN_ID'] = os.environ['ANYSCALE_TEST_DOMAIN_ID']
os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
# Every process the tests start uses the packaged discovery profile (a new node is found in
# 0.25 s, not up to Fast DDS's 3 s), as under ./run.sh, unless the caller names a profile: a
# bare ``pytest`` then runs what ``./run.sh test`` runs.
os.environ.update(config_files.with_discovery_profile(os.environ))

# A run started in the background of a non-interactive shell (``bash .ci/run &``, some CI
# runners) inherits SIGINT ignored, and so would every process the tests start: Ctrl-C, the
# way the tests stop a program, would then do nothing to a plain Python one. Python restores
# its Ctrl-C only where SIGINT was not ignored; restore it here, so children start with it.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(REPO, 'config')
TESTBED = os.path.join(CONFIG, 'icar2015_testbed.yaml')


def pytest_report_header(config):
    return (f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} "
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}")


@pytest.fixture(autouse=True)
def no_broken_dds_port_files():
    """Tests SIGKILL processes on purpose; one killed while its participant started leaves an
    empty Fast DDS port file that would hang every later participant on that port
    (agent/shm.py). Cleared before each test, and said."""
    from anyscale_manager.agent import shm
    shm.remove_broken_port_files(say=lambda text: print(f'\n[conftest] {text}', file=sys.stderr))
    yield


@pytest.fixture
def ros_env():
    """An explicit environment for child ROS processes (same domain, loopback only)."""
    env = dict(os.environ)
    env['PYTHONUNBUFFERED'] = '1'
    return env


@pytest.fixture
def ros():
    """This test's own rclpy context, initialised, with an executor and the nodes it destroys
    (spinning.RosContext): ``ros.node(name)``, ``ros.add(node)``, ``ros.spin_until(...)``; shut
    down after the test."""
    from spinning import RosContext
    with RosContext() as context:
        yield context


@pytest.fixture
def testbed_path():
    return TESTBED


@pytest.fixture
def python():
    return sys.executable


@pytest.fixture
def make_sup(tmp_path):
    """make(entries, settings=FAST, state=True, log_dir=None, state_path=None): a supervisor;
    nothing any of them started outlives the test (supervision.py)."""
    from supervision import Supervisors
    supervisors = Supervisors(tmp_path)
    yield supervisors.make
    supervisors.kill_all()


@pytest.fixture(autouse=True)
def no_warden_outlives_its_test(tmp_path):
    """A warden (agent/warden.py) outlives its agent on purpose, and leaves once the agent
    stopped cleanly or its state folder is gone. One whose test ended first (an agent killed,
    a folder kept) is stopped here, by the state file under this test's folder, and said."""
    yield
    import psutil
    root = str(tmp_path)
    for proc in psutil.process_iter(['pid', 'cmdline']):
        cmd = proc.info['cmdline'] or []
        if 'anyscale_manager.agent.warden' not in cmd or '--state' not in cmd[:-1]:
            continue
        if cmd[cmd.index('--state') + 1].startswith(root):
            try:
                proc.kill()
            except psutil.Error:
                continue
            print(f'\n[conftest] stopped warden pid {proc.pid} of this test', file=sys.stderr)
