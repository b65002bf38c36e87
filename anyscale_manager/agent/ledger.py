"""The claims on a shared host's capacity: one SQLite database (WAL mode) in ``agent.state_dir``
that the agents of every deployment on the host open, one transaction per question.

A scale declared ``shared`` is a machine that several deployments (robots) use. Each of its
agents (one per deployment) starts or activates a copy there only under a claim: (deployment,
node, CPU, memory, priority, lease). A claim is granted when it fits the host's capacity with
every other claim; an active copy claims its CPU and memory, a standby (inactive) copy its
memory only. A claim that does not fit is refused with who holds what, unless it may preempt:
claims of lower priority whose release would make it fit are then asked to leave (their agents
read the ask and tell their deciders, which take the node home), and the claim is granted once
they have gone. Nothing is handed over before.

Each agent renews its deployment's claims at every step; a claim not renewed within its lease
(a dead agent, its copies stopped by its warden meanwhile) is dropped by the next transaction.
The host's capacity is the figure of the first deployment that joined while no other was live;
a deployment whose file says otherwise is told so, and that figure still rules.

Times are the host's monotonic clock (one for every process of a Linux host). SQLite's
``BEGIN IMMEDIATE`` takes the write lock at the start, so two agents deciding at once are
serialised: the second sees the first's claim.
"""

import os
import sqlite3
from dataclasses import dataclass
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

FILE_NAME = 'claims.sqlite3'
# How long a writer waits for another's transaction (they last well under a millisecond).
BUSY_TIMEOUT_S = 5.0
_SCHEMA = (
    'CREATE TABLE IF NOT EXISTS host (id INTEGER PRIMARY KEY CHECK (id = 1), '
    'capacity_cpu REAL NOT NULL, memory_mb REAL NOT NULL, set_by TEXT NOT NULL)',
    'CREATE TABLE IF NOT EXISTS members (deployment TEXT PRIMARY KEY, capacity_cpu REAL NOT NULL,'
    ' memory_mb REAL NOT NULL, priority INTEGER NOT NULL, lease_until REAL NOT NULL)',
    'CREATE TABLE IF NOT EXISTS claims (deployment TEXT NOT NULL, node TEXT NOT NULL, '
    'cpu REAL NOT NULL, memory_mb REAL NOT NULL, active INTEGER NOT NULL, '
    'priority INTEGER NOT NULL, lease_until REAL NOT NULL, PRIMARY KEY (deployment, node))',
    # Claims waiting for lower ones to leave: the room they wait for is theirs (a claim of a
    # lower priority than a waiting one does not take it meanwhile).
    'CREATE TABLE IF NOT EXISTS waits (deployment TEXT NOT NULL, node TEXT NOT NULL, '
    'cpu REAL NOT NULL, memory_mb REAL NOT NULL, active INTEGER NOT NULL, '
    'priority INTEGER NOT NULL, lease_until REAL NOT NULL, PRIMARY KEY (deployment, node))',
    'CREATE TABLE IF NOT EXISTS asks (deployment TEXT NOT NULL, node TEXT NOT NULL, '
    'by_deployment TEXT NOT NULL, by_node TEXT NOT NULL, since REAL NOT NULL, '
    'PRIMARY KEY (deployment, node))',
)


class LedgerError(RuntimeError):
    """The ledger cannot be opened or written (a path, a permission, a corrupt file)."""


@dataclass(frozen=True)
class Claim:
    """What one copy holds, or asks to hold, on the host."""

    deployment: str
    node: str
    cpu: float             # reference-core percent; 0 for a standby copy
    memory_mb: float
    priority: int = 0
    active: bool = True

    def describe(self) -> str:
        what = f'{self.cpu:g} CPU' if self.active else 'standby'
        memory = f', {self.memory_mb:g} MiB' if self.memory_mb else ''
        return f'{self.deployment}/{self.node} ({what}{memory}, priority {self.priority})'


@dataclass(frozen=True)
class HostFigure:
    """The host's capacity, and what this deployment was told on joining."""

    capacity_cpu: float
    memory_mb: float       # 0: memory is not counted
    disagreement: str = ''


@dataclass(frozen=True)
class Answer:
    """A claim granted or not; ``waiting``: refused for now, lower claims were asked to leave
    (``reason`` names them) and it is granted once they have."""

    granted: bool
    reason: str
    waiting: bool = False


