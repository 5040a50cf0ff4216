#!/usr/bin/env python3
"""The layout's cost, before and after, side by side in one run: a render-only deploy of N robots (default 1,000).

Two checkouts run the same command on the same inputs, in turn, ``--repeat`` times each (the order alternates, so
that neither always runs first): ``before`` is a git worktree of ``--base`` (default: the commit before the layout
work), ``after`` this checkout. The command is the user's:

    ansible-playbook playbooks/deploy.yml -i <inventory of N robots> -e rosdeployment_file=<spec>
        -e kuberos_apply=false -e kuberos_render_dir=<empty dir>

with the deploy benchmark's inventory and spec (``bench_deploy.write_inventory``, ``write_spec``: four dedicated
modules per robot, 20 edge and 10 cloud nodes). Wall time from start to exit; peak RSS is ``ru_maxrss`` from
``os.wait4`` (the largest of the process and the children it waited for: Ansible's forked workers, where the
module runs). The rendered directories of both must hold the same manifests (compared file by file).

Output: Markdown on stdout and ``bench/results/layout.json`` (``--results``): every run, the medians, and the
ratios after/before (below 1: after is faster or smaller). The worktree is removed at the end.

    .venv/bin/python bench/bench_layout.py                     # 1,000 robots, 3 repeats each
    .venv/bin/python bench/bench_layout.py --robots 50 --repeat 1
"""

from __future__ import annotations

import argparse
import filecmp
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_deploy import machine, parse_profile, write_inventory, write_spec  # bench/ is on sys.path when a benchmark runs

REPO = Path(__file__).resolve().parent.parent
BASE = "c7a050c"  # main before the rooms, the one Kubernetes access layer and the one deploy pass


