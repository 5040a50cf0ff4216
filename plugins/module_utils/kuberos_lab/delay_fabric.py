"""The network fabric: IP packets between the hosts' TUN devices, each delayed by its pair's one-way delay, and
limited and lost as the two hosts' links are.

This kernel has no netem qdisc, so link delay is emulated in userspace. Every host namespace has a TUN device
(``eth0``); this process, in the root namespace, attaches to each of them (it enters the host's network
namespace only to open ``/dev/net/tun`` and attach by name, then returns), reads the IPv4 packets the host
sends and writes each to the destination host's TUN once ``delay_ms[src][dst]`` has passed (a timer heap;
``select`` waits with microsecond resolution). Dropped and counted, never forwarded:

- ``multicast``: multicast and broadcast destinations; participants meet only through discovery servers;
- ``unknown_destination``: an address no host has;
- ``not_ipv4``: anything but IPv4 (the hosts have IPv6 disabled; this catches the rest);
- ``queue_full``: a pair already holding ``queue_packets`` packets or ``queue_bytes`` bytes in flight, or all
  pairs together ``total_bytes``;
- ``write_error``: the destination TUN refused the packet;
- ``host_removed``: in flight to a host detached by a reload (its fd is closed and its number may be reused);
- ``loss``: lost on the sender's or the receiver's link (``link_loss``: the fraction each link loses, each way);
- ``link_queue_full``: a limited link (``link_bps``) already holding ``link_queue_s`` seconds of packets to send,
  as a router's queue in front of a slow link drops (tail drop).

A limited link sends one packet at a time at its rate, each way apart: a packet waits for the sender's link (its
uplink), then for the receiver's (its downlink), then for the pair's delay.

Standard library only; run as a script (``python fabric.py CONFIG.json``) by the runtime. CONFIG::

    {"hosts": [{"node": "edge-1", "netns": "krs-...", "tun": "eth0", "address": "10.213.64.10",
                "routes": ["10.232.1.0/24"]}, ...],                # optional: networks behind the host (pods)
     "delay_ms": {"fetch-1": {"edge-1": 2.5, ...}, ...},        # one-way, per ordered pair
     "link_bps": {"fetch-1": 20000000.0},                       # optional: links with a bandwidth, bits/s
     "link_loss": {"fetch-1": 0.02},                            # optional: links that lose packets, each way
     "link_queue_s": 0.5, "seed": null,                         # optional
     "stats_file": "...", "stats_interval": 1.0, "queue_packets": 8192, "queue_bytes": 33554432,
     "total_bytes": 268435456}

Prints ``fabric ready`` once every TUN is attached. SIGHUP: read CONFIG again (hosts can come and go while it
runs): attach the hosts it lists that are new (by ``node``), detach those it no longer lists, take its ``delay_ms``,
``link_bps`` and ``link_loss`` (packets in flight keep the time they were given; every other setting stays as started), then print
``fabric reloaded: N hosts``; a new host that cannot be attached, or a CONFIG that cannot be read, changes nothing
and prints ``fabric reload failed: <reason>``. SIGTERM or SIGINT: stop, write the statistics, exit 0. Every signal
wakes the loop at once (``signal.set_wakeup_fd``), not only when its wait runs out.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import heapq
import json
import os
import random
import select
import signal
import struct
import sys
import time
from dataclasses import dataclass, field

CLONE_NEWNET = 0x40000000
TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
PR_SET_TIMERSLACK = 29
READ_SIZE = 65536 + 64
READ_BATCH = 64  # packets read from one TUN before the others get a turn
DROP_REASONS = (
    "multicast", "unknown_destination", "not_ipv4", "queue_full", "write_error", "host_removed", "loss", "link_queue_full",
)  # fmt: skip


def ipv4_destination(packet: bytes) -> bytes | None:
    """The destination address of an IPv4 packet (4 bytes), None for anything else."""
    if len(packet) < 20 or packet[0] >> 4 != 4:
        return None
    return packet[16:20]


def parse_address(address: str) -> bytes:
    """``10.213.64.10`` -> its 4 bytes."""
    parts = [int(x) for x in address.split(".")]
    if len(parts) != 4 or not all(0 <= x <= 255 for x in parts):
        raise ValueError(f"{address!r} is not an IPv4 address")
    return bytes(parts)


def parse_network(cidr: str) -> tuple[int, int]:
    """``10.232.1.0/24`` -> (network, mask) as integers."""
    address, _sep, bits = cidr.partition("/")
    mask = (0xFFFFFFFF << (32 - int(bits or 32))) & 0xFFFFFFFF
    return int.from_bytes(parse_address(address), "big") & mask, mask


def is_multicast_or_broadcast(address: bytes, broadcasts: frozenset[bytes] = frozenset()) -> bool:
    """224.0.0.0/4, 255.255.255.255, or one of the subnet broadcast addresses given."""
    return 224 <= address[0] <= 239 or address == b"\xff\xff\xff\xff" or address in broadcasts


@dataclass
class PairStats:
    packets: int = 0
    bytes: int = 0
    drops: int = 0
    in_flight_packets: int = 0
    in_flight_bytes: int = 0
    max_in_flight_bytes: int = 0


@dataclass
class Stats:
    packets: int = 0
    bytes: int = 0
    drops: dict[str, int] = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    pairs: dict[tuple[str, str], PairStats] = field(default_factory=dict)
    in_flight_bytes: int = 0
    started: float = field(default_factory=time.monotonic)

    def to_dict(self, delay_ms: dict) -> dict:
        elapsed = max(time.monotonic() - self.started, 1e-9)
        usage = os.times()
        return {
            "packets": self.packets,
            "bytes": self.bytes,
            "drops": dict(self.drops),
            "dropped": sum(self.drops.values()),
            "seconds": round(elapsed, 3),
            "cpu_seconds": round(usage.user + usage.system, 3),
            "pairs": {
                f"{src}->{dst}": {
                    "packets": p.packets,
                    "bytes": p.bytes,
                    "drops": p.drops,
                    "delay_ms": delay_ms.get(src, {}).get(dst, 0.0),
                    "max_in_flight_bytes": p.max_in_flight_bytes,
                }
                for (src, dst), p in sorted(self.pairs.items())
            },
        }


def _links(config: dict) -> tuple[dict[str, float], dict[str, float]]:
    """A config's ``link_bps`` (node -> bits/s, above zero) and ``link_loss`` (node -> fraction from 0 to below 1)."""
    rates = {node: float(bps) for node, bps in (config.get("link_bps") or {}).items()}
    losses = {node: float(fraction) for node, fraction in (config.get("link_loss") or {}).items()}
    if any(not bps > 0 for bps in rates.values()) or any(not 0 <= f < 1 for f in losses.values()):
        raise ValueError(f"link_bps must be above zero and link_loss from 0 to below 1: {rates}, {losses}")
    return rates, losses