@dataclass(frozen=True)
class Share:
    """What one deployment sees of the host: its capacity and every other deployment's claims;
    ``asked``: its own nodes asked to leave, node -> by whom; ``reserved``: the others' claims
    that wait for lower ones to leave."""

    capacity_cpu: float
    memory_mb: float
    others: Tuple[Claim, ...]
    asked: Dict[str, str]
    # Other deployments' claims waiting for lower ones to leave: the room they reserve.
    reserved: Tuple[Claim, ...] = ()

    def others_cpu(self, below_priority: Optional[int] = None) -> float:
        """The CPU other deployments hold (only the claims of ``below_priority`` or more when
        given: what a deployment of that priority cannot preempt)."""
        return sum(c.cpu for c in self.others if c.active and
                   (below_priority is None or c.priority >= below_priority))

    def others_memory(self, below_priority: Optional[int] = None) -> float:
        return sum(c.memory_mb for c in self.others
                   if below_priority is None or c.priority >= below_priority)


class Ledger:
    """One deployment's agent's handle on the host's claims (one connection, one process)."""

    def __init__(self, state_dir: str, deployment: str, lease_s: float):
        self.path = os.path.join(state_dir, FILE_NAME)
        self.deployment = deployment
        self.lease_s = lease_s
        try:
            os.makedirs(state_dir, exist_ok=True)
            self._db = sqlite3.connect(self.path, timeout=BUSY_TIMEOUT_S, isolation_level=None,
                                       check_same_thread=False)
            self._db.execute('PRAGMA journal_mode=WAL')
            self._db.execute('PRAGMA synchronous=NORMAL')
            with self._write():
                for statement in _SCHEMA:
                    self._db.execute(statement)
        except (OSError, sqlite3.Error) as e:
            raise LedgerError(f'the claims ledger {self.path}: {e}') from e

    def close(self) -> None:
        self._db.close()

    # --- one transaction each --------------------------------------------------------------

    def join(self, capacity_cpu: float, memory_mb: float, priority: int,
             now: float) -> HostFigure:
        """Join (or renew membership of) the host with this deployment's figure of it; the
        host's figure comes back, with a disagreement said when they differ."""
        with self._write():
            self._expire(now)
            live = self._db.execute('SELECT COUNT(*) FROM members WHERE deployment != ?',
                                    (self.deployment,)).fetchone()[0]
            row = self._db.execute('SELECT capacity_cpu, memory_mb, set_by FROM host').fetchone()
            if row is None or not live:
                self._db.execute('INSERT OR REPLACE INTO host VALUES (1, ?, ?, ?)',
                                 (capacity_cpu, memory_mb, self.deployment))
                row = (capacity_cpu, memory_mb, self.deployment)
            self._db.execute('INSERT OR REPLACE INTO members VALUES (?, ?, ?, ?, ?)',
                             (self.deployment, capacity_cpu, memory_mb, priority,
                              now + self.lease_s))
        disagreement = ''
        if (row[0], row[1]) != (capacity_cpu, memory_mb):
            disagreement = (f'this deployment says the host has capacity_cpu {capacity_cpu:g}'
                            f" and memory_mb {memory_mb:g}; the host's figure, set by "
                            f'{row[2]}, is {row[0]:g} and {row[1]:g}, and rules')
        return HostFigure(row[0], row[1], disagreement)

    def renew(self, now: float) -> None:
        """Extend this deployment's membership and claims by a lease from ``now``."""
        with self._write():
            self._expire(now)
            for table in ('members', 'claims', 'waits'):
                self._db.execute(f'UPDATE {table} SET lease_until = ? WHERE deployment = ?',
                                 (now + self.lease_s, self.deployment))

    def claim(self, claim: Claim, now: float) -> Answer:
        """Grant ``claim`` (this deployment's) if it fits with every other; else refuse it,
        asking lower-priority claims to leave when their going would make it fit."""
        assert claim.deployment == self.deployment
        with self._write():
            self._expire(now)
            host = self._host()
            key = (claim.deployment, claim.node)
            mine = [c for c in self._claims() if (c.deployment, c.node) == key]
            held = [c for c in self._claims() if (c.deployment, c.node) != key]
            # The room others of a higher priority wait for, and the room this deployment's
            # other claims wait for: a robot that wants two nodes there asks room for both.
            reserved = [w for w in self._claims(table='waits') if (w.deployment, w.node) != key
                        and (w.deployment == claim.deployment or w.priority > claim.priority)]
            # A claim that asks no more than the one it replaces (a copy deactivated: its
            # standby claim) always fits: held and waited-for room may add up past the
            # capacity while a preemption is under way, and refusing the smaller claim would
            # keep the larger one, and the preemption, waiting for ever.
            shrinks = bool(mine) and _cpu(claim) <= _cpu(mine[0]) + 1e-9 \
                and claim.memory_mb <= mine[0].memory_mb + 1e-9
            over = '' if shrinks else _over(host, held + reserved, claim)
            row = (claim.deployment, claim.node, claim.cpu, claim.memory_mb, int(claim.active),
                   claim.priority, now + self.lease_s)
            if not over:
                self._db.execute('INSERT OR REPLACE INTO claims VALUES (?, ?, ?, ?, ?, ?, ?)', row)
                self._db.execute('DELETE FROM asks WHERE by_deployment = ? AND by_node = ?', key)
                self._db.execute('DELETE FROM waits WHERE deployment = ? AND node = ?', key)
                return Answer(True, f'granted: {claim.describe()} fits {_describe(host, held)}')
            # Only claims of a lower priority can make room; those waiting above it keep theirs.
            victims = _victims(host, held + reserved, claim)
            if victims:
                self._db.execute('INSERT OR REPLACE INTO waits VALUES (?, ?, ?, ?, ?, ?, ?)', row)
                for v in victims:
                    self._db.execute('INSERT OR IGNORE INTO asks VALUES (?, ?, ?, ?, ?)',
                                     (v.deployment, v.node, claim.deployment, claim.node, now))
                names = ', '.join(v.describe() for v in victims)
                return Answer(False, f'{claim.describe()} waits for {names} to leave (asked: '
                                     f'priority {claim.priority} is higher)', waiting=True)
            self._db.execute('DELETE FROM waits WHERE deployment = ? AND node = ?', key)
            return Answer(False, f'{claim.describe()} does not fit: {over}; '
                                 f'{_describe(host, held + reserved)}')

    def release(self, node: str, now: float) -> None:
        """Drop this deployment's claim on ``node`` (its copy is gone) and any ask of it."""
        with self._write():
            self._expire(now)
            for table in ('claims', 'waits'):
                self._db.execute(f'DELETE FROM {table} WHERE deployment = ? AND node = ?',
                                 (self.deployment, node))
            self._db.execute('DELETE FROM asks WHERE (deployment = ? AND node = ?) OR '
                             '(by_deployment = ? AND by_node = ?)',
                             (self.deployment, node, self.deployment, node))

    def withdraw(self, node: str, now: float) -> None:
        """This deployment no longer waits for room for ``node`` (it placed it elsewhere, or
        keeps it as it is): its reservation and its asks go, its claim stays."""
        with self._write():
            self._expire(now)
            self._db.execute('DELETE FROM waits WHERE deployment = ? AND node = ?',
                             (self.deployment, node))
            self._db.execute('DELETE FROM asks WHERE by_deployment = ? AND by_node = ?',
                             (self.deployment, node))

    def forget_waits(self, now: float) -> None:
        """Drop every wait of this deployment and the asks they made: a restarted agent does not
        know its predecessor's waits, and its renewals would keep them for as long as it
        lives; it waits anew for what its layout still wants."""
        with self._write():
            self._expire(now)
            self._db.execute('DELETE FROM waits WHERE deployment = ?', (self.deployment,))
            self._db.execute('DELETE FROM asks WHERE by_deployment = ?', (self.deployment,))

    def leave(self) -> None:
        """This deployment leaves the host: its membership, claims and asks go."""
        with self._write():
            for sql in ('DELETE FROM members WHERE deployment = ?',
                        'DELETE FROM claims WHERE deployment = ?',
                        'DELETE FROM waits WHERE deployment = ?',
                        'DELETE FROM asks WHERE deployment = ? OR by_deployment = ?'):
                self._db.execute(sql, (self.deployment,) * sql.count('?'))

    def share(self, now: float) -> Share:
        """The host as this deployment sees it (read only: no lock is taken)."""
        held = [c for c in self._claims(now) if c.deployment != self.deployment]
        reserved = [c for c in self._claims(now, 'waits') if c.deployment != self.deployment]
        host = self._host()
        asked = {node: f'{by}/{by_node}' for node, by, by_node in self._db.execute(
            'SELECT node, by_deployment, by_node FROM asks WHERE deployment = ?',
            (self.deployment,))}
        return Share(host[0], host[1], tuple(held), asked, tuple(reserved))

    def own(self, now: float) -> Dict[str, Claim]:
        """This deployment's live claims by node."""
        return {c.node: c for c in self._claims(now) if c.deployment == self.deployment}

    # --- inside a transaction -----------------------------------------------------------------

    def _write(self):
        return _Transaction(self._db, self.path)

    def _expire(self, now: float) -> None:
        for table in ('members', 'claims', 'waits'):
            self._db.execute(f'DELETE FROM {table} WHERE lease_until < ?', (now,))
        self._db.execute('DELETE FROM asks WHERE NOT EXISTS (SELECT 1 FROM claims c WHERE '
                         'c.deployment = asks.deployment AND c.node = asks.node)')

    def _host(self) -> Tuple[float, float]:
        row = self._db.execute('SELECT capacity_cpu, memory_mb FROM host').fetchone()
        return (0.0, 0.0) if row is None else (row[0], row[1])

    def _claims(self, now: Optional[float] = None, table: str = 'claims') -> List[Claim]:
        sql = f'SELECT deployment, node, cpu, memory_mb, priority, active FROM {table}'
        rows = (self._db.execute(sql + ' WHERE lease_until >= ?', (now,)) if now is not None
                else self._db.execute(sql))
        return [Claim(d, n, cpu, mem, prio, bool(active))
                for d, n, cpu, mem, prio, active in rows]


