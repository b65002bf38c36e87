"""The e2e modules' check of AMCL's carried state: over a whole test-bed run its pose never
jumped (testbed/poses.py), with the events and marks around a jump when it did."""

from anyscale_manager.testbed import poses


def assert_pose_never_jumped(bed, min_changes=4):
    bed.wait_heard(bed.now())
    with bed.lock:
        changes = [e for _, e in bed.record.moves() if e.node == 'amcl']
        jumps = poses.record_jumps(bed.record, 0.0, bed.now())
        heard = len(bed.record.poses.get('/amcl_pose', []))
    assert heard > 100, f'only {heard} poses heard on /amcl_pose'
    assert len(changes) >= min_changes, f'AMCL changed serving copy only {len(changes)} times'
    found = jumps['/amcl_pose']
    if found:
        t = found[0].t
        with bed.lock:
            near = [(round(at - t, 2), e.kind, e.from_scale, e.to_scale, e.reason[:100])
                    for at, e in bed.record.events if e.node == 'amcl' and abs(at - t) < 10.0]
            marks = [(round(at - t, 2), text) for at, text in bed.record.marks
                     if abs(at - t) < 10.0]
        raise AssertionError(f'the pose jumped at a change of serving copy: '
                             f'{[str(j) for j in found]}; AMCL events around the first '
                             f'{near}; harness marks {marks}')
