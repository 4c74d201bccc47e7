"""With `--dds-network loopback` (the default) a node's DDS sockets are bound to 127.0.0.1 only: no
socket on the wildcard address, none on another interface, no IPv6 socket, and still seen and called
by rclpy (Fast DDS on 127.0.0.1 with 127.0.0.1 as initial peer, tests/fastdds_loopback.xml).

The node's UDP sockets are found through /proc: the inodes of its `socket:[N]` file descriptors,
looked up in /proc/<pid>/net/udp and udp6.
"""

from __future__ import annotations

import os
import socket
import struct
from pathlib import Path

from std_srvs.srv import Trigger
from patchwalk_msgs.srv import ListMotions


def _socket_inodes(pid: int) -> set[str]:
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:["):-1])
    return inodes


def _ipv4(hex_addr: str) -> str:
    # /proc/net/udp prints the address as the host-order u32 in hex.
    return socket.inet_ntoa(struct.pack("<I", int(hex_addr, 16)))


def udp_sockets(pid: int) -> list[str]:
    """`address:port` of every UDP socket of process `pid` (IPv6 ones as `[v6]:port`)."""
    inodes = _socket_inodes(pid)
    found = []
    for table, v6 in (("udp", False), ("udp6", True)):
        path = Path(f"/proc/{pid}/net/{table}")
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            if fields[9] not in inodes:
                continue
            addr_hex, port_hex = fields[1].split(":")
            addr = f"[{addr_hex}]" if v6 else _ipv4(addr_hex)
            found.append(f"{addr}:{int(port_hex, 16)}")
    return found


def test_loopback_node_binds_every_udp_socket_to_127_0_0_1(ros, start_node):
    node = start_node("step_executor", "--dds-network", "loopback")
    ros.wait_for_nodes("/step_executor")
    sockets = udp_sockets(node.proc.pid)
    # Discovery unicast, user-traffic unicast and the sender at least.
    assert len(sockets) >= 3, sockets
    assert all(s.startswith("127.0.0.1:") for s in sockets), f"UDP sockets not on 127.0.0.1: {sockets}"
    print(f"step_executor UDP sockets (loopback): {sorted(sockets)}")

    # rclpy still finds and calls it.
    assert ros.call(Trigger, "/step_executor/stop").success
    assert ros.call(ListMotions, "/step_executor/list_motions").success
