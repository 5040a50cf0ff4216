"""The emulated round-trip time between two nodes: one rule, pure, for every pair.

The inventory defines latency only between a robot and a node (``Inventory.latency_ms``); like the latency
probe (ping, average RTT) the simulator reads it as a round-trip time. For the pairs it does not define:

- a node and itself: 0 (loopback; never crosses the fabric);
- a robot's computer and an edge or cloud node: ``Inventory.latency_ms(robot, node)`` (the robot's link
  override, else the node's latency, else the tier default);
- two robots' computers: ``LAN_RTT_MS``, the robots' local network;
- two edge or cloud nodes of one tier and one resource group (a site, a cloud region): ``LAN_RTT_MS``;
- any other two edge or cloud nodes (edge-cloud, two sites, two regions): the larger of their latencies to
  the robots, as the farther node's uplink dominates; so edge-cloud is the cloud node's latency.

Each direction of a pair is delayed by half the RTT.

Bandwidth and loss belong to a node's own link (``kuberos_link_bandwidth``, ``kuberos_link_loss``: a robot's wireless
link, a cloud VM's uplink), the same each way: a packet leaves through its sender's link and arrives through its
receiver's, each limited and lossy as the inventory says (``link_rates_bps``, ``link_losses``).
"""

from __future__ import annotations

LAN_RTT_MS = 1.0


def rtt_ms(inventory, a: str, b: str) -> float:
    """Round-trip time in milliseconds between the nodes ``a`` and ``b`` of ``inventory`` (symmetric)."""
    for name in (a, b):
        if name not in inventory.nodes:
            raise ValueError(f"{name!r} is not a node of the inventory; known nodes: {', '.join(inventory.nodes)}")
    if a == b:
        return 0.0
    first, second = inventory.nodes[a], inventory.nodes[b]
    if first.tier == "onboard" and second.tier == "onboard":
        return LAN_RTT_MS
    if first.tier == "onboard" or second.tier == "onboard":
        robot_node, other = (first, second) if first.tier == "onboard" else (second, first)
        return float(inventory.latency_ms(robot_node.robot, other.name))
    if first.tier == second.tier and first.resource_group == second.resource_group:
        return LAN_RTT_MS
    return float(max(first.latency_ms, second.latency_ms))


def one_way_delays_ms(inventory, nodes: list[str]) -> dict[str, dict[str, float]]:
    """Source node -> destination node -> one-way delay in milliseconds (half the RTT), for every ordered pair."""
    return {a: {b: rtt_ms(inventory, a, b) / 2.0 for b in nodes if b != a} for a in nodes}


def link_rates_bps(inventory, nodes: list[str]) -> dict[str, float]:
    """Node -> its link's bandwidth in bits per second, for the nodes whose link is limited."""
    return {n: inventory.nodes[n].link_bps for n in nodes if inventory.nodes[n].link_bps}


def link_losses(inventory, nodes: list[str]) -> dict[str, float]:
    """Node -> the fraction of packets its link loses (each way), for the nodes whose link loses any."""
    return {n: inventory.nodes[n].link_loss for n in nodes if inventory.nodes[n].link_loss}
