"""The last line a node wrote to its log, as one short printable line for its agent's report.

A node that cannot start (its script missing, a module it imports absent) says why on its
last line (``python3: can't open file '/opt/x.py': [Errno 2] No such file or directory``) and
exits at once; the supervisor reads that line when it sees the exit, so that the report, the
decider's event and ``status`` can say it, not only the log file on that scale.
"""

import os
import re

from ..protocol import LOG_TAIL_CHARS

# Enough of the file's end for a last line; a longer line is cut anyway.
READ_BYTES = 4096
# The supervisor's own line before each start (agent/supervisor.py _spawn): not the node's.
START_MARK = '--- '
# Terminal colour and cursor sequences (rcutils colours its output on a terminal).
_ESCAPES = re.compile(r'\x1b\[[0-9;?]*[ -/]*[@-~]|\x1b[@-_]')


def one_line(text: str, max_chars: int = LOG_TAIL_CHARS) -> str:
    """``text`` on one line of printable characters, at most ``max_chars`` long (cut with
    '...'): escape sequences dropped, tabs and other control characters as spaces."""
    text = _ESCAPES.sub('', text)
    text = ''.join(c if c.isprintable() else ' ' for c in text).strip()
    text = ' '.join(text.split())
    if len(text) > max_chars:
        text = text[:max_chars - 3].rstrip() + '...'
    return text


def last_line(path: str, max_chars: int = LOG_TAIL_CHARS) -> str:
    """The last non-empty line the node wrote to ``path`` since its last start, as
    ``one_line`` makes it; '' when it wrote none or the file cannot be read."""
    try:
        with open(path, 'rb') as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - READ_BYTES))
            data = f.read(READ_BYTES)
    except OSError:
        return ''
    lines = data.decode('utf-8', 'replace').splitlines()
    if size > READ_BYTES and lines:
        lines = lines[1:] or lines      # the first may be the end of a longer line
    for line in reversed(lines):
        if line.startswith(START_MARK):
            return ''                   # nothing written since this start
        text = one_line(line, max_chars)
        if text:
            return text
    return ''


__all__ = ['last_line', 'one_line']
