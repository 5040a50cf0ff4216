"""The KubeROS controller: a watch cache (watch.py), leader election on a Lease (leader_election.py), the
reconcile loop around the core's pure decisions (controller.py), its own manifests (manifests.py) and its command
line (cli.py, run as ``python -m`` of this package). Importing the package imports none of them."""