def _libc_call(name: str, *args) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if getattr(libc, name)(*args) != 0:
        error = ctypes.get_errno()
        raise OSError(error, f"{name}: {os.strerror(error)}")


def open_tun(netns: str, name: str) -> int:
    """A non-blocking fd attached to the TUN device ``name`` of the named network namespace."""
    home = os.open("/proc/self/ns/net", os.O_RDONLY)
    try:
        target = os.open(f"/var/run/netns/{netns}", os.O_RDONLY)
        try:
            _libc_call("setns", target, CLONE_NEWNET)
            try:
                fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
                try:
                    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH22x", name.encode(), IFF_TUN | IFF_NO_PI))
                except OSError:
                    os.close(fd)
                    raise
            finally:
                _libc_call("setns", home, CLONE_NEWNET)
        finally:
            os.close(target)
    finally:
        os.close(home)
    return fd


class Fabric:
    """The hosts' TUN fds, the delay per ordered pair, the packets in flight."""

    def __init__(self, config: dict):
        self.config = config
        self.delay_ms: dict[str, dict[str, float]] = config["delay_ms"]
        self.queue_packets = int(config.get("queue_packets", 8192))
        self.queue_bytes = int(config.get("queue_bytes", 32 << 20))
        self.total_bytes = int(config.get("total_bytes", 256 << 20))
        self.broadcasts = frozenset(parse_address(b) for b in config.get("broadcasts", []))
        self.link_bps, self.link_loss = _links(config)
        self.link_queue_s = float(config.get("link_queue_s", 0.5))
        self.random = random.Random(config.get("seed"))
        self.link_free: dict[tuple[str, str], float] = {}  # (node, "up" | "down") -> when its link has sent its queue
        self.fds: dict[int, str] = {}  # fd -> node
        self.by_address: dict[bytes, tuple[int, str]] = {}  # address -> (fd, node)
        self.by_network: list[tuple[int, int, int, str]] = []  # (network, mask, fd, node): networks behind a host
        self.heap: list[tuple[float, int, int, bytes, PairStats]] = []
        self.sequence = 0
        self.stats = Stats()
        self.running = True
        self.reload_requested = False  # SIGHUP: run() calls its ``reload`` at the end of the current turn

    def attach(self, opener=open_tun) -> None:
        """Attach every host of the config; ``opener(netns, tun)`` gives a host's fd."""
        self.reload(self.config, opener)

    def reload(self, config: dict, opener=open_tun) -> None:
        """Make the hosts those ``config`` lists: the new ones (by node) attached, those attached already kept as
        they are, the others detached; its ``delay_ms`` taken. All or nothing: when a new host cannot be attached
        (``opener`` raises) or its entry is not valid, the fds opened so far are closed and the error raised, with
        nothing changed."""
        hosts = {host["node"]: host for host in config["hosts"]}
        delay_ms = {src: {dst: float(ms) for dst, ms in row.items()} for src, row in config["delay_ms"].items()}
        attached = self.by_node()
        kept = {address for address, (_fd, node) in self.by_address.items() if node in hosts}
        new = []
        for node, host in hosts.items():
            if node in attached:
                continue
            address = parse_address(host["address"])
            if address in kept:
                raise ValueError(f"{node}: address {host['address']} is another host's")
            kept.add(address)
            new.append((host, address, [parse_network(route) for route in host.get("routes", ())]))
        opened: list[tuple[int, dict, bytes, list[tuple[int, int]]]] = []
        try:
            for host, address, routes in new:
                opened.append((opener(host["netns"], host.get("tun", "eth0")), host, address, routes))
        except BaseException:
            for fd, *_entry in opened:
                os.close(fd)
            raise
        for node in [n for n in attached if n not in hosts]:
            self.detach(node)
        for fd, host, address, routes in opened:
            self.fds[fd] = host["node"]
            self.by_address[address] = (fd, host["node"])
            self.by_network.extend((network, mask, fd, host["node"]) for network, mask in routes)
        link_bps, link_loss = _links(config)
        self.config = {
            **self.config, "hosts": list(config["hosts"]), "delay_ms": delay_ms, "link_bps": link_bps, "link_loss": link_loss
        }  # fmt: skip
        self.delay_ms, self.link_bps, self.link_loss = delay_ms, link_bps, link_loss

    def by_node(self) -> dict[str, int]:
        """Node -> the fd of its TUN, for every attached host."""
        return {node: fd for fd, node in self.fds.items()}

    def detach(self, node: str) -> None:
        """Close a host's fd and forget its address and networks; its packets in flight are dropped
        (``host_removed``), so that a new fd of the same number never receives them."""
        fd = self.by_node()[node]
        kept = []
        for entry in self.heap:
            if entry[2] != fd:
                kept.append(entry)
                continue
            size = len(entry[3])
            pair = entry[4]
            pair.in_flight_packets -= 1
            pair.in_flight_bytes -= size
            self.stats.in_flight_bytes -= size
            self._drop("host_removed", pair)
        if len(kept) != len(self.heap):
            heapq.heapify(kept)
            self.heap = kept
        del self.fds[fd]
        self.by_address = {a: target for a, target in self.by_address.items() if target[0] != fd}
        self.by_network = [entry for entry in self.by_network if entry[2] != fd]
        os.close(fd)

    def lookup(self, destination: bytes) -> tuple[int, str] | None:
        """The host a destination address belongs to: its own address, else a network behind it."""
        target = self.by_address.get(destination)
        if target is None and self.by_network:
            value = int.from_bytes(destination, "big")
            for network, mask, fd, node in self.by_network:
                if value & mask == network:
                    return fd, node
        return target

    def _pair(self, src: str, dst: str) -> PairStats:
        pair = self.stats.pairs.get((src, dst))
        if pair is None:
            pair = self.stats.pairs[(src, dst)] = PairStats()
        return pair

    def _drop(self, reason: str, pair: PairStats | None = None) -> None:
        self.stats.drops[reason] += 1
        if pair is not None:
            pair.drops += 1

    def receive(self, src: str, packet: bytes, now: float) -> None:
        """Queue one packet a host sent, or drop it."""
        destination = ipv4_destination(packet)
        if destination is None:
            return self._drop("not_ipv4")
        if is_multicast_or_broadcast(destination, self.broadcasts):
            return self._drop("multicast")
        target = self.lookup(destination)
        if target is None:
            return self._drop("unknown_destination")
        fd, dst = target
        pair = self._pair(src, dst)
        size = len(packet)
        if (
            pair.in_flight_packets >= self.queue_packets
            or pair.in_flight_bytes + size > self.queue_bytes
            or self.stats.in_flight_bytes + size > self.total_bytes
        ):
            return self._drop("queue_full", pair)
        lost = 1.0 - (1.0 - self.link_loss.get(src, 0.0)) * (1.0 - self.link_loss.get(dst, 0.0))
        if lost and self.random.random() < lost:
            return self._drop("loss", pair)
        sent = now
        for node, way in ((src, "up"), (dst, "down")):
            rate = self.link_bps.get(node)
            if rate:
                free = max(sent, self.link_free.get((node, way), 0.0))
                if free - now > self.link_queue_s:
                    return self._drop("link_queue_full", pair)
                sent = free + size * 8 / rate
                self.link_free[(node, way)] = sent
        pair.in_flight_packets += 1
        pair.in_flight_bytes += size
        pair.max_in_flight_bytes = max(pair.max_in_flight_bytes, pair.in_flight_bytes)
        self.stats.in_flight_bytes += size
        self.sequence += 1
        heapq.heappush(self.heap, (sent + self.delay_ms.get(src, {}).get(dst, 0.0) / 1000.0, self.sequence, fd, packet, pair))
        return None

    def deliver_due(self, now: float) -> None:
        """Write every packet whose time has come to its destination TUN."""
        while self.heap and self.heap[0][0] <= now:
            _due, _seq, fd, packet, pair = heapq.heappop(self.heap)
            size = len(packet)
            pair.in_flight_packets -= 1
            pair.in_flight_bytes -= size
            self.stats.in_flight_bytes -= size
            try:
                os.write(fd, packet)
            except OSError:
                self._drop("write_error", pair)
                continue
            pair.packets += 1
            pair.bytes += size
            self.stats.packets += 1
            self.stats.bytes += size

    def read_ready(self, fd: int) -> None:
        src = self.fds[fd]
        for _read in range(READ_BATCH):
            try:
                packet = os.read(fd, READ_SIZE)
            except BlockingIOError:
                return
            except OSError as error:
                if error.errno in (errno.EAGAIN, errno.EINTR):
                    return
                raise
            self.receive(src, packet, time.monotonic())

    def write_stats(self) -> None:
        path = self.config.get("stats_file")
        if not path:
            return
        tmp = f"{path}.tmp"
        with open(tmp, "w", encoding="utf-8") as handle:
            json.dump(self.stats.to_dict(self.delay_ms), handle, indent=1, sort_keys=True)
        os.replace(tmp, path)

    def run(self, wakeup: int | None = None, reload=None) -> None:
        """Forward until ``running`` is cleared. ``wakeup``: an fd that becomes readable when a signal arrives (it is
        drained); ``reload``: called once a turn is over when ``reload_requested`` was set, to reload."""
        interval = float(self.config.get("stats_interval", 1.0))
        next_stats = time.monotonic() + interval
        watched = [wakeup] if wakeup is not None else []
        fds = watched + list(self.fds)
        while self.running:
            now = time.monotonic()
            wait = min(next_stats, self.heap[0][0] if self.heap else next_stats) - now
            try:
                readable, _writable, _failed = select.select(fds, [], [], max(wait, 0.0))
            except InterruptedError:
                readable = []
            for fd in readable:
                if fd == wakeup:
                    _drain(fd)
                else:
                    self.read_ready(fd)
            now = time.monotonic()
            self.deliver_due(now)
            if now >= next_stats:
                self.write_stats()
                next_stats = now + interval
            if self.reload_requested and self.running:
                self.reload_requested = False
                if reload is not None:
                    reload()
                fds = watched + list(self.fds)


