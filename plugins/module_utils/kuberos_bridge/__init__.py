"""KubeROS-Bridge: ROS 2 topics between the main cluster and a third-party cluster over gRPC.

A server in the main cluster and a client beside the module in the other cluster each run a ROS 2 node
in their own graph and exchange the messages of the topics in a topics file over one bidirectional gRPC
stream with mutual TLS. Any message type crosses: the bridge carries the serialized (CDR) bytes in a
protobuf envelope (bridge.proto) with the topic, type name, sequence, timestamps and the publishers' QoS.

- ``python -m ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge server|client|certs``
  runs it (``__main__``); docs/bridge.md describes it.
- ``generate_certificates(out_dir, server_name)`` writes the CA, server and client certificates and keys
  and returns their paths; it needs only the cryptography package (no gRPC, no ROS).
- ``load_topics(path)`` validates a topics file.
"""

from __future__ import annotations

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.topics import Topic, TopicsError, load_topics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.bridge_certs import generate_certificates

__all__ = ["Topic", "TopicsError", "generate_certificates", "load_topics"]
