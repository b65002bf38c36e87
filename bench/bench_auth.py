#!/usr/bin/env python3
"""The cost of signed messages: sealing one and checking one, against plain JSON.

    python bench/bench_auth.py [--repeat 20000] [--nodes 11]

A layout of ``--nodes`` managed nodes (11 as on the ICAR test-bed) with a decider identity, as
the decider publishes it: ``seal`` (canonical JSON, HMAC-SHA256) on the decider's side; on an
agent's side decoding (what every layout costs without a key) and the gate's check (the HMAC
recomputed over the received JSON, the replay window), each in microseconds per message (median
of 5 rounds). Then the same for each status message at the test-bed's size (a scale status of
``--nodes`` nodes, a link status, a connection status of 8 readings, an event) and for a
heartbeat and its echo; and what that adds to each process at the test-bed's rates (two
scales, config/icar2015_testbed.yaml), in % of one core of this machine: derived from the
per-message figures and the rates, not measured on running processes. Pure Python, no ROS.
"""

import argparse
import statistics
import sys
import time

from anyscale_manager import protocol
from anyscale_manager.agent import warden
from anyscale_manager.protocol_auth import LayoutGate, Sealer, StatusGate, seal


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
        layout = protocol.Layout.from_json(text, 'bench')
        # On the clock of its making: the bench runs longer than the replay window.
        why = check.gate.check(text, layout, layout.stamp)
        if why:
            raise SystemExit(f'bench_auth: a sealed layout was refused: {why}')

    check_us = per_call_us(check, args.repeat)
    print(f'layout of {args.nodes} nodes, {len(texts[0])} bytes signed ({len(plain[0])} '
          f'unsigned); microseconds per message, median of 5 rounds of {args.repeat}:')
    print(f'  decider: build and serialise {build_us:.1f}; build and seal {seal_us:.1f} '
          f'(+{seal_us - build_us:.1f})')
    print(f'  agent:   decode {decode_us:.1f}; decode and check (HMAC, replay window) '
          f'{check_us:.1f} (+{check_us - decode_us:.1f})')
    extra = status_costs(key, args)
    beat_us = heartbeat_costs(key, args)
    # Messages per second at the test-bed's rates (robot = master, one remote scale).
    rates = {'ScaleStatus': 2.0, 'ConnectionStatus': 4.0, 'LinkStatus': 10.0}
    scales = 2
    sent = {'master agent': {'ScaleStatus': 2.0, 'ConnectionStatus': 4.0, 'LinkStatus': 10.0},
            'remote agent': {'ScaleStatus': 2.0, 'ConnectionStatus': 4.0}}
    checked = {'master agent': {'ConnectionStatus': 4.0 * scales},
               'decider': {k: v * (scales if k != 'LinkStatus' else 1)
                           for k, v in rates.items()}}
    print("extra CPU from signing at the test-bed's rates (derived), % of one core:")
    for who in ('master agent', 'remote agent', 'decider'):
        us = sum(extra[k][0] * hz for k, hz in sent.get(who, {}).items())
        us += sum(extra[k][1] * hz for k, hz in checked.get(who, {}).items())
        if who == 'master agent':
            us += 10.0 * (beat_us[0] + beat_us[3])     # sign each beat, check each echo
        print(f'  {who}: {us / 1e4:.3f} %')
    print(f'  warden (per remote scale): {10.0 * (beat_us[1] + beat_us[2]) / 1e4:.3f} %')
    return 0


