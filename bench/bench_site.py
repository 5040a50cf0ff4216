#!/usr/bin/env python3
"""Site benchmark: from bare machines to a running fleet, on the sample site as lab machines (docs/cluster-setup.md).

The same chain as ``tests/site/test_site_chain.py`` (``kuberos_lab.site_lab.SiteChain``), each step timed from the
start of its command to its end, on seven lab machines (three control planes behind a keepalived virtual IP, an edge
worker, two robots, a cloud VM behind the WireGuard tunnel):

- ``bare_to_ready_s``: ``site.yml`` on machines just booted (nothing of Kubernetes on them) until every node is
  Ready; ``second_run_s`` and ``second_run_changed`` (must be 0): ``site.yml`` again;
- ``cross_node_pod_traffic``, ``cloud_pod_traffic_over_vpn``, ``policy_denied``: a robot's pod fetching a 256 KiB
  file from pods on the edge worker and on the cloud VM, and a pod the NetworkPolicy does not admit;
- ``ready_to_app_running_s``: ``controller.yml`` (in the cluster) and ``deploy.yml`` of the example until every pod
  is Ready where placed; ``pick_cycles_completed``: the robot's simulated hardware with the real pods;
- ``register_robot_s``, ``undeploy_s``; ``site_run_with_robot_offline_ok`` and ``_s``: ``fetch-02`` powered off and
  a robot in the inventory where no machine answers, ``site.yml`` succeeds and names both once;
  ``api_back_after_losing_the_vip_holder_s``: the power of the control
  plane holding the virtual IP cut, until the API answers again through it.

Writes ``bench/results/site.json`` with ``--json``. As root; after ``make test``'s builds.

    .venv/bin/python bench/bench_site.py --json bench/results/site.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_deploy import REPO, log, machine

sys.path[:0] = [str(REPO / ".collections")]
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import site_lab  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.real_nodes import snapshot_host  # noqa: E402


def step(what: str, result) -> None:
    """Stop the benchmark at a step that failed, with its output's tail."""
    if getattr(result, "returncode", 0) != 0:
        raise SystemExit(f"bench: {what} failed:\n{result.stdout[-4000:]}{result.stderr[-2000:]}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--cycles", type=int, default=1)
    args = parser.parse_args()
    before = snapshot_host()
    folder = Path(tempfile.mkdtemp(prefix="bench-site-"))
    spec = site_lab.lab_example(str(REPO / "examples" / "pick-and-place.yml"), str(folder / "pick-and-place.yml"))
    lab = site_lab.SiteLab(str(folder / "state"), str(REPO), log=log)
    chain = site_lab.SiteChain(lab, spec, log=log)
    started = time.monotonic()
    try:
        site_vars = lab.up()
        chain.figures["machines_up_s"] = round(time.monotonic() - started, 1)
        step("site.yml", chain.site())
        robot = "fetch-01.robots.example.internal"  # the node name the sample gives fetch-01
        chain.network(site_vars["kuberos_lab_toolbox_image"], robot, "edge-d", "edge-b", site_lab.CLOUD_VM)
        step("site.yml again", chain.second_site())
        step("controller.yml and deploy.yml", chain.app(str(folder / "rendered")))
        chain.pick_cycles("fetch-01", site_lab.FLEET, cycles=args.cycles)
        step("register_robot.yml", chain.register_robot())
        step("deploy.yml with the new robot", chain.deploy(str(folder / "rendered")))
        step("undeploy.yml", chain.undeploy())
        step("site.yml with a robot off", chain.site_with_robots_offline("fetch-02", "fetch-09.robots.example.internal",
                                                                          site_lab.UNUSED_ADDRESS))  # fmt: skip
        chain.lose_vip_holder()
    finally:
        lab.down(remove=True)
    chain.figures["host_as_before"] = snapshot_host() == before
    chain.figures["total_s"] = round(time.monotonic() - started, 1)
    figures = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), **chain.figures}
    print(json.dumps(figures, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")
    return 0 if chain.figures.get("second_run_changed") == 0 else 1


if __name__ == "__main__":
    os.umask(0o022)
    sys.exit(main())
