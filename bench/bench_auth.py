#!/usr/bin/env python3
"""The cost of signed layouts: sealing one and checking one, against decoding it alone.

    python bench/bench_auth.py [--repeat 20000] [--nodes 11]

A layout of ``--nodes`` managed nodes (11 as on the ICAR test-bed) with a decider identity, as
the decider publishes it: ``seal`` (canonical JSON, HMAC-SHA256) on the decider's side; on an
agent's side decoding (what every layout costs without a key) and the gate's check (the HMAC
recomputed over the received JSON, the replay window), each in microseconds per message (median
of 5 rounds). Pure Python, no ROS.
"""

import argparse
import statistics
import sys
import time

from anyscale_manager import protocol
from anyscale_manager.protocol_auth import LayoutGate, seal


def per_call_us(fn, repeat: int) -> float:
    rounds = []
    for _ in range(5):
        t0 = time.perf_counter()
        for i in range(repeat):
            fn(i)
        rounds.append((time.perf_counter() - t0) / repeat * 1e6)
    return statistics.median(rounds)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--repeat', type=int, default=20000)
    parser.add_argument('--nodes', type=int, default=11)
    args = parser.parse_args()
    if args.repeat < 1 or args.nodes < 1:
        parser.error('--repeat and --nodes must be >= 1')
    key = bytes(range(32))
    who = protocol.DeciderIdentity(id='9f2c4e7a1b3d5f60', host='robot', pid=4242,
                                   started=time.time())

    def layout(seq: int) -> protocol.Layout:
        return protocol.Layout(generation=7, deployment='icar2015_testbed',
                               assignments={f'node_{i}': 'laptop' if i % 2 else 'robot'
                                            for i in range(args.nodes)},
                               reason='migrate amcl: CPU 79, the most CPU-intensive migratable '
                                      'node that fits', stamp=time.time(), decider=who, seq=seq)

    texts = [seal(key, layout(i + 1)) for i in range(args.repeat)]
    plain = [layout(i + 1).to_json() for i in range(args.repeat)]
    seal_us = per_call_us(lambda i: seal(key, layout(i + 1)), args.repeat)
    build_us = per_call_us(lambda i: layout(i + 1).to_json(), args.repeat)
    decode_us = per_call_us(lambda i: protocol.Layout.from_json(plain[i], 'bench'), args.repeat)

    def check(i: int) -> None:
        if i == 0:
            check.gate = LayoutGate(key, 30.0)
        text = texts[i]
        why = check.gate.check(text, protocol.Layout.from_json(text, 'bench'), time.time())
        if why:
            raise SystemExit(f'bench_auth: a sealed layout was refused: {why}')

    check_us = per_call_us(check, args.repeat)
    print(f'layout of {args.nodes} nodes, {len(texts[0])} bytes signed ({len(plain[0])} '
          f'unsigned); microseconds per message, median of 5 rounds of {args.repeat}:')
    print(f'  decider: build and serialise {build_us:.1f}; build and seal {seal_us:.1f} '
          f'(+{seal_us - build_us:.1f})')
    print(f'  agent:   decode {decode_us:.1f}; decode and check (HMAC, replay window) '
          f'{check_us:.1f} (+{check_us - decode_us:.1f})')
    return 0


if __name__ == '__main__':
    sys.exit(main())
