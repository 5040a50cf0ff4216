"""The ROS-level checks the platform runs in the cluster: the live graph check's pod, run by the deploy, the rollout's
gates and the controller (which keeps the dashboard's ROS graph current)."""
