"""The test-bed's error: one type for every step of building or driving it."""


class HarnessError(RuntimeError):
    """The test-bed could not be started or driven; the message says which step and why."""


__all__ = ['HarnessError']
