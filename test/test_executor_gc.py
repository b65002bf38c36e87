"""Garbage collection between callbacks (nodes/executor.py): with the automatic collector off,
``collect_due`` runs the collection it would have run, so cycles are still freed, but only
where the spin loop calls it, never inside the executor's dispatch."""

import gc
import weakref

from anyscale_manager.nodes.executor import collect_due


class Cycle:
    def __init__(self):
        self.me = self


def test_cycles_are_collected_by_the_loop_and_only_there():
    was = gc.isenabled()
    gc.disable()
    try:
        gc.collect()
        probe = Cycle()
        gone = weakref.ref(probe)
        del probe
        collect_due()                                # below every threshold: nothing runs
        assert gone() is not None
        for _ in range(gc.get_threshold()[0] + 10):  # what would have triggered a collection
            Cycle()
        assert gone() is not None                    # the collector is off: nothing ran
        collect_due()
        assert gone() is None
        assert gc.get_count()[0] < gc.get_threshold()[0]
    finally:
        if was:
            gc.enable()


def test_what_lives_when_the_loop_begins_is_left_out_of_every_collection():
    from anyscale_manager.nodes.executor import collect_between_callbacks
    was = gc.isenabled()
    try:
        early = Cycle()
        early_gone = weakref.ref(early)
        collect_between_callbacks()
        assert not gc.isenabled() and gc.get_freeze_count() > 0
        del early
        late = Cycle()
        late_gone = weakref.ref(late)
        del late
        gc.collect()
        assert late_gone() is None                  # a cycle made later is still collected
        assert early_gone() is not None             # frozen: never walked, never freed
    finally:
        gc.unfreeze()
        gc.collect()
        if was:
            gc.enable()
