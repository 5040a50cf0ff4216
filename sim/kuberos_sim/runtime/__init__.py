"""Run a rendered RosDeployment on this machine: hosts in network namespaces, delayed links, CPU classes.

See runtime.py for the whole picture; ``python -m kuberos_sim.runtime --help`` for the command.
"""

from __future__ import annotations

from .delays import LAN_RTT_MS, rtt_ms
from .processes import SimProcess
from .runtime import DEFAULT_CPU_SCALE, Host, ProcessExitedError, RemovedHost, Runtime, environment_problem

__all__ = [
    "DEFAULT_CPU_SCALE",
    "LAN_RTT_MS",
    "Host",
    "ProcessExitedError",
    "RemovedHost",
    "Runtime",
    "SimProcess",
    "environment_problem",
    "rtt_ms",
]
