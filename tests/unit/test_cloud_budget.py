"""Cloud VMs on demand, the pure model: budget, refusals, names, tags, inventory hosts, nodes, bad settings."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.filter.cloud_vm_inventory import cloud_vm_inventory
from ansible_collections.kuberos.platform.plugins.filter.cloud_vm_nodes import cloud_vm_nodes
from ansible_collections.kuberos.platform.plugins.filter.cloud_vm_plan import cloud_vm_plan
from ansible_collections.kuberos.platform.plugins.filter.cloud_vm_settings import cloud_vm_settings
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import cloud

BUDGET = {
    "max_vms": 4,
    "instance_types": {
        "t3.large": {"cpu": 2, "memory": "8Gi", "hourly_price": 0.0832},
        "g4dn.xlarge": {"cpu": 4, "memory": "16Gi", "gpu": 1, "hourly_price": 0.526, "max": 1},
        "m7g.large": {"cpu": "1500m", "memory": "8Gi", "arch": "arm64"},
    },
}
SETTINGS = {
    "site": "site-a",
    "fleet": "picking",
    "count": 2,
    "instance_type": "t3.large",
    "release": [],
    "region": "eu-central-1",
    "latency_ms": "35 ms",
    "resource_group": "",
    "ssh_user": "admin",
    "vpn_network": "",
    "budget": BUDGET,
}


def settings(**changes):
    return cloud.load_settings({**SETTINGS, **changes})


def vm(number, fleet="picking", site="site-a", kind="t3.large", state="running", vpn="", name=None):
    """A VM as plan() sees it, tagged as the role tags it."""
    name = name or cloud.vm_name(site, fleet, number)
    checked = cloud.load_settings({**SETTINGS, "site": site, "fleet": fleet})
    tags = cloud.vm_tags(site, fleet, name, checked.budget.instance_type(kind), vpn)
    return cloud.Vm(
        name, f"i-{site}-{fleet}-{number}", kind, site, fleet, state, f"10.0.0.{number}", "", tuple(sorted(tags.items()))
    )


def instance(vm_: cloud.Vm) -> dict:
    """The same VM as amazon.aws.ec2_instance_info returns it."""
    return {
        "instance_id": vm_.instance_id,
        "instance_type": vm_.instance_type,
        "state": {"code": 16, "name": vm_.state},
        "tags": dict(vm_.tags),
        "private_ip_address": vm_.private_ip,
        "public_ip_address": "203.0.113.9",
    }


def plan_of(existing=(), **changes):
    checked = settings(**changes)
    return cloud.plan(checked.request, list(existing), checked.budget)


# ------------------------------------------------------------------------------------------- the budget is respected
# existing VMs, request changes -> VMs launched, VMs released (by number), refused (count, words in the reason)
PLANS = [
    ("nothing yet: two launched", [], {}, [1, 2], [], None),
    ("as wanted: nothing to do", [vm(1), vm(2)], {}, [], [], None),
    ("one more", [vm(1)], {}, [2], [], None),
    ("fewer: the newest go", [vm(1), vm(2), vm(3)], {"count": 1}, [], [3, 2], None),
    ("zero: all go", [vm(1), vm(2)], {"count": 0}, [], [2, 1], None),
    ("a gap is filled first", [vm(2)], {"count": 3}, [1, 3], [], None),
    ("site limit cuts the request", [vm(1, fleet="other")], {"count": 5}, [1, 2, 3], [],
     (2, "at most 4 VM(s) at site site-a, and 4 run there")),
    ("other sites do not count", [vm(n, site="site-b") for n in range(1, 5)], {}, [1, 2], [], None),
    ("stopped VMs count", [vm(1, fleet="other", state="stopped")] + [vm(n, fleet="x") for n in (1, 2, 3)], {}, [], [],
     (2, "at most 4 VM(s) at site site-a, and 4 run there")),
    ("a type's own max", [], {"instance_type": "g4dn.xlarge"}, [1], [], (1, "at most 1 VM(s) of type g4dn.xlarge, and 1 run")),
    ("price cap", [], {"budget": {**BUDGET, "max_hourly_price": 0.2}, "count": 4}, [1, 2], [],
     (2, "at most 0.2/h at site site-a: 0.1664/h run there and a t3.large costs 0.0832/h")),
    ("released room is used", [vm(n, fleet="other") for n in (1, 2, 3)] + [vm(1)],
     {"release": ["site-a-picking-cloud-1"], "count": 1}, [2], [1], None),
    ("release by name, count keeps", [vm(1), vm(2)], {"release": ["site-a-picking-cloud-1"]}, [3], [1], None),
    ("a budget of none", [], {"budget": {**BUDGET, "max_vms": 0}}, [], [], (2, "at most 0 VM(s)")),
]  # fmt: skip


@pytest.mark.parametrize(("case", "existing", "changes", "launched", "released", "refused"), PLANS, ids=[p[0] for p in PLANS])
def test_plan_launches_and_releases_within_the_budget(case, existing, changes, launched, released, refused):
    result = plan_of(existing, **changes)
    assert [x.name for x in result.launch] == [cloud.vm_name("site-a", "picking", n) for n in launched]
    assert [v.name for v in result.release] == [cloud.vm_name("site-a", "picking", n) for n in released]
    launch_refusals = [r for r in result.refused if r.action == "launch"]
    if refused is None:
        assert launch_refusals == []
    else:
        assert [(r.count, refused[1] in r.reason) for r in launch_refusals] == [(refused[0], True)], launch_refusals
    assert result.changes == bool(launched or released)
    if result.launch:  # what runs at the site afterwards fits every limit of the budget
        budget = settings(**changes).budget
        after = [v.instance_type for v in existing if v.site == "site-a" and v not in result.release]
        after += [x.instance_type for x in result.launch]
        assert len(after) <= budget.max_vms
        for kind in budget.instance_types:
            assert kind.max_vms is None or after.count(kind.name) <= kind.max_vms
        assert budget.max_hourly_price is None or sum(budget.hourly_price(k) for k in after) <= budget.max_hourly_price


def test_a_name_to_release_that_is_not_the_fleets_is_refused_with_its_reason():
    result = plan_of([vm(1), vm(1, fleet="other")], release=["site-a-other-cloud-1", "site-a-picking-cloud-9"])
    assert result.release == ()
    reasons = {r.name: r.reason for r in result.refused if r.action == "release"}
    assert set(reasons) == {"site-a-other-cloud-1", "site-a-picking-cloud-9"}
    assert "not a VM of fleet picking at site site-a (its VMs: site-a-picking-cloud-1)" in reasons["site-a-picking-cloud-9"]
    assert "did you mean 'site-a-picking-cloud-1'" in reasons["site-a-picking-cloud-9"]
    assert [x.name for x in result.launch] == ["site-a-picking-cloud-2"]


def test_a_released_vms_number_is_not_reused_by_the_same_plan():
    result = plan_of([vm(1), vm(2)], release=["site-a-picking-cloud-2"])
    assert [x.name for x in result.launch] == ["site-a-picking-cloud-3"]


def test_vms_not_named_by_kuberos_go_last_and_keep_their_names():
    foreign = vm(0, name="hand-made-vm")
    result = plan_of([foreign, vm(1)], count=1)
    assert [v.name for v in result.release] == ["site-a-picking-cloud-1"]
    assert [v.name for v in result.keep] == ["hand-made-vm"]


def test_summary_says_what_is_launched_released_and_refused():
    text = plan_of([vm(n, fleet="other") for n in (1, 2, 3)], count=3).summary()
    assert text == (
        "site site-a, fleet picking: 3 VM(s) wanted, 0 kept; launch 1 t3.large (site-a-picking-cloud-1); "
        "refused to launch 2 t3.large: the budget allows at most 4 VM(s) at site site-a, and 4 run there"
    )
    assert plan_of([vm(1), vm(2)]).summary().endswith("nothing to launch or release")


# ------------------------------------------------------------------------------------------------- names and tags
def test_vm_names_are_dns_labels_numbered_from_one():
    assert cloud.vm_name("site-a", "picking", 1) == "site-a-picking-cloud-1"
    assert cloud.vm_number(vm(12)) == 12
    assert cloud.vm_number(vm(0, name="site-a-picking-cloud-01")) is None
    assert cloud.vm_number(vm(0, name="site-a-picking-cloud-1x")) is None
    for launch in plan_of(count=4).launch:
        assert len(launch.name) <= 63 and launch.name == launch.name.lower()


def test_tags_name_the_site_fleet_manager_host_and_capacity():
    launch = plan_of().launch[0]
    assert dict(launch.tags) == {
        "Name": "site-a-picking-cloud-1",
        "kuberos.io/managed-by": "kuberos",
        "kuberos.io/site": "site-a",
        "kuberos.io/fleet": "picking",
        "kuberos.io/inventory-host": "site-a-picking-cloud-1",
        "kuberos.io/cpu": "2",
        "kuberos.io/memory": "8Gi",
        "kuberos.io/gpu": "0",
        "kuberos.io/arch": "amd64",
    }


def test_vpn_addresses_are_the_lowest_free_ones_of_the_network_and_run_out_with_a_reason():
    existing = [vm(1, vpn="10.100.0.129"), vm(1, fleet="other", vpn="10.100.0.131")]
    result = plan_of(existing, count=4, vpn_network="10.100.0.128/29", budget={**BUDGET, "max_vms": 10})
    assert [x.vpn_address for x in result.launch] == ["10.100.0.130", "10.100.0.132", "10.100.0.133"]
    assert dict(result.launch[0].tags)["kuberos.io/vpn-address"] == "10.100.0.130"
    small = plan_of(existing, count=3, vpn_network="10.100.0.128/30")
    assert [x.vpn_address for x in small.launch] == ["10.100.0.130"]
    assert [(r.count, r.reason) for r in small.refused] == [(1, "no free address left in the VPN network 10.100.0.128/30")]


def test_instances_of_amazon_aws_become_vms_and_foreign_or_gone_ones_are_left_out():
    mine = instance(vm(1))
    foreign = {**instance(vm(2)), "tags": {"Name": "web-1"}}
    gone = {**instance(vm(3)), "state": {"name": "terminated"}}
    vms = cloud.vms_from_instances([gone, foreign, mine, "junk"])
    assert [(v.name, v.site, v.fleet, v.instance_type, v.public_ip) for v in vms] == [
        ("site-a-picking-cloud-1", "site-a", "picking", "t3.large", "203.0.113.9")
    ]


# ------------------------------------------------------------------------------------------ what a VM becomes
def test_inventory_hosts_carry_the_cloud_node_variables():
    checked = settings(vpn_network="10.100.0.128/25")
    vms = [vm(1, vpn="10.100.0.129"), vm(2, kind="g4dn.xlarge"), vm(3, state="pending"), vm(1, site="site-b")]
    hosts = cloud.inventory_hosts(vms, checked.request.site, checked.budget)
    assert list(hosts) == ["site-a-picking-cloud-1", "site-a-picking-cloud-2"]
    assert hosts["site-a-picking-cloud-1"] == {
        "ansible_host": "10.0.0.1",
        "ansible_user": "admin",
        "kuberos_arch": "amd64",
        "kuberos_cloud_instance_id": "i-site-a-picking-1",
        "kuberos_cloud_instance_type": "t3.large",
        "kuberos_cloud_region": "eu-central-1",
        "kuberos_cpu": 2,
        "kuberos_fleets": ["picking"],
        "kuberos_gpu": 0,
        "kuberos_latency_ms": 35,
        "kuberos_memory": "8Gi",
        "kuberos_resource_group": "cloud-eu-central-1",
        "kuberos_shared": False,
        "kuberos_vpn_address": "10.100.0.129",
    }
    assert hosts["site-a-picking-cloud-2"]["kuberos_gpu"] == 1
    assert "kuberos_vpn_address" not in hosts["site-a-picking-cloud-2"]


def test_capacity_comes_from_the_tags_so_a_budget_edit_does_not_change_running_vms():
    checked = settings()
    other_budget = {"max_vms": 1, "instance_types": {"c7i.large": {"cpu": 2, "memory": "4Gi"}}}
    edited = cloud.load_settings({**SETTINGS, "budget": other_budget, "instance_type": "c7i.large"})
    assert cloud.inventory_hosts([vm(1, kind="m7g.large")], edited.request.site, edited.budget) == cloud.inventory_hosts(
        [vm(1, kind="m7g.large")], checked.request.site, checked.budget
    )
    untagged = cloud.Vm("site-a-picking-cloud-1", "i-1", "x9.huge", "site-a", "picking")
    with pytest.raises(SpecError) as error:
        cloud.inventory_hosts([untagged], checked.request.site, checked.budget)
    assert "cloud_vms: vms.site-a-picking-cloud-1: its capacity is unknown" in str(error.value)
    assert "add the type to cloud_vms_budget.instance_types or release the VM" in str(error.value)


def test_inventory_hosts_load_as_cloud_nodes_of_the_fleet():
    checked = settings()
    hosts = cloud.inventory_hosts([vm(1, kind="m7g.large")], checked.request.site, checked.budget)
    raw = {
        "hosts": {"fetch-1": {"kuberos_fleet": "picking", "kuberos_cpu": 4, "kuberos_memory": "8Gi"}, **hosts},
        "groups": {"robots": ["fetch-1"], "cloud": list(hosts)},
    }
    node = load_inventory(raw).nodes["site-a-picking-cloud-1"]
    assert node == cloud.cloud_node("site-a-picking-cloud-1", hosts["site-a-picking-cloud-1"])
    assert (node.tier, node.cpu_millis, node.arch, node.fleets, node.shared, node.latency_ms) == (
        "cloud", 1500, "arm64", ("picking",), False, 35.0
    )  # fmt: skip


def test_simulated_nodes_are_kwok_cloud_nodes_with_the_types_capacity():
    checked = settings()
    document = cloud.inventory_document(cloud.inventory_hosts([vm(1, kind="g4dn.xlarge")], checked.request.site, checked.budget))
    (node,) = cloud_vm_nodes(document)
    assert node["metadata"]["name"] == "site-a-picking-cloud-1"
    labels = node["metadata"]["labels"]
    assert labels["kuberos.io/role"] == "cloud" and labels["kuberos.io/shared"] == "false"
    assert labels["fleet-access.kuberos.io/picking"] == "true"
    assert labels["resource-group.kuberos.io/name"] == "cloud-eu-central-1"
    assert node["metadata"]["annotations"] == {"kwok.x-k8s.io/node": "fake", "kuberos.io/latency-ms": "35"}
    assert node["status"]["capacity"] == {"cpu": "4", "memory": "16Gi", "pods": "110", "nvidia.com/gpu": "1"}
    assert "spec" not in node  # no robot taint on a cloud node
    assert cloud_vm_nodes({"all": {"children": {"cloud": {"hosts": {}}}}}) == []


def test_the_filters_take_amazon_aws_output_and_role_settings():
    raw = dict(SETTINGS)
    plan = cloud_vm_plan([instance(vm(1))], raw)
    assert [x["name"] for x in plan["launch"]] == ["site-a-picking-cloud-2"]
    assert plan["keep"] == ["site-a-picking-cloud-1"] and plan["changes"] is True
    assert plan["launch"][0]["tags"]["kuberos.io/fleet"] == "picking"
    document = cloud_vm_inventory([instance(vm(1))], raw)
    assert list(document["all"]["children"]["cloud"]["hosts"]) == ["site-a-picking-cloud-1"]
    assert cloud_vm_settings(raw) == raw


# ------------------------------------------------------------------------------------------------ bad settings
# changes -> the problems, each naming the variable, the field and the reason
BAD = [
    ({"site": "Site_A"}, ["cloud_vms_site: 'Site_A' is not valid; expected a name of lowercase letters, digits and '-'"]),
    ({"fleet": ""}, ["cloud_vms: cloud_vms_fleet: '' is not valid; expected a name of lowercase"]),
    ({"fleet": "f" * 50}, ["cloud_vms_fleet: site 'site-a' and fleet 'fff", "make VM names longer than 63 characters"]),
    ({"count": -1}, ["cloud_vms: cloud_vms_count: -1 (int) is not valid; expected a whole number >= 0"]),
    ({"count": "two"}, ["cloud_vms: cloud_vms_count: 'two' is not valid; expected a whole number >= 0"]),
    ({"instance_type": "t3.larg"}, ["cloud_vms: cloud_vms_instance_type: 't3.larg' is not an instance type of cloud_vms_budget",
                                    "did you mean 't3.large'?"]),
    ({"region": "Frankfurt"}, ["cloud_vms: cloud_vms_region: 'Frankfurt' is not valid; expected a region such as eu-central-1"]),
    ({"latency_ms": "fast"}, ["cloud_vms: cloud_vms_latency_ms: 'fast' is not valid; expected a latency"]),
    ({"vpn_network": "10.100.0.1/24"}, ["cloud_vms: cloud_vms_vpn_network: '10.100.0.1/24' is not a network"]),
    ({"vpn_network": "10.100.0.0/31"}, ["cloud_vms_vpn_network: 10.100.0.0/31 has no room for VMs"]),
    ({"release": "site-a-picking-cloud-1"}, ["cloud_vms_release: 'site-a-picking-cloud-1' is not valid; expected a list"]),
    ({"ssh_user": "Admin User"}, ["cloud_vms: cloud_vms_ssh_user: 'Admin User' is not valid"]),
    ({"reigon": "x"}, ["cloud_vms: cloud_vms_reigon: unknown setting; did you mean 'region'?"]),
    ({"budget": None}, ["cloud_vms_budget: None (NoneType) is not valid; expected a mapping with max_vms and instance_types"]),
    ({"budget": {**BUDGET, "max_vms": "lots"}}, ["cloud_vms_budget.max_vms: 'lots' is not valid; expected a whole number"]),
    ({"budget": {**BUDGET, "max_vm": 2}}, ["cloud_vms: cloud_vms_budget.max_vm: unknown field; did you mean 'max_vms'?"]),
    ({"budget": {**BUDGET, "max_hourly_price": -1}}, ["cloud_vms_budget.max_hourly_price: -1 (int) is not valid"]),
    ({"budget": {"max_vms": 1, "instance_types": {}}}, ["cloud_vms_budget.instance_types: {} (dict) is not valid"]),
    ({"budget": {"max_vms": 1, "instance_types": {"t3.large": {"memory": "8Gi"}}}},
     ["cloud_vms: cloud_vms_budget.instance_types['t3.large'].cpu: is required; expected a CPU quantity"]),
    ({"budget": {"max_vms": 1, "instance_types": {"t3.large": {"cpu": 2, "memory": "lots"}}}},
     ["cloud_vms_budget.instance_types['t3.large'].memory: 'lots' is not valid; expected a memory quantity"]),
    ({"budget": {"max_vms": 1, "instance_types": {"t3.large": {"cpu": 2, "memory": "8Gi", "gpus": 1}}}},
     ["cloud_vms_budget.instance_types['t3.large'].gpus: unknown field; did you mean 'gpu'?"]),
    ({"budget": {"max_vms": 1, "instance_types": {"T3 Large": {"cpu": 2, "memory": "8Gi"}}}, "instance_type": "T3 Large"},
     ["cloud_vms_budget.instance_types['T3 Large']: is not an instance type name; expected e.g. t3.large"]),
    ({"budget": {"max_vms": 1, "instance_types": {"t3.large": {"cpu": 0, "memory": "8Gi", "hourly_price": "cheap"}}}},
     ["cloud_vms_budget.instance_types['t3.large'].cpu: must be more than zero",
      "cloud_vms_budget.instance_types['t3.large'].hourly_price: 'cheap' is not valid; expected a price per hour"]),
]  # fmt: skip


@pytest.mark.parametrize(("changes", "expected"), BAD, ids=[str(sorted(c))[:40] for c, _ in BAD])
def test_bad_settings_name_the_variable_the_field_and_the_reason(changes, expected):
    with pytest.raises(SpecError) as error:
        settings(**changes)
    text = str(error.value)
    assert text.startswith("the cloud VM settings are not valid (")
    for part in expected:
        assert part in text, text


def test_every_problem_is_reported_at_once_and_the_filter_says_the_same():
    bad = {**SETTINGS, "site": "", "count": -2, "region": ""}
    with pytest.raises(SpecError) as error:
        cloud.load_settings(bad)
    assert len(error.value.problems) == 3
    with pytest.raises(AnsibleFilterError) as filtered:
        cloud_vm_settings(bad)
    assert str(filtered.value) == str(error.value)


def test_counts_given_as_text_on_the_command_line_are_taken():
    assert settings(count="3").request.count == 3
    assert settings(budget={**BUDGET, "max_vms": "2"}).budget.max_vms == 2


# -- burst: the VM count from the controller's demand -------------------------------------------------------------
def _burst(demand, vms=(), busy=(), now=1000.0, release_after=60.0):
    checked = settings()
    return cloud.burst(demand, list(vms), set(busy), checked.request, checked.budget, now, release_after)


def test_a_demand_asks_for_the_vms_that_hold_it_less_those_still_joining():
    demand = {"instances": 2, "cpu_millis": 3000, "memory_bytes": 2 * 1024**3, "gpu": 0, "modules": ["app/planner"]}
    first = _burst(demand)
    assert (first.count, first.release) == (2, ())  # 3 cores on 2-core t3.large VMs
    assert "app/planner" in first.why
    joining = _burst(demand, vms=[vm(1)], busy=())
    assert joining.count == 2 and "1 joining or not yet used" in joining.why  # one is there, idle: one more
    used = _burst(demand, vms=[vm(1)], busy={vm(1).name})
    assert used.count == 3  # the VM runs something already: two more
    gpu = _burst({**demand, "gpu": 1})
    assert gpu.count == 10**6, "t3.large has no GPU: asks for more than any budget, and the plan refuses it"


def test_without_demand_idle_vms_go_only_after_the_quiet_period():
    quiet = {"instances": 0, "quiet_since": "1970-01-01T00:15:40Z"}  # 940 s after the epoch
    vms = [vm(1), vm(2)]
    early = _burst(quiet, vms=vms, busy={vm(1).name}, now=990.0)
    assert (early.count, early.release) == (2, ()) and "50 of 60 s" in early.why
    late = _burst(quiet, vms=vms, busy={vm(1).name}, now=1001.0)
    assert (late.count, late.release) == (1, (vm(2).name,))
    busy = _burst(quiet, vms=vms, busy={vm(1).name, vm(2).name}, now=5000.0)
    assert busy.release == () and busy.count == 2
    assert _burst(None, vms=vms).release == (), "no demand ConfigMap yet: nothing is released"
    other_fleet = _burst(quiet, vms=[vm(3, fleet="other")], now=5000.0)
    assert (other_fleet.count, other_fleet.release) == (0, ())


def test_the_burst_filter_reads_the_configmap_and_the_pods():
    from ansible_collections.kuberos.platform.plugins.filter.cloud_vm_burst import cloud_vm_burst

    demand = '{"instances": 1, "cpu_millis": 500, "memory_bytes": 1, "gpu": 0, "modules": ["a/b"]}'
    result = cloud_vm_burst(
        [instance(vm(1))], SETTINGS, [{"data": {"demand.json": demand}}], [{"spec": {"nodeName": vm(1).name}}], 60, 0
    )
    assert result == {"count": 2, "release": [], "why": "1 instance(s) of a/b lack room; 1 more VM(s) of t3.large"}