def status_costs(key: bytes, args) -> dict:
    """Message kind -> (extra us to seal, extra us to check), printed as it goes."""
    now = time.time()
    readings = {f'conn_{i}': protocol.ConnectionReading(rate_hz=10.0, bytes_per_s=2800.0,
                                                        below_for_s=0.0, level=protocol.OK,
                                                        ended_below_s=None,
                                                        recent_bytes_per_s=2790.0)
                for i in range(8)}
    samples = {
        'ScaleStatus': lambda: protocol.ScaleStatus(
            scale='laptop', stamp=now, cpu_total=123.4, capacity_cpu=700.0,
            cpu_by_node={f'node_{i}': 10.0 + i for i in range(args.nodes)}, mem_percent=41.0,
            load_1m=1.2, cpu_source='cgroup'),
        'LinkStatus': lambda: protocol.LinkStatus(
            master='robot', remote='laptop', stamp=now, up=True, rtt_ms=1.2, loss=0.0,
            bandwidth_available_kbps=42000.0, bandwidth_available_age_s=12.0,
            bandwidth_used_kbps=6400.0, queueing_delay_ms=2.0, congested=False,
            peer_agent='alive', peer_agent_for_s=100.0),
        'ConnectionStatus': lambda: protocol.ConnectionStatus(scale='laptop', stamp=now,
                                                              connections=readings),
        'Event': lambda: protocol.Event(stamp=now, kind='migrate', node='amcl',
                                        from_scale='robot', to_scale='laptop',
                                        reason='the most CPU-intensive migratable node',
                                        generation=3),
    }
    out = {}
    print('status messages, microseconds per message:')
    for name, make in samples.items():
        cls = type(make())
        sealer = Sealer(key, 'agent laptop')
        texts = [sealer.seal(make()) for _ in range(args.repeat)]
        plain_text = make().to_json()
        plain_us = per_call_us(lambda i: make().to_json(), args.repeat)
        seal_us = per_call_us(lambda i: sealer.seal(make()), args.repeat)
        decode_us = per_call_us(lambda i: cls.from_json(plain_text, 'bench'), args.repeat)

        def check(i: int) -> None:
            if i == 0:
                check.gate = StatusGate(key, 30.0)
            why = check.gate.check(texts[i], cls.from_json(texts[i], 'bench'), now)
            if why:
                raise SystemExit(f'bench_auth: a sealed {name} was refused: {why}')
        check_us = per_call_us(check, args.repeat)     # a new gate each round (i == 0)
        out[name] = (seal_us - plain_us, check_us - decode_us)
        print(f'  {name:17s} {len(texts[0]):5d} B: build+serialise {plain_us:.1f}, +seal '
              f'{seal_us - plain_us:.1f}; decode {decode_us:.1f}, +check '
              f'{check_us - decode_us:.1f}')
    return out


def heartbeat_costs(key: bytes, args) -> tuple:
    """(beat sign, beat check + echo sign, echo sign part, echo check) extra microseconds."""
    beats = [warden.beat('icar2015_testbed', 'laptop', i, key, 'a1b2c3d4e5f60718')
             for i in range(args.repeat)]
    plain = [warden.beat('icar2015_testbed', 'laptop', i, None, 'a1b2c3d4e5f60718')
             for i in range(args.repeat)]
    echoes = [warden.answer(b, 'icar2015_testbed', 'laptop', 'alive', 1.0, key) for b in beats]
    plain_echoes = [warden.answer(b, 'icar2015_testbed', 'laptop', 'alive', 1.0)
                    for b in plain]
    sign = per_call_us(lambda i: warden.beat('icar2015_testbed', 'laptop', i, key, 'a1'),
                       args.repeat) - per_call_us(
        lambda i: warden.beat('icar2015_testbed', 'laptop', i, None, 'a1'), args.repeat)
    answer = per_call_us(lambda i: warden.answer(beats[i], 'icar2015_testbed', 'laptop',
                                                 'alive', 1.0, key), args.repeat) - \
        per_call_us(lambda i: warden.answer(plain[i], 'icar2015_testbed', 'laptop', 'alive',
                                            1.0), args.repeat)
    parse = per_call_us(lambda i: warden.parse_echo(echoes[i], 'icar2015_testbed', key,
                                                    'a1b2c3d4e5f60718'), args.repeat) - \
        per_call_us(lambda i: warden.parse_echo(plain_echoes[i], 'icar2015_testbed', None,
                                                'a1b2c3d4e5f60718'), args.repeat)
    print(f'heartbeats, extra microseconds: sign a beat {sign:.1f}; check it and sign the echo '
          f'{answer:.1f}; check an echo {parse:.1f}')
    return sign, answer, 0.0, parse


if __name__ == '__main__':
    sys.exit(main())
