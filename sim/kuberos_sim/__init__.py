"""The KubeROS simulator: a rendered RosDeployment run for real on this machine.

``kuberos_sim.runtime`` runs the rendered manifests: a network namespace per node, a userspace fabric that
delays packets between them by the inventory's latencies, a CPU cgroup per node, and the Deployments'
processes exactly as rendered.
"""
