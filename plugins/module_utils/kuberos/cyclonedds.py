"""Cyclone DDS without multicast: the configuration file that gives a module instance its unicast peers.

Cyclone DDS has no discovery server. Pods have no multicast, so each participant is given the names of the
module instances it talks with (each instance's Service, `<instance>.<namespace>.svc.<cluster-domain>`, which
forwards the discovery ports of ``discovery_ports`` to the pod that runs it now) and finds them by unicast SPDP;
after that the participants talk pod to pod. The file is mounted under CONFIG_DIR and named by CYCLONEDDS_URI.

Measured with real Cyclone DDS 11 participants behind an iptables stand-in for kube-proxy
(tests/integration/test_cyclonedds_netns.py): a name that does not resolve aborts the process at start, a Service
whose pod does not exist yet does not (its packets are rejected, and the two meet when the later one starts); a
participant probes a Service address only in its first ~0.3 s and drops it after 30 s, so an instance that moves
(or starts late) is found again because its own list names the others: the lists must be symmetric, as the
renderer makes them. (Cyclone 11's ``Peer PruneDelay="inf"`` would keep probing, but 0.10, the version in ROS 2
Jazzy's rmw_cyclonedds_cpp, may not know the attribute, and an unknown one stops Cyclone at start.)
"""

from __future__ import annotations

from collections.abc import Sequence
from xml.sax.saxutils import escape

RMW_CYCLONEDDS = "rmw_cyclonedds_cpp"
CONFIG_DIR = "/etc/kuberos-cyclonedds"
# DDSI maps a participant index i of domain d to UDP port 7400 + 250 d + 10 + 2 i (discovery) and + 11 + 2 i (data):
# indices stay below 120 so that domains do not overlap, and domain ids stay at most 232 so that ports stay below 65536.
MAX_PARTICIPANTS = 120
MAX_DOMAIN_ID = 232


def config_xml(peers: Sequence[str], domain_id: int = 0, max_participants: int = 32) -> str:
    """The Cyclone DDS (0.10, 11) configuration of one module instance: unicast discovery of `peers`.

    - Domain Id is the instance's ROS_DOMAIN_ID: the settings apply to that domain only.
    - AllowMulticast false: no SPDP multicast is sent and no group joined; discovery is by the peer list only.
    - ParticipantIndex auto, MaxAutoParticipantIndex max_participants - 1: each process of the pod takes the
      lowest free index, so its discovery port is predictable, and a peer is probed on the ports of indices
      0..MaxAutoParticipantIndex. ("none", Cyclone's choice when multicast is available, uses random ports
      and makes unicast discovery impossible.) A pod runs at most max_participants DDS processes (rmw
      participants); rmw_cyclonedds_cpp's own localhost-only setting allows 33.
    - Peers: the other instances' DNS names, sorted and deduplicated so that the file (and the ConfigMap's
      hash) changes only when the set changes, and XML-escaped. AddLocalhost true: processes of the same pod
      find one another too. Names are resolved once, when the participant starts; an instance that moves
      later is found because its own peer list names this one (so lists must be symmetric), and Cyclone
      DDS 11 aborts the process at start if a name does not resolve.
    - No Interfaces: Cyclone picks the interface (a pod has eth0 besides lo); naming one would break on
      nodes where it is called otherwise.
    With rmw_cyclonedds_cpp (Jazzy), CYCLONEDDS_URI comes after the rmw's own fragment (from
    ROS_AUTOMATIC_DISCOVERY_RANGE), so these settings win over it.
    """
    if not 1 <= max_participants <= MAX_PARTICIPANTS:
        raise ValueError(f"max_participants must be 1 to {MAX_PARTICIPANTS}, not {max_participants}")
    if not 0 <= domain_id <= MAX_DOMAIN_ID:
        raise ValueError(f"domain_id must be 0 to {MAX_DOMAIN_ID}, not {domain_id}")
    addresses = [escape(peer, {'"': "&quot;"}) for peer in sorted(set(peers))]
    return "\n".join(
        [
            '<?xml version="1.0" encoding="UTF-8"?>',
            '<CycloneDDS xmlns="https://cdds.io/config">',
            f'  <Domain Id="{domain_id}">',
            "    <General>",
            "      <AllowMulticast>false</AllowMulticast>",
            "    </General>",
            "    <Discovery>",
            "      <ParticipantIndex>auto</ParticipantIndex>",
            f"      <MaxAutoParticipantIndex>{max_participants - 1}</MaxAutoParticipantIndex>",
            '      <Peers AddLocalhost="true">',
            *(f'        <Peer Address="{address}"/>' for address in addresses),
            "      </Peers>",
            "    </Discovery>",
            "  </Domain>",
            "</CycloneDDS>",
            "",
        ]
    )


def discovery_ports(domain_id: int = 0, max_participants: int = 32) -> list[int]:
    """The unicast discovery (SPDP) port of each participant index a peer is probed on: what a Service in front of
    an instance forwards, so that a peer's name always resolves (to the Service) and reaches whichever pod runs."""
    return [7400 + 250 * domain_id + 10 + 2 * index for index in range(max_participants)]
