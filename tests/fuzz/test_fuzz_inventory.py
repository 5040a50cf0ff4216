"""Fuzzing the inventory (``load_inventory``, what the ``fleet_inventory`` filter hands every module): the local
inventory with a third-party cluster, one place made hostile (a host variable, a group, the tiers' default latency,
the whole). Each case gives an inventory, or one ``SpecError`` whose every problem names the inventory and where in
it: the host and its variable, the group, or the setting."""

from __future__ import annotations

import copy
import functools

from fuzz_bounds import fuzz_settings, run_case
from fuzz_values import hostile_value
from helpers import inventory_raw
from hypothesis import given
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import HOST_VARS, load_inventory

SOURCE = "inventory"
PARTNER = {
    "kuberos_bridge_endpoint": "bridge.example.com",
    "kuberos_bridge_node_port": 31000,
    "kuberos_fleets": ["test-fleet"],
    "kuberos_latency_ms": 20,
}


@functools.cache
def base() -> dict:
    raw = copy.deepcopy(inventory_raw())
    raw["hosts"]["partner"] = dict(PARTNER)
    raw["groups"]["clusters"] = ["partner"]
    raw.setdefault("default_latency_ms", {"edge": 5, "cloud": 40})
    return raw


GROUPS = ["robots", "edge", "cloud", "clusters", "ungrouped"]


@st.composite
def inventories(draw) -> dict:
    raw = copy.deepcopy(base())
    hosts = sorted(raw["hosts"])
    robots = list(raw["groups"]["robots"])
    places = ["host", "host", "host", "group", "member", "default", "link", "device"]
    chosen = sorted(draw(st.lists(st.sampled_from(places), min_size=1, max_size=3)), key=places.index)
    if draw(st.integers(0, 9)) == 0:
        chosen.append("top")  # last: the others need hosts, groups and defaults to be mappings
    for where in chosen:
        value = draw(hostile_value)
        if where == "member" and not isinstance(raw["groups"], dict):
            continue
        if where == "host":
            host = draw(st.sampled_from(hosts))
            var = draw(st.one_of(st.sampled_from(HOST_VARS), st.text(max_size=10)))
            raw["hosts"][host][var] = value
        elif where == "group":
            raw["groups"][draw(st.sampled_from(GROUPS))] = value
        elif where == "member":
            group = draw(st.sampled_from(GROUPS[:4]))
            members = raw["groups"].get(group)
            raw["groups"][group] = [*(members if isinstance(members, list) else []), value]
        elif where == "default":
            raw["default_latency_ms"][draw(st.sampled_from(["edge", "cloud", "onboard", "fog"]))] = value
        elif where == "link":
            robot = draw(st.sampled_from(robots))
            key = draw(st.one_of(st.sampled_from(hosts), st.text(max_size=10)))
            raw["hosts"][robot]["kuberos_link_latency_ms"] = {key: value}
        elif where == "device":
            robot = draw(st.sampled_from(robots))
            device = draw(st.sampled_from(["camera", "gripper", "lidar", "x\n"]))
            raw["hosts"][robot]["kuberos_device_parameters"] = {device: value}
        else:
            raw[draw(st.sampled_from(["hosts", "groups", "default_latency_ms"]))] = value
    return raw


def inventory_located(error: SpecError) -> str:
    """'' when every problem names the inventory and a place in it: a host (and its variable), a group, a setting."""
    if not isinstance(error, SpecError) or not error.problems:
        return "is not a list of problems"
    for problem in error.problems:
        if problem.source != SOURCE:
            return f"names {problem.source!r}, not the inventory ({problem})"
        if not problem.path.startswith(("hosts", "groups", "kuberos_default_latency_ms")) and not problem.message.startswith(
            ("... and", "no hosts in the groups")
        ):
            return f"names no host, group or setting ({problem})"
    return ""


@fuzz_settings(800)
@given(raw=inventories())
def test_a_hostile_inventory_is_a_model_or_one_located_refusal(raw):
    run_case("inventory", lambda: load_inventory(raw, SOURCE), SpecError, inventory_located, raw)


@fuzz_settings(200)
@given(raw=hostile_value)
def test_anything_as_the_inventory_is_refused_in_one_located_line(raw):
    def located(error):
        return "" if str(error).count("\n") == 1 and "inventory" in str(error) else "is not one line naming the inventory"

    run_case("inventory", lambda: load_inventory(raw, SOURCE), SpecError, located, raw)
