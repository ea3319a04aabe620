"""The demo's loopback ports are distinct (each flight binds seven of them)."""

from __future__ import annotations

import socket

from companion.flight import free_ports


def test_ports_picked_together_are_distinct_and_bindable() -> None:
    # 500 picks one at a time from ~28,000 ephemeral ports would repeat one with ~99 %
    # probability (birthday bound); held open together they cannot
    ports = free_ports(500)
    assert len(set(ports)) == 500
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", ports[0]))  # released again after the pick
