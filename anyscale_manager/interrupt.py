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


def interrupt_once() -> None:
    """The first SIGINT raises KeyboardInterrupt; every later one is ignored.

    A supervisor repeats its SIGINT while a node cleans up (destroying the node, shutting
    rclpy down). With Python's own handler, a second one landing then raises in the cleanup
    and ends the process with a traceback. Installed before ``rclpy.init``, whose handler
    hands the signal on to it.
    """
    signal.signal(signal.SIGINT, _interrupt_then_ignore)


def _interrupt_then_ignore(signum, frame) -> None:
    ignore_interrupts()
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
