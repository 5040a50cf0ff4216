"""The emulated round-trip time between two nodes: the rule lives in the collection's pure core
(plugins/module_utils/kuberos_cluster/link_delays.py), shared with the local cluster's real nodes."""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster.link_delays import (  # noqa: F401
    LAN_RTT_MS,
    link_losses,
    link_rates_bps,
    one_way_delays_ms,
    rtt_ms,
)
