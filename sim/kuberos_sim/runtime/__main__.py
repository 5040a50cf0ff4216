"""Run a rendered directory on this machine until Ctrl-C.

    PYTHONPATH=sim .venv/bin/python -m kuberos_sim.runtime --rendered rendered/pick-and-place -i inventories/local

Prints the hosts (node, tier, address, CPU quota, processes), reports processes that exit, and on Ctrl-C (or
after --duration seconds) stops everything, removes the namespaces and cgroups, and prints the CPU seconds
per host and the fabric's figures. Bad input is reported as file, field and reason (exit 2), never a traceback.
"""

from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time

from ._core import SpecError
from .runtime import DEFAULT_CPU_SCALE, ProcessExitedError, Runtime


def load_inventory_file(path: str):
    """An Ansible inventory (file or directory) as the resource model, read as the collection reads it."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.ansible_inventory import read_inventory

    return load_inventory(read_inventory(path), source=path)


def host_table(runtime: Runtime) -> str:
    rows = [("NODE", "TIER", "ADDRESS", "CPU QUOTA", "PROCESSES")]
    for node, host in runtime.hosts.items():
        names = [p.name for p in runtime.processes.values() if p.host == node]
        rows.append((node, host.tier, host.address, f"{host.cpu_cores:.3g} cores", ", ".join(names) or "-"))
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(row[:4], widths, strict=True)) + "  " + row[4] for row in rows)


def summary(runtime: Runtime) -> str:
    lines = ["CPU seconds (node cgroup / hardware cgroup):"]
    used = runtime.cpu_seconds()
    for node in runtime.hosts:
        lines.append(f"  {node:<12} {used[(node, 'node')]:8.2f} / {used[(node, 'hardware')]:8.2f}")
    stats = runtime.fabric_stats()
    if stats:
        lines.append(
            f"fabric: {stats['packets']} packets, {stats['bytes'] / 1e6:.1f} MB forwarded, {stats['dropped']} dropped "
            f"({', '.join(f'{k} {v}' for k, v in stats['drops'].items() if v) or 'none'}) in {stats['seconds']:.0f} s"
        )
    lines.extend(runtime.close_problems)
    return "\n".join(lines)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m kuberos_sim.runtime", description=__doc__.split("\n\n")[0])
    parser.add_argument("--rendered", required=True, help="a rendered directory (manifests/, placement.json)")
    parser.add_argument("-i", "--inventory", required=True, help="the Ansible inventory the deployment was placed on")
    parser.add_argument("--run-dir", help="logs, volumes and fabric statistics (default: a new temporary directory)")
    parser.add_argument("--cpu-scale", type=float, default=DEFAULT_CPU_SCALE, help="cores here per inventory CPU")
    parser.add_argument("--host", action="append", default=[], help="simulate this inventory node too (repeatable)")
    parser.add_argument("--no-modules", action="store_true", help="start hosts, fabric and discovery servers only")
    parser.add_argument("--keep-going", action="store_true", help="keep running when processes exit right after start")
    parser.add_argument("--duration", type=float, help="stop after this many seconds instead of waiting for Ctrl-C")
    return parser.parse_args(argv)


def _watch(runtime: Runtime, duration: float | None) -> None:
    reported: set[str] = set()
    deadline = time.monotonic() + duration if duration is not None else None
    while deadline is None or time.monotonic() < deadline:
        for process in runtime.exited():
            if process.name not in reported:
                reported.add(process.name)
                print(process.tail(), flush=True)
        time.sleep(0.5)


def _interrupt(_signum, _frame) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    # Ctrl-C and SIGTERM end the run through the same teardown (SIGINT also when started in the background,
    # where the shell leaves it ignored).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        inventory = load_inventory_file(args.inventory)
        run_dir = args.run_dir or tempfile.mkdtemp(prefix="kuberos-sim-")
        runtime = Runtime(args.rendered, inventory, run_dir, args.cpu_scale, extra_hosts=tuple(args.host))
    except (SpecError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    try:
        with runtime:
            runtime.start(modules=not args.no_modules, strict=not args.keep_going)
            print(host_table(runtime))
            print(f"run directory: {run_dir}; Ctrl-C stops", flush=True)
            _watch(runtime, args.duration)
    except KeyboardInterrupt:
        print("stopping", file=sys.stderr)
    except (ProcessExitedError, RuntimeError) as error:
        print(f"error: {error}", file=sys.stderr)
        print(summary(runtime))
        return 1
    print(summary(runtime))
    return 0


if __name__ == "__main__":
    sys.exit(main())