class _Transaction:
    """``BEGIN IMMEDIATE`` ... ``COMMIT`` (``ROLLBACK`` on an error), errors as LedgerError."""

    def __init__(self, db: sqlite3.Connection, path: str):
        self._db, self._path = db, path

    def __enter__(self) -> None:
        try:
            self._db.execute('BEGIN IMMEDIATE')
        except sqlite3.Error as e:
            raise LedgerError(f'the claims ledger {self._path}: {e}') from e

    def __exit__(self, kind, error, trace) -> bool:
        try:
            self._db.execute('ROLLBACK' if kind else 'COMMIT')
        except sqlite3.Error as e:
            raise LedgerError(f'the claims ledger {self._path}: {e}') from e
        if isinstance(error, sqlite3.Error):
            raise LedgerError(f'the claims ledger {self._path}: {error}') from error
        return False


def _totals(held: Iterable[Claim]) -> Tuple[float, float]:
    cpu = memory = 0.0
    for c in held:
        cpu += c.cpu if c.active else 0.0
        memory += c.memory_mb
    return cpu, memory


def _cpu(claim: Claim) -> float:
    """The CPU ``claim`` holds: a standby copy's none."""
    return claim.cpu if claim.active else 0.0


def _over(host: Tuple[float, float], held: Sequence[Claim], claim: Claim) -> str:
    """What ``claim`` would exceed beside ``held`` ('' when it fits)."""
    cpu, memory = _totals(held)
    want_cpu = claim.cpu if claim.active else 0.0
    if cpu + want_cpu > host[0] + 1e-9:
        return f'CPU {cpu:g} held + {want_cpu:g} > capacity {host[0]:g}'
    if host[1] > 0 and memory + claim.memory_mb > host[1] + 1e-9:
        return f'memory {memory:g} MiB held + {claim.memory_mb:g} > {host[1]:g} MiB'
    return ''


def _victims(host: Tuple[float, float], held: Sequence[Claim], claim: Claim) -> List[Claim]:
    """The fewest lower-priority claims of other deployments (lowest priority first, then the
    largest) whose going makes ``claim`` fit; [] when none would."""
    lower = sorted((c for c in held if c.priority < claim.priority
                    and c.deployment != claim.deployment),
                   key=lambda c: (c.priority, -(c.cpu if c.active else 0.0), -c.memory_mb))
    rest, chosen = list(held), []
    for c in lower:
        if not _over(host, rest, claim):
            break
        rest.remove(c)
        chosen.append(c)
    return chosen if chosen and not _over(host, rest, claim) else []


def _describe(host: Tuple[float, float], held: Sequence[Claim]) -> str:
    cpu, memory = _totals(held)
    holders = '; '.join(c.describe() for c in held) or 'nothing'
    room = f'capacity {host[0]:g} CPU' + (f', {host[1]:g} MiB' if host[1] > 0 else '')
    return f'{room}, held: {holders} ({cpu:g} CPU, {memory:g} MiB)'
