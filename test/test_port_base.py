"""The ports the tests' and benches' deployments listen on are ports nothing else takes here
(testbed/ports.py): past the kernel's ephemeral range and the test domains' DDS ports."""

from anyscale_manager.testbed.ports import LOW, SPAN, STRIDE_ROOM, port_base

# DDS (RTPS) ports of domain d: 7400 + 250 d and the 250 after; the tests draw d in 1-100 and
# also use d + 1 and, for a fleet's second robot, d + 100 (testbed/fleet.other_domain).
HIGHEST_TEST_DOMAIN = 201


def test_a_base_and_the_ports_after_it_are_past_the_ephemeral_range_and_dds():
    with open('/proc/sys/net/ipv4/ip_local_port_range') as f:
        _, ephemeral_high = map(int, f.read().split())
    assert LOW > ephemeral_high
    assert LOW > 7400 + 250 * (HIGHEST_TEST_DOMAIN + 1)
    for salt in range(0, 2000, 7):
        base = port_base(salt)
        assert LOW <= base and base + STRIDE_ROOM <= 65535


def test_two_salts_of_one_process_give_bases_apart():
    for salt in (7, 11, 13):
        assert port_base(salt) - port_base(0) in (salt, salt - (SPAN - STRIDE_ROOM))
