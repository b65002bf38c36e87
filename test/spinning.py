"""Spinning rclpy in tests: a fresh context with its executor and the nodes it destroys (the
``ros`` fixture, conftest.py), and the one wait on a condition, which fails naming what it
waited for, with the state it was given and the last output of the test's processes."""

import time

import rclpy
from rclpy.executors import SingleThreadedExecutor

SPIN_S = 0.05               # the longest one spin_once waits for work
TAIL_CHARS = 3000           # the end of each process's output shown on a failure


class RosContext:
    """A fresh rclpy context (``rclpy.init(context=...)``) with one executor, made at first use
    by ``make_executor``; the nodes it owns are destroyed and the context shut down by
    ``close()`` or at the end of a ``with`` block. Every test that spins has one of its own, so
    none inherits another's nodes, callbacks or shutdown."""

    def __init__(self, make_executor=SingleThreadedExecutor):
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self._make_executor = make_executor
        self._executor = None
        self.nodes = []

    @property
    def executor(self):
        if self._executor is None:
            self._executor = self._make_executor(context=self.context)
        return self._executor

    def node(self, name, spin=True, **kwargs):
        """A plain node of this context, spun by its executor unless not to ``spin``."""
        node = rclpy.create_node(name, context=self.context, **kwargs)
        return self.add(node) if spin else self.own(node)

    def own(self, node):
        """``node``, destroyed with this context, and not spun (yet)."""
        self.nodes.append(node)
        return node

    def add(self, node):
        """``node`` (of this context), spun by its executor and destroyed with the context."""
        if node not in self.nodes:
            self.own(node)
        self.executor.add_node(node)
        return node

    def spin_until(self, condition, timeout_s, what, procs=(), **options):
        """``spin_until`` on this context's executor."""
        return spin_until(self.executor, condition, timeout_s, what, procs, **options)

    def spin_for(self, seconds):
        spin_for(self.executor, seconds)

    def close(self):
        if self._executor is not None:
            for node in self._executor.get_nodes():
                self._executor.remove_node(node)
            self._executor.shutdown()
        for node in reversed(self.nodes):
            node.destroy_node()
        self.nodes.clear()
        rclpy.try_shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def spin_until(executor, condition, timeout_s, what, procs=(), *, watch=(), state=None,
               tick=None, tick_every_s=0.2, spin_s=SPIN_S, required=True):
    """Spin ``executor`` until ``condition()`` is true, and return that value.

    ``procs``: the test's processes, a mapping or (name, process) pairs, each a LoggedProcess
    (processes.py) or a Popen; the end of one named in ``watch`` (True: any of them) ends the
    wait at once, as a failure. ``tick()``, if given, is called every ``tick_every_s`` (a fake
    peer's reports). Past ``timeout_s`` an AssertionError names ``what`` and shows ``state()``
    and the last output of every process in ``procs``; with ``required=False`` the condition's
    last value is returned instead (a wait that may go unanswered, and is tried again).
    """
    procs = list(procs.items() if hasattr(procs, 'items') else procs)
    deadline = time.monotonic() + timeout_s
    next_tick = 0.0
    while True:
        value = condition()
        if value:
            return value
        if tick is not None and time.monotonic() >= next_tick:
            tick()
            next_tick = time.monotonic() + tick_every_s
        ended = [name for name, proc in procs
                 if (watch is True or name in watch) and _popen(proc).poll() is not None]
        if ended:
            raise AssertionError(_failure(
                f'{", ".join(ended)} exited while waiting for {what}', state, procs))
        if time.monotonic() >= deadline:
            if not required:
                return value
            raise AssertionError(_failure(
                f'timed out after {timeout_s:g} s waiting for {what}', state, procs))
        executor.spin_once(timeout_sec=spin_s)


def spin_for(executor, seconds):
    """Spin ``executor`` for ``seconds``: what is on its way is taken."""
    spin_until(executor, lambda: False, seconds, f'{seconds:g} s to pass', required=False)


def _popen(proc):
    return getattr(proc, 'proc', proc)


def _output(proc):
    """The end of a process's output: a LoggedProcess's file, or an exited Popen's pipe (a
    running one's would block)."""
    if hasattr(proc, 'text'):
        return proc.text()[-TAIL_CHARS:]
    pipe = getattr(proc, 'stdout', None)
    if pipe is None or proc.poll() is None:
        return '(output not kept)' if pipe is None else '(still running: output not read)'
    text = pipe.read()
    return (text.decode(errors='replace') if isinstance(text, bytes) else text)[-TAIL_CHARS:]


def _failure(headline, state, procs):
    lines = [headline]
    if state is not None:
        lines.append(f'state: {state()}')
    for name, proc in procs:
        code = _popen(proc).poll()
        lines.append(f'--- {name} ({"running" if code is None else f"exit {code}"})')
        lines.append(_output(proc))
    return '\n'.join(lines)
