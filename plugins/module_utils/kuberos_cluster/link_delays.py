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
