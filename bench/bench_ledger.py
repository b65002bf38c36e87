"""What a claim decision costs on a shared host's ledger (agent/ledger.py), with many
deployments, and whether agents contending for it from separate processes ever over-commit.

    python bench/bench_ledger.py [--deployments 50] [--nodes 2] [--rounds 2000]
                                 [--processes 4] [--dir DIR]

One real SQLite database in a temporary folder (or DIR). Each of --deployments deployments
joins and claims --nodes nodes; then --processes processes, each the agent of some of those
deployments, claim and release copies at random for --rounds rounds each, as fast as they can.
Each decision (claim, release, renew, share) is timed inside its process. After every granted
claim the process reads the host's total of active claims in a transaction of its own: a total
over the capacity is an over-commit. Printed: p50, p95, max of each kind in milliseconds, the
claims granted and refused, and the over-commits seen (must be 0).
"""

import argparse
import multiprocessing
import os
import random
import shutil
import sqlite3
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..'))

from anyscale_manager.agent.ledger import Claim, Ledger  # noqa: E402

CAPACITY = 1000.0
LEASE_S = 1e6


def _agent(folder, names, nodes, rounds, seed, out):
    rng = random.Random(seed)
    books = {n: Ledger(folder, n, LEASE_S) for n in names}
    times = {'claim': [], 'release': [], 'renew': [], 'share': []}
    granted = refused = over = 0
    db = sqlite3.connect(os.path.join(folder, 'claims.sqlite3'), isolation_level=None)
    for i in range(rounds):
        name = rng.choice(names)
        book = books[name]
        node = f'n{rng.randrange(nodes)}'
        now = float(i)
        kind = rng.choice(('claim', 'claim', 'release', 'renew', 'share'))
        start = time.perf_counter()
        if kind == 'claim':
            answer = book.claim(Claim(name, node, rng.choice((10.0, 30.0, 60.0)), 0.0,
                                      rng.randrange(3)), now)
        elif kind == 'release':
            book.release(node, now)
        elif kind == 'renew':
            book.renew(now)
        else:
            book.share(now)
        times[kind].append((time.perf_counter() - start) * 1000.0)
        if kind == 'claim':
            if answer.granted:
                granted += 1
                db.execute('BEGIN')
                total = db.execute('SELECT COALESCE(SUM(cpu), 0) FROM claims WHERE active = 1'
                                   ).fetchone()[0]
                db.execute('COMMIT')
                over += total > CAPACITY + 1e-9
            else:
                refused += 1
    out.put((times, granted, refused, over))


def _pct(values, q):
    values = sorted(values)
    return values[min(len(values) - 1, int(q * len(values)))] if values else float('nan')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--deployments', type=int, default=50)
    ap.add_argument('--nodes', type=int, default=2)
    ap.add_argument('--rounds', type=int, default=2000)
    ap.add_argument('--processes', type=int, default=4)
    ap.add_argument('--dir', default='')
    a = ap.parse_args(argv)
    folder = a.dir or tempfile.mkdtemp(prefix='ledger_bench_')
    names = [f'robot_{i:02d}' for i in range(a.deployments)]
    for name in names:
        Ledger(folder, name, LEASE_S).join(CAPACITY, 0.0, 0, 0.0)
    context = multiprocessing.get_context('spawn')
    out = context.Queue()
    share = [names[i::a.processes] for i in range(a.processes)]
    procs = [context.Process(target=_agent, args=(folder, share[i], a.nodes, a.rounds, i, out))
             for i in range(a.processes) if share[i]]
    for p in procs:
        p.start()
    results = [out.get(timeout=600) for _ in procs]
    for p in procs:
        p.join(60)
    merged = {}
    for times, _, _, _ in results:
        for kind, values in times.items():
            merged.setdefault(kind, []).extend(values)
    print(f'ledger: {a.deployments} deployments x {a.nodes} nodes, {len(procs)} processes x '
          f'{a.rounds} rounds, capacity {CAPACITY:g}')
    for kind in ('claim', 'release', 'renew', 'share'):
        v = merged.get(kind, [])
        if v:
            print(f'  {kind:<8} n={len(v):<6} p50 {statistics.median(v):.2f} ms  '
                  f'p95 {_pct(v, 0.95):.2f} ms  max {max(v):.2f} ms')
    granted = sum(r[1] for r in results)
    refused = sum(r[2] for r in results)
    over = sum(r[3] for r in results)
    print(f'  claims granted {granted}, refused {refused}; over-commits seen {over}')
    if not a.dir:
        shutil.rmtree(folder, ignore_errors=True)
    return 1 if over else 0


if __name__ == '__main__':
    sys.exit(main())
