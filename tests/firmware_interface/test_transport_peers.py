"""Who a UDP transport listens to: ``udpout`` reads only its configured peer, from
the local address that routes to it; ``udpin`` never moves its peer by itself."""

from __future__ import annotations

import socket

from devkit.timing import wait_until
from firmware_interface.transport import UdpInTransport, local_address_towards, open_transport


def udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock


def test_udpout_binds_the_address_that_routes_to_its_peer_not_every_interface():
    with udp_socket() as autopilot:
        port = autopilot.getsockname()[1]
        with open_transport(f"udpout:127.0.0.1:{port}") as link:
            # Today's code bound 0.0.0.0: reachable from every network the board is on.
            assert link.local_address[0] == "127.0.0.1"
    assert local_address_towards("127.0.0.1", 9) == "127.0.0.1"


def read_next(link) -> tuple[bytes, object]:
    """The next datagram the transport lets through (bounded wait)."""
    got: list = []
    assert wait_until(lambda: got.append(link.read_from(0.05)) or got[-1][0])
    return got[-1]


def test_udpout_keeps_only_datagrams_from_its_peer_and_counts_the_others():
    with udp_socket() as autopilot, udp_socket() as stranger, udp_socket() as same_host:
        with open_transport(f"udpout:127.0.0.1:{autopilot.getsockname()[1]}") as link:
            ours = link.local_address
            stranger.sendto(b"from a stranger", ours)
            same_host.sendto(b"same host, other port", ours)
            autopilot.sendto(b"from the autopilot", ours)
            # Today's code handed all three to the link.
            assert read_next(link) == (b"from the autopilot", autopilot.getsockname())
            assert link.foreign_datagrams == 2
            assert link.peer == autopilot.getsockname()


def test_udpin_reports_each_sender_and_never_moves_its_peer_by_itself():
    with open_transport("udpin:127.0.0.1:0") as link, udp_socket() as a, udp_socket() as b:
        assert isinstance(link, UdpInTransport) and link.datagrams
        a.sendto(b"x", link.local_address)
        assert read_next(link) == (b"x", a.getsockname())
        assert link.peer is None
        link.set_peer(a.getsockname())
        b.sendto(b"y", link.local_address)
        assert read_next(link) == (b"y", b.getsockname())
        assert link.peer == a.getsockname()  # a datagram from b changed nothing
        link.write(b"reply")
        assert a.recvfrom(16)[0] == b"reply"
