"""The site chain's control-plane replacement on the lab site (``tests/site``): a lost control plane rebuilt from a
bare disk and ``site.yml`` run again, with the virtual IP's holders (``VipSampler``, every 0.5 s) and the API through
it (``site_operations.ApiSampler``) sampled throughout; then etcd's members and their health as each control plane's
etcd answers them. Every wait is bounded in time."""

from __future__ import annotations

import threading
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_lab import (
    CONTROL_PLANES,
    SiteChain,
    etcd_gateway,
    etcd_members,
    nodes,
    vip_holders,
    wait_for,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.site_operations import ApiSampler


class Sampler(threading.Thread):
    """Calls ``sample(moment)`` every ``every`` seconds (on a fixed pace: the time a sample takes counts) until
    ``stop`` or for at most ``limit`` seconds."""

    def __init__(self, every: float = 0.5, limit: float = 3600):
        super().__init__(daemon=True)
        self.every, self.limit = every, limit
        self._stopping = threading.Event()

    def sample(self, moment: float) -> None:
        raise NotImplementedError

    def run(self) -> None:
        started = time.monotonic()
        while not self._stopping.is_set() and time.monotonic() - started < self.limit:
            moment = time.monotonic()
            self.sample(moment)
            self._stopping.wait(max(0.0, self.every - (time.monotonic() - moment)))

    def stop(self) -> None:
        self._stopping.set()
        self.join(10)


class VipSampler(Sampler):
    """Asks which control planes hold the virtual IP every ``every`` seconds until ``stop`` (at most ``limit`` s):
    ``holders_max`` and the samples where more than one held it (``two_holders``)."""

    def __init__(self, machines, control_planes=CONTROL_PLANES, every: float = 0.5, limit: float = 3600):
        super().__init__(every, limit)
        self.machines, self.control_planes = machines, list(control_planes)
        self.holders_max, self.samples = 0, 0
        self.two_holders: list[list[str]] = []

    def sample(self, moment: float) -> None:
        try:
            holders = vip_holders(self.machines, [m for m in self.control_planes if self.machines.machines[m].leader])
        except Exception:  # pylint: disable=broad-exception-caught  # a machine booting or going down: not a holder
            holders = []
        self.holders_max = max(self.holders_max, len(holders))
        if len(holders) > 1:
            self.two_holders.append(holders)
        self.samples += 1


def etcd_health(machines, name: str) -> dict:
    """Control plane ``name``'s etcd: its member list (names) and whether it says it is healthy (``/health``)."""
    health = etcd_gateway(machines, name, "/health")
    return {"members": etcd_members(machines, name), "healthy": str(health.get("health")) == "true"}


def replace_control_plane(chain: SiteChain, machine: str, timeout: float = 600, run=None) -> dict:
    """``machine`` (a control plane, powered off) rebuilt from a bare disk, then ``site.yml``. Records
    ``control_plane_replaced_s`` (the run), ``vip_holders_max`` (sampled every 0.5 s from the rebuild to the end of
    the run), ``api_unavailable_during_replace_max_s`` (the longest time the API did not answer through the virtual
    IP) and ``etcd_members_after_replace``; returns the run, each control plane's etcd health and the sampler.
    ``run`` runs site.yml instead of a plain run (the chain's run with robots off, so that one run shows both)."""
    sampler = VipSampler(chain.lab.machines)
    sampler.start()
    try:
        with ApiSampler(chain.kube) as api:
            chain.lab.machines.rebuild(machine, log=chain.log)
            result = run() if run is not None else chain._play("site.yml")
            if result.returncode == 0:
                wait_for(f"{machine} Ready", lambda: nodes(chain.kube).get(machine, {}).get("ready"), timeout)
    finally:
        sampler.stop()
    health = {}
    if result.returncode == 0:
        health = wait_for(
            "every control plane's etcd healthy with three members",
            lambda: (found := {cp: etcd_health(chain.lab.machines, cp) for cp in CONTROL_PLANES})
            and all(h["healthy"] and len(h["members"]) == len(CONTROL_PLANES) for h in found.values())
            and found,
            timeout,
            5,
        )  # fmt: skip
    chain.figures["control_plane_replaced_s"] = round(result.seconds, 1)
    chain.figures["vip_holders_max"] = sampler.holders_max
    chain.figures["api_unavailable_during_replace_max_s"] = round(api.longest_outage(), 1)
    chain.figures["etcd_members_after_replace"] = len(health.get(CONTROL_PLANES[0], {}).get("members", []))
    return {"result": result, "health": health, "sampler": sampler, "api_samples": len(api.samples)}
