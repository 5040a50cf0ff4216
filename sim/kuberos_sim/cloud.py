"""Cloud VMs on demand in the simulator: the controller's burst with the provider replaced by the runtime's hosts.

On a site (docs/cloud.md) the controller writes what a fleet lacks (``kuberos.capacity``: instances that may run in
the cloud but found no node), ``playbooks/cloud.yml -e cloud_vms_burst=true`` sizes the fleet's VMs from it with
the pure rules of ``kuberos_cluster.cloud`` (``burst``, then ``plan`` within the budget), launches them through
``amazon.aws.ec2_instance`` and makes each a node; the controller adds that node to the fleet's resource model and
places there, and after the peak the VMs that run nothing are released once the fleet has had no demand for
``release_after`` seconds.

``SimCloud`` takes the same decisions with the same functions. What differs is the provider: a launched VM is a
new host of the runtime (a network namespace with the cloud's latency on the fabric, a cgroup with the instance
type's CPUs scaled as every host's) that becomes a node ``boot_s`` seconds after launch (a stand-in for the
provider starting the VM and ``kubeadm join``: minutes on a real provider); a released VM's host is removed.
Its node model is what the role writes to the inventory for a running VM (``cloud.inventory_hosts``, read back
with ``cloud.cloud_node``). The provider's API itself is not on this path: it cannot exist on this machine, and
tests/cluster/test_burst.py runs the role against moto's EC2 server instead.

Every launch, node, refusal and release is kept in ``log`` (seconds since ``start``), for the run's results.
"""

from __future__ import annotations

import dataclasses
import time

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import cloud

SITE = "sim"
REGION = "eu-central-1"
# The budget of the evaluation's burst run: one instance type with the CPUs of four planners, at most 2 VMs.
BUDGET = {"max_vms": 2, "instance_types": {"c5.2xlarge": {"cpu": 8, "memory": "16Gi", "hourly_price": 0.388}}}
BOOT_S = 10.0
RELEASE_AFTER_S = 20.0


@dataclasses.dataclass
class SimVm:
    vm: cloud.Vm
    launched_at: float  # seconds since start, as every time below
    node_at: float  # when its host is made and it is a node
    running: bool = False
    released_at: float | None = None


class SimCloud:
    """A fleet's VMs at one simulated cloud site; ``reconcile`` once per controller pass with the fleet's demand."""

    def __init__(
        self,
        runtime,
        fleet: str,
        *,
        budget: dict | None = None,
        instance_type: str | None = None,
        latency_ms: float = 50.0,
        boot_s: float = BOOT_S,
        release_after_s: float = RELEASE_AFTER_S,
    ):
        budget = budget or BUDGET
        settings = cloud.load_settings(
            {
                "site": SITE,
                "fleet": fleet,
                "count": 0,
                "instance_type": instance_type or next(iter(budget["instance_types"])),
                "region": REGION,
                "latency_ms": latency_ms,
                "budget": budget,
            }
        )
        self.runtime = runtime
        self.request, self.budget = settings.request, settings.budget
        self.boot_s, self.release_after_s = boot_s, release_after_s
        self.vms: dict[str, SimVm] = {}
        self.log: list[dict] = []
        self._ids = 0
        self.started = time.monotonic()

    def start(self) -> SimCloud:
        self.started = time.monotonic()
        return self

    def _t(self) -> float:
        return round(time.monotonic() - self.started, 2)

    def _note(self, event: str, name: str = "", detail: str = "") -> str:
        self.log.append({"t": self._t(), "event": event, "vm": name, "detail": detail})
        return f"{event}: {name} {detail}".strip()

    def live(self) -> list[SimVm]:
        return [v for v in self.vms.values() if v.released_at is None]

    def running(self) -> list[SimVm]:
        """The live VMs whose boot is over: nodes now."""
        return [v for v in self.live() if v.running]

    def nodes(self) -> list:
        """The resource model's nodes of the VMs that are nodes now (as the inventory would read them)."""
        running = [dataclasses.replace(v.vm, state="running") for v in self.running()]
        hosts = cloud.inventory_hosts(running, self.request.site, self.budget)
        return [cloud.cloud_node(name, variables) for name, variables in hosts.items()]

    def reconcile(self, demand: dict | None, now: float) -> list[str]:
        """One provisioner run for the fleet: VMs whose boot is over become nodes; then the burst rule sizes the fleet
        from ``demand`` (``kuberos.capacity.advance``'s dict) and the plan launches and releases within the budget.
        ``now``: epoch seconds (the demand's stamps are). Returns what it did, one line each."""
        done = []
        for sim in self.live():
            if not sim.running and self._t() >= sim.node_at:
                sim.running = True
                inventory = self.runtime.inventory.with_nodes([n for n in self.nodes() if n.name == sim.vm.name])
                self.runtime.add_host(sim.vm.name, inventory)
                done.append(self._note("node", sim.vm.name, f"ready {self._t() - sim.launched_at:.1f} s after launch"))
        vms = [v.vm for v in self.live()]
        busy = {p.host for p in self.runtime.processes.values() if p.running}
        decision = cloud.burst(demand, vms, busy, self.request, self.budget, now, self.release_after_s)
        request = dataclasses.replace(self.request, count=decision.count, release=decision.release)
        plan = cloud.plan(request, vms, self.budget)
        for launch in plan.launch:
            self._ids += 1
            vm = cloud.Vm(launch.name, f"i-sim{self._ids:05d}", launch.instance_type, SITE, request.fleet, "pending",
                          tags=launch.tags)  # fmt: skip
            self.vms[vm.name] = SimVm(vm, self._t(), self._t() + self.boot_s)
            done.append(self._note("launched", vm.name, f"{launch.instance_type}; {decision.why}"))
        for vm in plan.release:
            sim = self.vms[vm.name]
            if sim.running:
                self.runtime.remove_host(vm.name)
            sim.released_at = self._t()
            done.append(self._note("released", vm.name, decision.why))
        for refusal in plan.refused:
            if not self.log or self.log[-1]["detail"] != refusal.reason:  # said once while it stands
                done.append(self._note("refused", "", refusal.reason))
        return done

    def release_all(self) -> list[str]:
        """At the end of a run: every VM still live is released (and counted as such)."""
        done = []
        for sim in self.live():
            if sim.running:
                self.runtime.remove_host(sim.vm.name)
            sim.released_at = self._t()
            done.append(self._note("released", sim.vm.name, "the run ended"))
        return done

    def summary(self) -> dict:
        """VMs provisioned and released (by the burst rule, not by the run's end), and the log."""
        launched = [e for e in self.log if e["event"] == "launched"]
        released = [e for e in self.log if e["event"] == "released" and e["detail"] != "the run ended"]
        return {
            "vms_provisioned": len(launched),
            "vms_released": len(released),
            "vms_left_at_end": len([e for e in self.log if e["event"] == "released" and e["detail"] == "the run ended"]),
            "instance_type": self.request.instance_type,
            "boot_s": self.boot_s,
            "release_after_s": self.release_after_s,
            "max_vms": self.budget.max_vms,
            "log": list(self.log),
        }
