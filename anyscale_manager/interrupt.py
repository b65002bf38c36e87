"""Ctrl-C for every program of the package, however it was started."""

import signal


def restore_ctrl_c() -> None:
    """Make SIGINT interrupt again when this process inherited it ignored.

    A program started in the background of a non-interactive shell (``decider ... &`` in a
    script, some service managers) inherits SIGINT ignored; Python and rclpy then leave it
    ignored, so Ctrl-C or ``kill -INT`` (the ROS way to stop a node) does nothing to it, nor to
    the nodes an agent starts, which inherit it. Called first by every entry point.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


_rclpy_stops = False
_stop_asked = False


def interrupt_once() -> None:
    """The first SIGINT stops the program; every later one is ignored.

    A supervisor repeats its SIGINT while a node cleans up (destroying the node, shutting
    rclpy down). With Python's own handler, a second one landing then raises in the cleanup
    and ends the process with a traceback. Installed before ``rclpy.init``, whose handler
    hands the signal on to it. Until ``rclpy_stops_on_sigint()`` the first one raises
    KeyboardInterrupt; after, rclpy's own handler stops the spin and this one only ignores
    the later ones.
    """
    global _rclpy_stops, _stop_asked
    _rclpy_stops = _stop_asked = False
    signal.signal(signal.SIGINT, _interrupt_then_ignore)


def stop_asked() -> bool:
    """Whether a SIGINT has come since ``interrupt_once``: a spin loop checks it beside
    ``rclpy.ok()``, so that it ends on its own word, whether or not rclpy's handler managed to
    shut the context down."""
    return _stop_asked


def rclpy_stops_on_sigint() -> None:
    """Say that ``rclpy.init`` has installed rclpy's signal handler: a SIGINT now shuts the
    context down, so the spin returns or raises ExternalShutdownException where it waits. It
    is not raised as KeyboardInterrupt as well: that lands at whatever bytecode runs then,
    inside rclpy's executor too, where a Task left half-built fails in its ``__del__`` at
    exit ("'Task' object has no attribute '_exception'", a traceback in the node's log)."""
    global _rclpy_stops
    _rclpy_stops = True


def _interrupt_then_ignore(signum, frame) -> None:
    global _stop_asked
    _stop_asked = True
    ignore_interrupts()
    if not _rclpy_stops:
        raise KeyboardInterrupt


def ignore_interrupts() -> None:
    """Ignore SIGINT from here on. A SIGINT that lands while the handler is being replaced
    raises in this call; it asks for the stop already under way, so it is dropped and the
    replacement done again."""
    while True:
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            return
        except KeyboardInterrupt:
            continue
