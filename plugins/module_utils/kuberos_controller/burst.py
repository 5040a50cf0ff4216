"""Cloud burst: the controller asks for VMs when a fleet lacks room, and for their release after the peak.

The controller writes what each fleet lacks to the ConfigMap ``kuberos-capacity`` of the fleet's namespace
(``kuberos.capacity``). With ``--burst-command`` it also runs the provisioner itself: that command (in the
embedded default ``ansible-playbook playbooks/cloud.yml -e cloud_vms_burst=true ...``, which reads the demand,
sizes the fleet's VMs within the budget, makes new VMs nodes, and drains and releases idle ones; docs/cloud.md)
with ``-e cloud_vms_fleet=<fleet>`` appended, one run at a time, in a thread of its own:

- at once when a fleet's demand appears or changes;
- ``release_after`` seconds after it ends, and again every ``release_after`` seconds while the run reports VMs of
  the fleet (an idle VM is released once the fleet has had no demand for that long).

A run's output goes to the controller's log (the command never gets credentials on its command line: the cloud
collection reads them from the environment). Only the leader writes demand, so only the leader runs the command.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import threading
import time

log = logging.getLogger("kuberos.controller.burst")


class Burst:
    def __init__(self, argv: list[str], release_after_s: float = 300.0, timeout_s: float = 1800.0):
        self.argv = list(argv)
        self.release_after_s = release_after_s
        self.timeout_s = timeout_s
        self.due: dict[str, float] = {}  # fleet -> when to run for it
        self.lock = threading.Lock()
        self.wake = threading.Event()
        self.runs: list[dict] = []  # fleet, started, seconds, exit code, what was launched and released

    def demand_changed(self, fleet: str, demand: dict) -> None:
        delay = 0.0 if int(demand.get("instances") or 0) > 0 else self.release_after_s + 1.0
        with self.lock:
            self.due[fleet] = time.time() + delay
        self.wake.set()

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            with self.lock:
                now = time.time()
                ready = sorted(f for f, at in self.due.items() if at <= now)
                nearest = min(self.due.values(), default=now + 3600)
            if not ready:
                self.wake.wait(max(0.1, min(5.0, nearest - now)))
                self.wake.clear()
                continue
            for fleet in ready:
                with self.lock:
                    self.due.pop(fleet, None)
                outcome = self.provision(fleet)
                if outcome.get("vms"):
                    with self.lock:  # the fleet still has VMs: look again later (release once idle and quiet)
                        self.due.setdefault(fleet, time.time() + self.release_after_s)

    def provision(self, fleet: str) -> dict:
        """One run of the command for ``fleet``; what it launched, released and kept (from Ansible's json callback)."""
        argv = [*self.argv, "-e", f"cloud_vms_fleet={fleet}"]
        env = {**os.environ, "ANSIBLE_STDOUT_CALLBACK": "json", "ANSIBLE_SHOW_CUSTOM_STATS": "true", "ANSIBLE_NOCOLOR": "1"}
        started = time.time()
        log.info("burst: provisioning for fleet %s", fleet)
        try:
            done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=self.timeout_s, check=False)
            output, code = done.stdout, done.returncode
        except (OSError, subprocess.TimeoutExpired) as exc:
            output, code = "", -1
            log.error("burst: the provisioner for fleet %s did not run: %s", fleet, exc)
        stats = {}
        try:
            stats = (json.loads(output[output.index("{") :]).get("global_custom_stats") or {}).get("cloud_vms") or {}
        except ValueError:
            pass
        outcome = {
            "fleet": fleet,
            "started": round(started, 1),
            "seconds": round(time.time() - started, 1),
            "exit": code,
            "launched": list(stats.get("launched") or []),
            "released": list(stats.get("released") or []),
            "kept": list(stats.get("kept") or []),
            "why": stats.get("burst", ""),
        }
        outcome["vms"] = len(outcome["launched"]) + len(outcome["kept"])
        self.runs.append(outcome)
        if code != 0:
            log.error("burst: the provisioner for fleet %s failed (exit %s): %s", fleet, code, _failure(output))
        else:
            log.info(
                "burst: fleet %s: launched %s, released %s, kept %s (%s; %.1f s)", fleet, outcome["launched"] or "none",
                outcome["released"] or "none", outcome["kept"] or "none", outcome["why"] or "-", outcome["seconds"],
            )  # fmt: skip
        return outcome


def _failure(output: str) -> str:
    """The failed tasks' messages of a json-callback run, short."""
    try:
        plays = json.loads(output[output.index("{") :]).get("plays") or []
    except ValueError:
        return output[-500:]
    messages = []
    for play in plays:
        for task in play.get("tasks") or []:
            for result in (task.get("hosts") or {}).values():
                if result.get("failed"):
                    messages.append(f"{task['task'].get('name')}: {str(result.get('msg', ''))[:300]}")
    return "; ".join(messages)[:1000] or output[-500:]
