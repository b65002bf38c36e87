"""Signed messages: the deployment key, the canonical form, the HMAC and the replay window.

Pure: no ROS, the clock is passed in. A layout is sealed by adding ``auth`` = HMAC-SHA256,
keyed by the deployment's key, over the canonical JSON of every other field (keys sorted, no
spaces, ASCII). A receiver recomputes it over the JSON it received, so both sides hash the same
bytes whatever order the fields travelled in. What the HMAC gives: a layout comes from a holder
of the key and was not altered on the way. What it does not: secrecy (anyone on the domain still
reads it), nor a check of who joins the domain; DDS Security does both (docs/decider.md).

Replay: a message signed once stays valid, so each sender numbers its messages (``seq``) and
stamps them with its wall clock; a receiver refuses a sequence number not above the last one it
accepted from that sender, and a stamp further than ``window_s`` from its own clock (which
bounds a replay to a receiver that has not heard the sender yet). The window needs the scales'
clocks within it of each other (NTP or chrony).
"""

import hashlib
import hmac
import itertools
import json
import os
import secrets
import stat
from collections import OrderedDict
from typing import Any, Mapping, Optional

from .protocol import Message, error_kind

KEY_BYTES = 32
MIN_KEY_BYTES = 16
DEFAULT_WINDOW_S = 30.0


# What a gate's reason to drop a message begins with: each kind is logged on its own (a forgery
# and a replay in the same ten seconds are two lines, not one and a count).
REFUSALS = ('not valid JSON', 'not a JSON object', 'not signed', 'cannot be put in canonical',
            'bad authenticator', 'signed but names no', 'no sequence number', 'stamped',
            'sequence')


def refusal_kind(why: str) -> str:
    """The kind of a reason to drop a message, a key from a fixed set for the throttled log:
    a gate's (one of ``REFUSALS``; as wrapped by a caller, 'dropped ...: <reason>', it is read
    after the last ': '), else the decoder's (``protocol.error_kind``)."""
    reason = why.rsplit(': ', 1)[-1]
    return next((kind for kind in REFUSALS if reason.startswith(kind)), None) \
        or error_kind(why)


class KeyFileError(ValueError):
    """A key file that cannot be used, said in one line."""


