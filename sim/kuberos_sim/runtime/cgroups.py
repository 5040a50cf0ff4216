"""CPU classes: a cgroup v1 group per host in the cpu and cpuacct hierarchies.

A host's ``node`` group has ``cpu.cfs_quota_us`` = its CPUs in the inventory x ``cpu_scale`` (capped at this
machine's cores): the robot computer, edge server or cloud VM it stands for. Its ``hardware`` group (for
the physics simulator of a robot) has no quota and is accounted apart. Processes join a group by writing
their pid to ``cgroup.procs`` before they exec (see processes.py). Usage is ``cpuacct.usage`` (nanoseconds).

Weights (``cpu.shares``): a quota caps a group, but when the machine is short of CPU the kernel divides it
among the busy groups by weight, and every group's default weight is the same (1024). An edge server of 18
processes then got no more CPU than one robot's physics process: with 8 robots the two edge servers got 0.26
core together while the physics took 0.8, and their planners took about a minute to start their worker
processes (59-69 s, against 3 s with 2 robots). So a ``node`` group weighs in proportion to its quota
(``shares_for``: 2048 per core, at least the kernel's default 1024, which is a robot computer's half core):
an edge server or cloud VM of 2 cores weighs 4096, as much as four robot computers. A ``hardware`` group
keeps the default 1024 (``HARDWARE_SHARES``), as much as its robot's computer: it needs about 0.15 core, so
it keeps up unless the machine is far over its capacity.
"""

from __future__ import annotations

import os
import signal
import time

CPU_ROOT = "/sys/fs/cgroup/cpu"
CPUACCT_ROOT = "/sys/fs/cgroup/cpuacct"
PERIOD_US = 100_000
MIN_QUOTA_US = 1_000  # the kernel's smallest quota
DEFAULT_SHARES = 1024  # the kernel's default weight
SHARES_PER_CORE = 2048  # a robot computer's half core weighs the default
HARDWARE_SHARES = DEFAULT_SHARES
REMOVE_TRIES = 50  # rmdir attempts, 0.1 s apart, while killed tasks leave


def cgroup_problem() -> str | None:
    """Why cpu/cpuacct cgroups cannot be made here (None if they can)."""
    for root, probe in ((CPU_ROOT, "cpu.cfs_quota_us"), (CPUACCT_ROOT, "cpuacct.usage")):
        if not os.path.exists(os.path.join(root, probe)):
            return f"{root} is not a cgroup v1 hierarchy with {probe}"
        if not os.access(root, os.W_OK):
            return f"{root} is not writable (root needed)"
    return None


def machine_cores() -> int:
    return len(os.sched_getaffinity(0)) or os.cpu_count() or 1


def quota_cores(cpu_millis: int, cpu_scale: float, cores: int | None = None) -> float:
    """The cores a host of ``cpu_millis`` gets here: scaled, capped at this machine's cores."""
    return min(cpu_millis / 1000.0 * cpu_scale, float(cores or machine_cores()))


def shares_for(cores: float) -> int:
    """The weight (cpu.shares) of a group with a quota of ``cores``: in proportion to it, at least the default."""
    return max(DEFAULT_SHARES, round(cores * SHARES_PER_CORE))


def _write(path: str, value: str) -> None:
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(value)


class Cgroup:
    """One group, ``<parent>/<name>``, in both hierarchies (one directory when they are mounted together)."""

    def __init__(self, path: str, cores: float | None, shares: int | None = None):
        self.path = path  # relative to the hierarchies' roots
        self.cores = cores  # None: no quota
        self.shares = shares  # None: the kernel's default weight
        self.dirs = list(dict.fromkeys(os.path.realpath(os.path.join(r, path)) for r in (CPU_ROOT, CPUACCT_ROOT)))
        self.cpu_dir = os.path.join(CPU_ROOT, path)
        self.acct_dir = os.path.join(CPUACCT_ROOT, path)
        self.created: list[str] = []

    @property
    def procs_files(self) -> list[str]:
        """The cgroup.procs files a process writes its pid to, to join."""
        return [os.path.join(d, "cgroup.procs") for d in self.dirs]

    def create(self) -> None:
        for directory in self.dirs:
            os.makedirs(directory, exist_ok=True)
            self.created.append(directory)
        if self.cores is not None:
            _write(os.path.join(self.cpu_dir, "cpu.cfs_period_us"), str(PERIOD_US))
            _write(os.path.join(self.cpu_dir, "cpu.cfs_quota_us"), str(max(MIN_QUOTA_US, round(self.cores * PERIOD_US))))
        if self.shares is not None:
            _write(os.path.join(self.cpu_dir, "cpu.shares"), str(self.shares))

    def usage_seconds(self) -> float:
        try:
            with open(os.path.join(self.acct_dir, "cpuacct.usage"), encoding="utf-8") as handle:
                return int(handle.read().strip()) / 1e9
        except (OSError, ValueError):
            return 0.0

    def pids(self) -> set[int]:
        found: set[int] = set()
        for directory in self.created:
            try:
                with open(os.path.join(directory, "cgroup.procs"), encoding="utf-8") as handle:
                    found.update(int(line) for line in handle if line.strip())
            except OSError:
                pass
        return found

    def remove(self) -> list[str]:
        """Kill what is left in the group, then remove it; problems as text (empty when all went)."""
        problems = []
        for pid in self.pids():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        for directory in reversed(self.created):
            for _ in range(REMOVE_TRIES):
                try:
                    os.rmdir(directory)
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    time.sleep(0.1)
            else:
                problems.append(f"cgroup {directory} could not be removed (tasks: {sorted(self.pids())})")
        self.created = [d for d in self.created if os.path.isdir(d)]
        return problems


def remove_parent(path: str) -> list[str]:
    """Remove the run's parent group from both hierarchies (its children first, by the caller)."""
    problems = []
    for root in dict.fromkeys(os.path.realpath(r) for r in (CPU_ROOT, CPUACCT_ROOT)):
        directory = os.path.join(root, path)
        try:
            os.rmdir(directory)
        except FileNotFoundError:
            pass
        except OSError as error:
            problems.append(f"cgroup {directory} could not be removed: {error}")
    return problems
