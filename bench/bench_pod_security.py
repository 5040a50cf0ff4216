#!/usr/bin/env python3
"""Pod Security admission counts: how many of the pods the collection renders the API server admits at each level.

Every example is rendered as deploy renders it on the embedded site (tests/admission.py: every RosDeployment example,
the batch jobs, the controller), plus the modules that ask for more (``user: 0``, ``privileged: true``). Each pod is
dry-run created, as a Pod, in three namespaces of a real kube-apiserver (the local control plane on ports of its own,
started and removed here), each enforcing one level of the Pod Security Standards. The figure is admitted / rendered
per level, per example; the collection's own reading of each pod's level is printed beside it.

    .venv/bin/python bench/bench_pod_security.py                 # results/pod_security.json
    .venv/bin/python bench/bench_pod_security.py --json /tmp/pss.json

The result is printed as Markdown, ready to paste into bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [os.path.join(ROOT, "tests"), os.path.join(ROOT, ".collections")]

from admission import DECLARED, admitted_counts, example_pods, level_namespaces, opt_out_pods, verdicts  # noqa: E402
from helpers import Cluster, free_ports  # noqa: E402

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pod_security  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", default=os.path.join(ROOT, "bench", "results", "pod_security.json"))
    args = parser.parse_args()
    found = example_pods()
    groups = {**found, "modules that ask for more (user: 0, privileged: true)": opt_out_pods()}
    with tempfile.TemporaryDirectory(prefix="kuberos-pss-") as state:
        first = free_ports(6)
        names = ("apiserver", "etcd_client", "etcd_peer", "controller_manager", "scheduler", "kwok")
        cluster = Cluster(state, ports={name: first + offset for offset, name in enumerate(names)})
        started = cluster.start()
        if started.returncode != 0:
            print(started.stdout[-4000:], started.stderr[-2000:], file=sys.stderr)
            return 1
        try:
            core, _apps, _discovery = cluster.clients()
            namespaces = level_namespaces(core)
            rows, undeclared = [], 0
            for group, pods in groups.items():
                said = verdicts(core, pods, namespaces)
                if group in found:
                    undeclared += sum(1 for name, _ in pods if said[(name, "restricted")] and (group, name) not in DECLARED)
                counts = admitted_counts(pods, said)
                ours = {
                    level: sum(1 for _n, spec in pods if pod_security.level(spec)[0] == level) for level in pod_security.LEVELS
                }
                rows.append({"example": group, "pods": len(pods), "admitted": counts, "collection_reads": ours})
        finally:
            cluster.stop(state="absent")
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    result = {
        "date": datetime.date.today().isoformat(),
        "commit": commit,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "command": "bench/bench_pod_security.py",
        "rows": rows,
        # pods of the examples refused under restricted that no example declares (admission.DECLARED): 0 is the target
        "undeclared_refused_under_restricted": undeclared,
    }
    os.makedirs(os.path.dirname(args.json), exist_ok=True)
    with open(args.json, "w", encoding="utf-8") as handle:
        json.dump(result, handle, indent=2)
        handle.write("\n")
    print("| rendered from | pods | admitted: restricted | baseline | privileged | the collection reads |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        reads = ", ".join(f"{n} {level}" for level, n in r["collection_reads"].items() if n)
        a = r["admitted"]
        print(f"| {r['example']} | {r['pods']} | {a['restricted']} | {a['baseline']} | {a['privileged']} | {reads} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
