"""A live view on a terminal: one screen redrawn in place, as ``top`` does; plain snapshots else.

On a terminal the view takes the alternate screen (the shell's screen comes back untouched when
it ends) with the cursor hidden, and each frame moves the cursor home and rewrites the lines,
clearing what the previous frame left to their right and below; a frame is cut to the
terminal's size, so it never scrolls. When it closes (normally, on an exception, on Ctrl-C) it
gives the screen back and prints the last frame once, as a plain record of what was seen.
When the output is not a terminal (a pipe, a file, ``TERM=dumb``), each frame is appended as a
plain snapshot with no escape codes, at most every ``plain_every_s``.
"""

import os
import sys
from typing import List, Optional, TextIO, Tuple

ENTER = '\x1b[?1049h\x1b[?25l'     # the alternate screen, cursor hidden
LEAVE = '\x1b[?25h\x1b[?1049l'     # cursor shown, the normal screen back
HOME = '\x1b[H'
CLEAR_LINE = '\x1b[K'              # to the end of the line
CLEAR_BELOW = '\x1b[J'             # to the end of the screen
DEFAULT_SIZE = (80, 24)


def is_terminal(stream: TextIO) -> bool:
    """Whether ``stream`` is a terminal that understands cursor movement."""
    try:
        return stream.isatty() and os.environ.get('TERM', '') != 'dumb'
    except (AttributeError, ValueError):     # no isatty, or a closed stream
        return False


def fit(text: str, columns: int, rows: int) -> List[str]:
    """The lines of ``text`` cut to a screen: long lines cut (one column spare so the terminal
    never wraps), and a view taller than the screen ends with one line that says so."""
    width, height = max(1, columns - 1), max(1, rows)
    lines = [line[:width] for line in text.split('\n')]
    if len(lines) > height:
        more = len(lines) - height + 1
        lines = lines[:height - 1] + [f'... {more} more line(s): enlarge the terminal'[:width]]
    return lines


def frame(text: str, columns: int, rows: int) -> str:
    """The escape sequence that redraws the whole screen with ``text``, from the top left."""
    # CR LF: the next line starts at the left even where the terminal does not add the CR.
    return HOME + (CLEAR_LINE + '\r\n').join(fit(text, columns, rows)) + CLEAR_LINE + \
        CLEAR_BELOW


class LiveScreen:
    """Shows successive frames of a text view on ``stream`` (a context manager).

    ``terminal`` forces the mode (default: ``is_terminal(stream)``). ``keep_last``: print the
    last frame on the normal screen when a terminal view closes.
    """

    def __init__(self, stream: Optional[TextIO] = None, terminal: Optional[bool] = None,
                 plain_every_s: float = 0.0, keep_last: bool = True):
        self.stream = stream if stream is not None else sys.stdout
        self.terminal = is_terminal(self.stream) if terminal is None else terminal
        self.plain_every_s = plain_every_s
        self.keep_last = keep_last
        self.last: Optional[str] = None
        self._opened = False
        self._last_plain: Optional[float] = None

    def __enter__(self) -> 'LiveScreen':
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def open(self) -> None:
        if self.terminal and not self._opened:
            self._opened = True
            self._write(ENTER)

    def size(self) -> Tuple[int, int]:
        """(columns, rows) of the terminal now (it may have been resized)."""
        try:
            size = os.get_terminal_size(self.stream.fileno())
            if size.columns > 0 and size.lines > 0:
                return size.columns, size.lines
        except (AttributeError, OSError, ValueError):
            pass
        return DEFAULT_SIZE

    def show(self, text: str, now: float) -> bool:
        """Draw ``text``; False when a plain snapshot was skipped (too soon after the last)."""
        if self.terminal:
            self.open()
            self.last = text
            self._write(frame(text, *self.size()))
            return True
        if self._last_plain is not None and now - self._last_plain < self.plain_every_s:
            return False
        self._last_plain = now
        self.last = text
        self._write(text + '\n\n')
        return True

    def close(self) -> None:
        """Give the screen back (idempotent); print the last frame on it."""
        if not self._opened:
            return
        self._opened = False
        try:
            self._write(LEAVE + (self.last + '\n' if self.keep_last and self.last else ''))
        except (OSError, ValueError):
            pass    # the terminal is gone (a hang-up, a closed stream): nothing to give back

    def _write(self, text: str) -> None:
        self.stream.write(text)
        self.stream.flush()


__all__ = ['CLEAR_BELOW', 'CLEAR_LINE', 'ENTER', 'HOME', 'LEAVE', 'LiveScreen', 'fit', 'frame',
           'is_terminal']