def peak_rss_of(command: list[str], cwd: Path, env: dict, timeout: float) -> tuple[int, float, float, str]:
    """Run ``command``; (exit status, wall seconds, peak RSS MiB of it and its waited-for children, output tail)."""
    start = time.perf_counter()
    child = subprocess.Popen(command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    deadline = start + timeout
    chunks = []
    while True:
        pid, status, usage = os.wait4(child.pid, os.WNOHANG)
        if pid:
            break
        if time.perf_counter() > deadline:
            child.kill()
        chunks.append(child.stdout.read1(65536) if child.stdout else b"")
    rest = child.stdout.read() if child.stdout else b""
    output = b"".join(chunks) + rest
    return os.waitstatus_to_exitcode(status), time.perf_counter() - start, usage.ru_maxrss / 1024, output.decode(errors="replace")


MODULE_TASK = "rosdeployment"  # the profile line of the task that runs the module (its name differs by revision)


def run_one(checkout: Path, inventory: Path, spec: Path, dest: Path, timeout: float) -> dict:
    env = {**os.environ, "ANSIBLE_CONFIG": str(checkout / "ansible.cfg"), "ANSIBLE_NOCOLOR": "1",
           "ANSIBLE_CALLBACKS_ENABLED": "ansible.posix.profile_tasks", "PROFILE_TASKS_SORT_ORDER": "none",
           "PROFILE_TASKS_TASK_OUTPUT_LIMIT": "all"}  # fmt: skip
    command = [
        str(REPO / ".venv" / "bin" / "ansible-playbook"), "playbooks/deploy.yml", "-i", str(inventory),
        "-e", f"rosdeployment_file={spec}", "-e", "kuberos_apply=false", "-e", f"kuberos_render_dir={dest}",
    ]  # fmt: skip
    code, wall, rss, output = peak_rss_of(command, checkout, env, timeout)
    # the module's task: "Validate, place, render, dry-run, apply, prune and wait" (its role's prefix included)
    task = [s for name, s in parse_profile(output) if name.endswith("dry-run, apply, prune and wait")]
    return {"wall_s": round(wall, 2), "module_task_s": task[0] if task else None, "peak_rss_mib": round(rss, 1), "exit": code,
            "tail": output[-1500:] if code else ""}  # fmt: skip


def same_manifests(one: Path, other: Path) -> list[str]:
    """The files under manifests/ that differ between two render directories (or exist in only one)."""
    differ = []
    for folder, _dirs, files in os.walk(one / "manifests"):
        for name in files:
            path = Path(folder) / name
            twin = other / path.relative_to(one)
            if not twin.exists() or not filecmp.cmp(path, twin, shallow=False):
                differ.append(str(path.relative_to(one)))
    for folder, _dirs, files in os.walk(other / "manifests"):
        for name in files:
            if not (one / (Path(folder) / name).relative_to(other)).exists():
                differ.append(str((Path(folder) / name).relative_to(other)))
    return sorted(set(differ))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=1000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--base", default=BASE, help="the revision measured as before [%(default)s]")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per render [%(default)s]")
    parser.add_argument("--results", default=str(REPO / "bench" / "results" / "layout.json"))
    args = parser.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="kuberos-bench-layout-"))
    before = work / "before"
    try:
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-f", str(before), args.base], check=True,
                       capture_output=True)  # fmt: skip
        inventory = write_inventory(work / "inventory", args.robots)
        spec = write_spec(work / "spec.json")
        runs: dict[str, list[dict]] = {"before": [], "after": []}
        started = machine()
        for index in range(args.repeat):
            order = ("before", "after") if index % 2 == 0 else ("after", "before")
            for which in order:
                checkout = before if which == "before" else REPO
                dest = work / f"render-{which}-{index}"
                run = run_one(checkout, inventory, spec, dest, args.timeout)
                run["dest"] = str(dest)
                runs[which].append(run)
                print(f"{which} #{index + 1}: {run['wall_s']} s (module task {run['module_task_s']} s), "
                      f"{run['peak_rss_mib']} MiB, exit {run['exit']}", file=sys.stderr)  # fmt: skip
                if run["exit"]:
                    print(run["tail"], file=sys.stderr)
                    return 1
        differ = same_manifests(Path(runs["before"][0]["dest"]), Path(runs["after"][0]["dest"]))
        summary = {}
        for which, measured in runs.items():
            for key in ("wall_s", "module_task_s", "peak_rss_mib"):
                summary[f"{which}_{key}_median"] = statistics.median(r[key] for r in measured)
        summary["wall_ratio_after_before"] = round(summary["after_wall_s_median"] / summary["before_wall_s_median"], 3)
        summary["module_task_ratio_after_before"] = round(
            summary["after_module_task_s_median"] / summary["before_module_task_s_median"], 3
        )
        # each repeat's two runs ran next to each other: the median of their ratios is the least noisy comparison
        pairs = [a["module_task_s"] / b["module_task_s"] for a, b in zip(runs["after"], runs["before"], strict=True)]
        summary["module_task_pair_ratio_median"] = round(statistics.median(pairs), 3)
        summary["rss_ratio_after_before"] = round(summary["after_peak_rss_mib_median"] / summary["before_peak_rss_mib_median"], 3)
        data = {
            "machine": started,
            "load_after": machine()["load"],
            "command": "bench/bench_layout.py " + " ".join(argv if argv is not None else sys.argv[1:]),
            "robots": args.robots,
            "repeat": args.repeat,
            "base": subprocess.run(
                ["git", "-C", str(REPO), "rev-parse", "--short", args.base], capture_output=True, text=True
            ).stdout.strip(),
            "manifests_differ": differ,
            **summary,
            "runs": {w: [{k: v for k, v in r.items() if k not in ("tail", "dest")} for r in rs] for w, rs in runs.items()},
        }
        Path(args.results).write_text(json.dumps(data, indent=1) + "\n")
        print(f"# Layout before ({data['base']}) and after ({started['commit']}), render-only deploy of {args.robots} robots\n")
        print("| | before | after | after/before |\n|---|---|---|---|")
        print(f"| wall s (median of {args.repeat}) | {summary['before_wall_s_median']} | {summary['after_wall_s_median']} | "
              f"{summary['wall_ratio_after_before']} |")  # fmt: skip
        print(f"| the module's task s (median) | {summary['before_module_task_s_median']} | "
              f"{summary['after_module_task_s_median']} | {summary['module_task_ratio_after_before']} |")  # fmt: skip
        print(f"| the module's task, after/before per repeat (median) | | | {summary['module_task_pair_ratio_median']} |")
        print(f"| peak RSS MiB (median) | {summary['before_peak_rss_mib_median']} | {summary['after_peak_rss_mib_median']} | "
              f"{summary['rss_ratio_after_before']} |")  # fmt: skip
        print(f"\nmanifests that differ: {len(differ)} {differ[:5]}")
        return 0
    finally:
        subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(before)], capture_output=True)
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
