"""Long-running processes with a pid file and a log: start detached, find again, stop.

A pid file alone is not trusted: the process must still exist, not be a zombie, and its command
line must contain ``marker`` (a pid can be reused by an unrelated process).
"""

from __future__ import annotations

import os
import signal
import subprocess
import time


def run_checked(command, error: type[Exception], check: bool = True, timeout: float = 30) -> subprocess.CompletedProcess:
    """Run a short command; ``error`` with the command and its output when it cannot run or, if ``check``, fails."""
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    except (OSError, subprocess.TimeoutExpired) as failure:
        raise error(f"{' '.join(command)}: {failure}") from failure
    if check and done.returncode != 0:
        raise error(f"{' '.join(command)} exited {done.returncode}: {(done.stderr or done.stdout).strip()}")
    return done


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        with open(f"/proc/{pid}/stat", encoding="utf-8") as handle:
            return handle.read().split(") ")[-1][:1] != "Z"
    except OSError:
        return False


def cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as handle:
            return [part.decode(errors="replace") for part in handle.read().split(b"\0") if part]
    except OSError:
        return []


def running_pid(pidfile: str, marker) -> int | None:
    """The pid in ``pidfile`` if that process runs and ``marker(argv)`` accepts its command line."""
    try:
        with open(pidfile, encoding="utf-8") as handle:
            pid = int(handle.read().strip())
    except (OSError, ValueError):
        return None
    return pid if alive(pid) and marker(cmdline(pid)) else None


def start(command: list[str], pidfile: str, logfile: str, env: dict | None = None) -> subprocess.Popen:
    """Start ``command`` in its own session, output appended to ``logfile``, pid written to ``pidfile``."""
    for path in (pidfile, logfile):
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(logfile, "ab") as log:
        process = subprocess.Popen(
            command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True, close_fds=True, env=env,
        )  # fmt: skip
    with open(pidfile, "w", encoding="utf-8") as handle:
        handle.write(f"{process.pid}\n")
    # Until the child has exec'd, its command line is ours and running_pid() would not recognise it.
    ours = cmdline(os.getpid())
    deadline = time.monotonic() + 5.0
    while process.poll() is None and cmdline(process.pid) == ours and time.monotonic() < deadline:
        time.sleep(0.005)
    return process


def stop(pidfile: str, marker, timeout: float = 15.0) -> int | None:
    """SIGTERM, then SIGKILL after ``timeout``; removes the pid file. Returns the pid stopped, or None."""
    pid = running_pid(pidfile, marker)
    if pid is not None:
        os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and alive(pid):
            time.sleep(0.1)
        if alive(pid):
            os.kill(pid, signal.SIGKILL)
    try:
        os.remove(pidfile)
    except FileNotFoundError:
        pass
    return pid


def tail(path: str, lines: int = 15) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as handle:
            return "".join(handle.readlines()[-lines:])
    except OSError:
        return ""


CGROUP_ROOT = "/sys/fs/cgroup"


def cgroup_hierarchies() -> list[str]:
    """The mounted cgroup v1 hierarchies (cpu, memory, ..., the named systemd one): where the lab's machines and real
    nodes make their cgroups."""
    try:
        with open("/proc/self/mounts", encoding="utf-8") as handle:
            mounts = handle.read()
    except OSError:
        return []
    found = []
    for line in mounts.splitlines():
        parts = line.split()
        if len(parts) > 2 and parts[2] == "cgroup" and parts[1].startswith(CGROUP_ROOT + "/"):
            found.append(parts[1])
    return sorted(set(found))
