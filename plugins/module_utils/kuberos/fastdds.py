"""Fast DDS transports for every module container: UDPv4 only, never shared memory (SHM).

Fast DDS (2.14.5 as in requirements-ros.txt; rmw_fastrtps_cpp) enables its SHM transport by default and uses it, and
only it, towards any participant whose GUID carries the same *host id* as its own. The host id is 16 bits: the MD5
of the process's non-loopback IPv4 addresses, folded (``host_id``; a real participant at 10.214.9.77 carried
2841 in its GUID, the value ``host_id(["10.214.9.77"])`` gives). Nothing checks that the two participants really see
the same /dev/shm, so two participants with equal host ids but separate /dev/shm match, and every message between
them is lost, silently: the publisher counts the subscriber, nothing arrives, nothing is logged.

Measured with real processes in the lab of tests/integration/test_shared_memory.py (which keeps the UDPv4 column and
the two losing rows as tests): a fast-discovery-server, a talker and a listener (rclpy), each "pod" a network
namespace with a /dev/shm of its own (tmpfs), containers of one pod joining its network and mount namespaces; 100
messages at 50 Hz, reliable; through the discovery server as rendered (ROS_DISCOVERY_SERVER) and with simple
discovery, the same result both ways:

=====================================================  =======================  ==========================
layout                                                 default transports       FASTDDS_BUILTIN_TRANSPORTS
                                                                                =UDPv4
=====================================================  =======================  ==========================
A  two pods (own network namespace, own /dev/shm)      matched, 100 of 100      matched, 100 of 100
A' two pods whose addresses give the same host id      matched, 0 of 100        matched, 100 of 100
   (10.214.0.47 and 10.214.0.254: both 15901)
B  hostNetwork pods (one network namespace, same IPs,  matched, 0 of 100        matched, 100 of 100
   own /dev/shm each)
C  two containers of one pod (one network namespace,   matched, 100 of 100      matched, 100 of 100
   one /dev/shm)                                       (over SHM)
=====================================================  =======================  ==========================

Discovery took 1.2-1.4 s through the server (0.4 s simple) in every row. The losing rows are deterministic: 0
received on every run (B: 5 runs through the server, one of them publishing 3052 messages over 61 s, and 1 simple; A':
3 through the server, 1 simple). A' is how the lab models pods on different nodes as much as on one node (separate
network namespaces and /dev/shm, one bridge: tests/integration/test_discovery_netns.py), so any two pods, on any nodes,
whose IPv4 addresses collide in those 16 bits lose every message between them. For one pair of pods the chance is 1
in 65536; a fleet whose modules exchange topics between E pairs of pods expects E/65536 such pairs, and a rescheduled
pod draws again with its new address. SHM is used only when both ends have it: in A' with the talker on default
transports and the listener on UDPv4, or the other way round, 100 of 100 arrived, so pods rendered before and after
the setting work together during a rollout. A module whose address collides with a discovery server's is unharmed
(100 of 100 with either setting).

With the setting Fast DDS creates no file in /dev/shm at all (with the default each participant leaves eight
``fastrtps_*`` files), so this version honours the variable, in rclpy's participants and in fast-discovery-server
alike.

What a module loses: SHM between the containers of one pod (layout C), the only layout pods have where it works.
Those messages now cross the pod's loopback as UDP, fragmented above 64 KiB. In the same lab (rclpy, so Python's own
cost is in the numbers) 100 messages of 1 MB took 0.16-0.22 s over SHM against 0.28-0.36 s over UDP, 25 of 4 MB
0.11-0.13 s against 0.12-0.30 s; small messages do not notice. How to offer it back: the containers of one pod
already share one /dev/shm (the runtime's, 64 MiB) and one network namespace, so a per-module option can render
``FASTDDS_BUILTIN_TRANSPORTS=DEFAULT`` for that module alone, with an emptyDir of medium Memory mounted at /dev/shm
when the runtime's 64 MiB is too small. Its exposure is then only pairs of such opted-in pods whose host ids collide,
since SHM needs both ends (above).
"""

from __future__ import annotations

import hashlib
import ipaddress
from collections.abc import Iterable

# The environment of every container that runs a Fast DDS participant (modules, bridges, discovery servers).
TRANSPORT_ENV: tuple[tuple[str, str], ...] = (("FASTDDS_BUILTIN_TRANSPORTS", "UDPv4"),)


def host_id(addresses: Iterable[str]) -> int:
    """The host id Fast DDS 2.14 puts in bytes 2-3 of every GUID prefix, from the process's non-loopback IPv4
    addresses in the order the system lists them: MD5 over each address as a 16-byte locator address (12 zero bytes,
    then the 4 address bytes), the digest's eight 16-bit big-endian words XORed together (checked against a real
    participant with one address)."""
    digest_input = hashlib.md5(usedforsecurity=False)
    for address in addresses:
        digest_input.update(bytes(12) + ipaddress.IPv4Address(address).packed)
    digest = digest_input.digest()
    value = 0
    for index in range(0, len(digest), 2):
        value ^= (digest[index] << 8) | digest[index + 1]
    return value
