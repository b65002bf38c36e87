"""Broken Fast DDS shared-memory port files: found, removed, and a real participant freed."""

import os
import subprocess
import sys
import time

import pytest

from anyscale_manager.agent import shm


def _touch(path, size=0, age_s=0.0):
    with open(path, 'wb') as f:
        f.write(b'x' * size)
    t = time.time() - age_s
    os.utime(path, (t, t))


def test_only_old_empty_port_files_are_broken(tmp_path):
    d = str(tmp_path)
    _touch(os.path.join(d, 'fastrtps_port7411'), age_s=60)            # broken
    _touch(os.path.join(d, 'fastrtps_port7413'), age_s=1)             # being created
    _touch(os.path.join(d, 'fastrtps_port7415'), size=16, age_s=60)   # sized: in use
    _touch(os.path.join(d, 'fastrtps_port7411_el'), age_s=60)         # a lock file
    _touch(os.path.join(d, 'sem.fastrtps_port7411_mutex'), age_s=60)
    _touch(os.path.join(d, 'fastrtps_0123456789abcdef'), age_s=60)    # a segment
    assert shm.broken_port_files(d) == [os.path.join(d, 'fastrtps_port7411')]
    said = []
    assert shm.remove_broken_port_files(d, say=said.append) == \
        [os.path.join(d, 'fastrtps_port7411')]
    assert 'fastrtps_port7411' in said[0] and 'hang' in said[0]
    assert sorted(os.listdir(d)) == ['fastrtps_0123456789abcdef', 'fastrtps_port7411_el',
                                     'fastrtps_port7413', 'fastrtps_port7415',
                                     'sem.fastrtps_port7411_mutex']
    assert shm.broken_port_files(d, now=time.time() + 10) == \
        [os.path.join(d, 'fastrtps_port7413')]


def test_a_missing_folder_finds_nothing(tmp_path):
    assert shm.broken_port_files(str(tmp_path / 'absent')) == []
    assert shm.remove_broken_port_files(str(tmp_path / 'absent')) == []


PARTICIPANT = '''
import rclpy
rclpy.init()
node = rclpy.create_node('shm_check')
print('up', flush=True)
node.destroy_node()
rclpy.try_shutdown()
'''


@pytest.mark.skipif(not os.path.isdir(shm.SHM_DIR), reason=f'no {shm.SHM_DIR} here')
def test_an_empty_port_file_hangs_a_participant_until_removed(ros_env):
    # The ports a participant of this domain picks first (Fast DDS: 7400 + 250 x domain + 10
    # + 2 x participant id for unicast; its shared-memory port reuses the number, + 1).
    domain = int(ros_env['ROS_DOMAIN_ID'])
    base = 7400 + 250 * domain + 10
    made = []
    for port in range(base, base + 8):
        path = os.path.join(shm.SHM_DIR, f'fastrtps_port{port}')
        if not os.path.exists(path):
            _touch(path, age_s=60)
            made.append(path)
    try:
        stuck = subprocess.Popen([sys.executable, '-c', PARTICIPANT], env=ros_env,
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            out, _ = stuck.communicate(timeout=8)
            hung = False
        except subprocess.TimeoutExpired:
            hung = True
        finally:
            stuck.kill()
            stuck.wait()
        removed = shm.remove_broken_port_files()
        assert set(made) <= set(removed)
        freed = subprocess.run([sys.executable, '-c', PARTICIPANT], env=ros_env, timeout=60,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert 'up' in freed.stdout, freed.stdout
        # What this guards against, shown on this machine's Fast DDS (not a condition of the
        # fix: a later Fast DDS may pick ports differently).
        print(f'participant with empty port files present: {"hung" if hung else "started"}')
    finally:
        for path in made:
            if os.path.exists(path) and os.path.getsize(path) == 0:
                os.unlink(path)
