# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Options of the live graph check (declared topics), shared by the deploy and the rollout."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  graph_check:
    description:
      - Check the live ROS graph of every deployment whose modules declare C(topics) - after the deploy's wait, and in
        a rollout after every wave's soak, as part of its gate (a failure rolls the wave back).
      - A short-lived pod from O(bridge_image) (rclpy and the collection), on the node of one of the deployment's
        modules and with its ROS environment, joins the graph through the fleet's discovery servers as a super
        client; every declared publisher and subscription must be there, with the declared type, compatible QoS
        (what the endpoints really use) and a rate within its declared bounds (docs/software.md, "Declared topics").
      - C(false) skips it (a site whose nodes run no containers, such as kwok nodes).
    type: bool
    default: true
  graph_check_timeout:
    description: Seconds the check waits for every declared endpoint to appear in the graph.
    type: float
    default: 30
  graph_check_window:
    description: Seconds over which the check measures the rate of each topic that declares one.
    type: float
    default: 3
"""
