#!/usr/bin/env python3
"""Day 2 of a site, on the sample site as lab machines (docs/cluster-setup.md, "Operations").

The site chain of ``tests/site/test_site_chain.py`` (``kuberos_lab.site_lab.SiteChain``) with its day-2 steps, each
timed from the start of its command to its end:

- ``node_removed_clean``, ``remove_fetch_03_s``, ``remove_edge_d_s``: ``remove_node.yml`` for the robot that
  ``register_robot.yml`` added (its onboard modules stopped by its deployment's pass) and for the edge worker (its
  modules moved); Nodes gone, machines reset, the inventory forgets them (``kuberos_lab.site_removal``);
- ``etcd_backup_s``, ``etcd_restore_s``, ``restored_objects_back``: ``etcd_backup.yml``, the app's deployment
  record deleted, ``etcd_restore.yml`` of the snapshot, the record back (``kuberos_lab.site_operations``);
- ``cert_renew_s``, ``cert_not_after_moved``, ``api_unavailable_during_renew_max_s``: ``certificates.yml -e
  renew=true``, the API asked through the virtual IP every 0.4 s;
- ``control_plane_replaced_s``, ``vip_holders_max``, ``etcd_members_after_replace``,
  ``api_unavailable_during_replace_max_s``: the first control plane (the virtual IP's holder, the VPN's hub)
  powered off, rebuilt from a bare disk, ``site.yml`` again (``kuberos_lab.site_replace``); in the same run a robot
  powered off and one that never joined (``site_run_with_robot_offline_ok`` and ``_s``);
- ``site_reset_s``, ``site_reset_clean``: ``reset.yml`` takes the site apart.

- ``upgrade_from``, ``upgrade_to``, ``upgrade_s``, ``api_unavailable_max_s``, ``app_downtime_max_s``,
  ``pick_cycles_during_upgrade``, ``onboard_pods_restarted_by_upgrade``, ``vip_holders_max_during_upgrade``: the site
  built at ``--upgrade-from`` (default the Makefile's ``UPGRADE_FROM``, built by ``make test``) and ``upgrade.yml`` to
  the pinned release with the app running and pick cycles going on (``kuberos_lab.site_upgrade``).

Writes ``bench/results/lifecycle.json`` with ``--json``. As root; after ``make test``'s builds. About 45 minutes on two
cores.

    .venv/bin/python bench/bench_lifecycle.py --json bench/results/lifecycle.json
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
from bench_site import step

sys.path[:0] = [str(REPO / ".collections")]
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import record_name  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import (  # noqa: E402
    kubeadm_images,
    site_lab,
    site_operations,
    site_removal,
    site_replace,
    site_upgrade,
)

UPGRADE_FROM = "v1.33.13"  # the Makefile's UPGRADE_FROM


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the figures here")
    parser.add_argument("--upgrade-from", default=UPGRADE_FROM, help="the older release the site is built at")
    args = parser.parse_args()
    os.environ[site_lab.KUBERNETES_VERSION_ENV] = args.upgrade_from
    folder = Path(tempfile.mkdtemp(prefix="bench-lifecycle-"))
    spec = site_lab.lab_example(str(REPO / "examples" / "pick-and-place.yml"), str(folder / "pick-and-place.yml"))
    lab = site_lab.SiteLab(str(folder / "state"), str(REPO), log=log)
    chain = site_lab.SiteChain(lab, spec, log=log)
    started = time.monotonic()
    try:
        site_vars = lab.up()
        step("site.yml", chain.site())
        step("controller.yml and deploy.yml", chain.app(str(folder / "rendered")))
        chain.pick_cycles("fetch-01", site_lab.FLEET, cycles=1)
        target = kubeadm_images.pinned_versions()["kubernetes"]
        upgraded = site_upgrade.upgrade_site(chain, target, site_vars["kuberos_lab_upgrade_binaries"], "fetch-01", site_lab.FLEET)
        step(f"upgrade.yml {args.upgrade_from} -> {target}", upgraded["result"])
        step("register_robot.yml", chain.register_robot())
        step("deploy.yml with the new robot", chain.deploy(str(folder / "rendered")))
        for host, name in ((site_lab.NEW_ROBOT, site_lab.NEW_ROBOT), (site_removal.inventory_name("edge-d"), "edge-d")):
            step(f"remove_node.yml {host}", site_removal.remove_node(chain, host, name)["result"])
        restored = site_operations.backup_and_restore(chain, f"kuberos-{site_lab.FLEET}", record_name("pick-and-place"))
        step("etcd_restore.yml", restored["restore"] or restored["backup"])
        step("certificates.yml -e renew=true", site_operations.renew_certificates(chain))
        step("undeploy.yml", chain.undeploy())
        lost = chain.lose_vip_holder()
        replaced = site_replace.replace_control_plane(chain, lost, run=lambda: chain.site_with_robots_offline(
            "fetch-02", "fetch-09.robots.example.internal", site_lab.UNUSED_ADDRESS))  # fmt: skip
        step("site.yml with the lost control plane rebuilt and robots off", replaced["result"])
        first = site_removal.inventory_name(site_lab.CONTROL_PLANES[0])
        step("reset.yml", site_removal.reset_site(chain, first, sorted(lab.machines.machines))["result"])
    finally:
        lab.down(remove=True)
    chain.figures["total_s"] = round(time.monotonic() - started, 1)
    figures = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), **chain.figures}
    print(json.dumps(figures, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    os.umask(0o022)
    sys.exit(main())