def _drain(fd: int) -> None:
    """Read a non-blocking fd empty."""
    try:
        while os.read(fd, 512):
            pass
    except (BlockingIOError, InterruptedError):
        pass


def main(argv: list[str]) -> int:
    # A command line program's entry point (python -m ...), not code a module runs: it prints and exits.
    # pylint: disable=ansible-bad-function
    if len(argv) != 2:
        print("usage: fabric.py CONFIG.json", file=sys.stderr)
        return 2
    with open(argv[1], encoding="utf-8") as handle:
        fabric = Fabric(json.load(handle))

    def stop(_signum, _frame) -> None:
        fabric.running = False

    def hangup(_signum, _frame) -> None:
        fabric.reload_requested = True

    def reload() -> None:
        try:
            with open(argv[1], encoding="utf-8") as handle:
                config = json.load(handle)
            fabric.reload(config)
        except (OSError, ValueError, LookupError, TypeError, AttributeError) as error:
            print(f"fabric reload failed: {error}", flush=True)
            return
        fabric.write_stats()
        print(f"fabric reloaded: {len(fabric.fds)} hosts", flush=True)

    wakeup, woken = os.pipe()
    os.set_blocking(wakeup, False)
    os.set_blocking(woken, False)
    signal.set_wakeup_fd(woken, warn_on_full_buffer=False)
    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGHUP, hangup)
    try:
        ctypes.CDLL(None).prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0)  # wake within a microsecond of the deadline
        os.setpriority(os.PRIO_PROCESS, 0, -10)
    except (OSError, AttributeError):
        pass
    fabric.attach()
    fabric.write_stats()
    print(f"fabric ready: {len(fabric.fds)} hosts", flush=True)
    fabric.run(wakeup, reload)
    fabric.write_stats()
    print(f"fabric stopped: {fabric.stats.packets} packets forwarded, {sum(fabric.stats.drops.values())} dropped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))  # pylint: disable=ansible-bad-function