def write_key(path: str) -> None:
    """A new random key in a new file, readable by its owner only; never overwrites."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise KeyFileError(f'{path}: exists; not overwriting a key (remove it first)') from None
    except OSError as e:
        raise KeyFileError(f'{path}: cannot create: {e.strerror}') from None
    with os.fdopen(fd, 'w') as f:
        os.fchmod(f.fileno(), 0o600)      # whatever the umask
        f.write(secrets.token_hex(KEY_BYTES) + '\n')


def load_key(path: str) -> bytes:
    """The key in ``path``; KeyFileError when it is missing, open to others or malformed."""
    path = os.path.expanduser(path)
    try:
        info = os.stat(path)
    except OSError as e:
        raise KeyFileError(f'security.key_file {path}: cannot read: {e.strerror}') from None
    if not stat.S_ISREG(info.st_mode):
        raise KeyFileError(f'security.key_file {path}: not a regular file')
    if info.st_mode & 0o077:
        raise KeyFileError(f'security.key_file {path}: mode {stat.S_IMODE(info.st_mode):04o} '
                           "lets group or others read it; a key must be its owner's only "
                           f'(chmod 600 {path})')
    try:
        with open(path, encoding='ascii') as f:
            text = f.read(4096).strip()
        key = bytes.fromhex(text)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise KeyFileError(f'security.key_file {path}: not a hex key written by '
                           f'anyscale-manager keygen ({e})') from None
    if len(key) < MIN_KEY_BYTES:
        raise KeyFileError(f'security.key_file {path}: {len(key)} bytes, at least '
                           f'{MIN_KEY_BYTES} needed')
    return key


def canonical(data: Mapping[str, Any]) -> bytes:
    """The signed bytes: every field but ``auth``, keys sorted, no spaces."""
    body = {k: v for k, v in data.items() if k != 'auth'}
    return json.dumps(body, sort_keys=True, separators=(',', ':'),
                      allow_nan=False).encode('ascii')


def sign(key: bytes, data: Mapping[str, Any]) -> str:
    return hmac.new(key, canonical(data), hashlib.sha256).hexdigest()


def seal(key: Optional[bytes], message: Message) -> str:
    """The message as JSON, with ``auth`` when there is a key."""
    data = message.to_dict()
    data.pop('auth', None)
    if key is not None:
        data['auth'] = sign(key, data)
    return json.dumps(data, sort_keys=True, separators=(',', ':'))


def check_signature(key: bytes, text: str) -> str:
    """'' when ``text`` carries a valid ``auth`` for ``key``, else why not."""
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        return 'not valid JSON'
    if not isinstance(data, dict):
        return 'not a JSON object'
    tag = data.get('auth')
    if not isinstance(tag, str):
        return 'not signed (no auth field), and this deployment has a key'
    try:
        expected = sign(key, data)
    except (TypeError, ValueError):
        return 'cannot be put in canonical form'
    if not hmac.compare_digest(expected, tag):
        return 'bad authenticator (forged, altered, or signed with another key)'
    return ''


class ReplayGuard:
    """Per sender, the last accepted sequence number; and the stamp window."""

    def __init__(self, window_s: float = DEFAULT_WINDOW_S, max_senders: int = 256):
        self.window_s = window_s
        self.max_senders = max_senders
        self._last: 'OrderedDict[str, int]' = OrderedDict()

    def check(self, sender: str, seq: Optional[int], stamp: float, now_wall: float) -> str:
        """'' when the message may be new, else why it is refused (nothing is recorded)."""
        if seq is None:
            return 'no sequence number (needed against replays when there is a key)'
        skew = now_wall - stamp
        if abs(skew) > self.window_s:
            return (f'stamped {skew:+.1f} s from this clock, outside the {self.window_s:g} s '
                    'window (a replay, or clocks apart)')
        last = self._last.get(sender)
        if last is not None and seq <= last:
            return f'sequence {seq} not above {last}, already accepted from it (a replay)'
        return ''

    def accept(self, sender: str, seq: int) -> None:
        self._last[sender] = seq
        self._last.move_to_end(sender)
        while len(self._last) > self.max_senders:
            self._last.popitem(last=False)

    def last(self, sender: str) -> Optional[int]:
        return self._last.get(sender)


class Gate:
    """What a receiver checks on a signed topic before looking at a message."""

    def __init__(self, key: Optional[bytes], window_s: float = DEFAULT_WINDOW_S):
        self.key = key
        self.replay = ReplayGuard(window_s)

    @property
    def keyed(self) -> bool:
        return self.key is not None

    def check_from(self, text: str, sender: Optional[str], seq: Optional[int], stamp: float,
                   now_wall: float) -> str:
        """'' to go on, else the reason to drop it. Without a key everything goes on. A
        message that passes is recorded: the same one again is a replay."""
        if self.key is None:
            return ''
        why = check_signature(self.key, text)
        if why:
            return why
        if not sender:
            return 'signed but names no sender'
        why = self.replay.check(sender, seq, stamp, now_wall)
        if why:
            return why
        self.replay.accept(sender, seq)
        return ''


class LayoutGate(Gate):
    """The gate of /anyscale/layout: the sender is the layout's decider."""

    def check(self, text: str, layout: Any, now_wall: float) -> str:
        if self.key is not None and layout.decider is None:
            why = check_signature(self.key, text)
            return why or 'signed but names no decider'
        sender = None if layout.decider is None else layout.decider.id
        return self.check_from(text, sender, layout.seq, layout.stamp, now_wall)


class StatusGate(Gate):
    """The gate of a signed status topic (scale, link and connection status, events, plan
    check): the sender is the process named in the message's ``sender``."""

    def check(self, text: str, message: Any, now_wall: float) -> str:
        return self.check_from(text, message.sender, message.seq, message.stamp, now_wall)


class Sealer:
    """A sender of signed status messages: its key, its id (``prefix``/a random id drawn at its
    start, so that a restarted sender is a new one to every replay guard) and its count. Without
    a key, messages go out unsigned, as plain JSON."""

    def __init__(self, key: Optional[bytes], prefix: str):
        self.key = key
        self.sender = f'{prefix[:100]}/{secrets.token_hex(8)}'
        self._seq = itertools.count(1)      # safe across the threads of one process

    def seal(self, message: Message) -> str:
        if self.key is None:
            return message.to_json()
        message.sender = self.sender
        message.seq = next(self._seq)
        return seal(self.key, message)
