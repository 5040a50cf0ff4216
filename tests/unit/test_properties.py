"""Property tests: any valid spec either places with every hard requirement met, or fails with an
explanation; any input at all gives a RosDeployment or a SpecError, never another exception."""

from __future__ import annotations

from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import PlacementError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import (
    DISCOVERY_CPU_MILLIS,
    DISCOVERY_MEMORY_BYTES,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments, parse_rosdeployment

DEVICES = ["camera", "lidar", "gripper"]
ARCHES = ["amd64", "arm64"]
SETTINGS = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def sites(draw):
    hosts, groups = {}, {"robots": [], "edge": [], "cloud": []}
    fleets = ["f", "g"][: draw(st.integers(1, 2))]
    for i in range(draw(st.integers(1, 5))):
        name = f"r{i}"
        hosts[name] = {
            "kuberos_fleet": draw(st.sampled_from(fleets)),
            "kuberos_cpu": draw(st.sampled_from([1, 2, "500m", 4])),
            "kuberos_memory": draw(st.sampled_from(["512Mi", "2Gi", "8Gi"])),
            "kuberos_arch": draw(st.sampled_from(ARCHES)),
            "kuberos_devices": draw(st.lists(st.sampled_from(DEVICES), unique=True, max_size=2)),
        }
        groups["robots"].append(name)
    fleets = sorted({hosts[r]["kuberos_fleet"] for r in groups["robots"]})
    for tier in ("edge", "cloud"):
        for i in range(draw(st.integers(0, 3))):
            name = f"{tier[0]}{i}"
            host = {
                "kuberos_cpu": draw(st.sampled_from([1, 4, 16])),
                "kuberos_memory": draw(st.sampled_from(["1Gi", "8Gi", "64Gi"])),
                "kuberos_gpu": draw(st.integers(0, 2)),
                "kuberos_arch": draw(st.sampled_from(ARCHES)),
                "kuberos_latency_ms": draw(st.sampled_from([1, 5, 30, 120])),
            }
            if draw(st.booleans()):
                host["kuberos_fleets"] = [draw(st.sampled_from(fleets))]
            hosts[name] = host
            groups[tier].append(name)
    targets = groups["edge"] + groups["cloud"]
    for robot in groups["robots"]:
        if targets and draw(st.booleans()):
            hosts[robot]["kuberos_link_latency_ms"] = {draw(st.sampled_from(targets)): draw(st.sampled_from([2, 50, 300]))}
    return {"hosts": hosts, "groups": groups}


tiers = st.sampled_from(["onboard", "edge", "cloud"])
modules = st.fixed_dictionaries(
    {"name": st.just("m"), "image": st.just("img"), "launch": st.just(["ros2 run p n"])},
    optional={
        "preference": st.one_of(tiers, st.lists(tiers, min_size=1, max_size=3, unique=True)),
        "requirements": st.fixed_dictionaries(
            {},
            optional={
                "onboard": st.booleans(),
                "max_latency": st.sampled_from(["3 ms", "40 ms", 100, "0.2 s"]),
                "arch": st.sampled_from(ARCHES),
                "devices": st.lists(st.sampled_from(DEVICES), unique=True, max_size=2),
            },
        ),
        "resources": st.fixed_dictionaries(
            {},
            optional={
                "cpu": st.sampled_from(["100m", 1, 2, "3500m"]),
                "memory": st.sampled_from(["64Mi", "1Gi", "4Gi"]),
                "gpu": st.integers(0, 2),
            },
        ),
        "strategy": st.sampled_from(["dedicated", "shared"]),
    },
)


@st.composite
def specs(draw):
    mods = draw(st.lists(modules, min_size=1, max_size=4))
    for index, mod in enumerate(mods):
        mod["name"] = f"m{index}"
        if mod.get("strategy") == "shared" and draw(st.booleans()):
            mod["robotsPerInstance"] = draw(st.integers(1, 3))
    return {
        "metadata": {"name": "app", "targetFleet": draw(st.sampled_from(["f", "g"]))},
        "discovery": {"servers": draw(st.integers(1, 3))},
        "rosModules": mods,
    }


def check_hard_requirements(placement, dep, inventory):
    modules = {m.name: m for m in dep.modules}
    robots = inventory.fleets[dep.fleet]
    used: dict[str, list[int]] = {n: [0, 0, 0, 0] for n in inventory.nodes}
    for servers in placement.discovery.values():
        for s in servers:
            used[s.node][0] += DISCOVERY_CPU_MILLIS
            used[s.node][1] += DISCOVERY_MEMORY_BYTES
            used[s.node][3] += 1
    seen = set()
    for inst in placement.instances:
        mod, node = modules[inst.module], inventory.nodes[inst.node]
        req = mod.requirements
        assert inst.tier == node.tier and inst.tier in mod.tiers
        assert node.serves_fleet(dep.fleet) or node.tier == "onboard"
        if node.tier == "onboard":
            assert inst.robots == (node.robot,), "an onboard computer serves only its own robot"
        if req.onboard:
            assert node.tier == "onboard"
        if req.max_latency_ms is not None:
            assert all(inventory.latency_ms(r, node.name) <= req.max_latency_ms for r in inst.robots)
        assert not req.arch or node.arch in req.arch
        assert set(req.devices) <= node.devices
        assert len(inst.robots) <= mod.robots_per_instance
        for robot in inst.robots:
            assert (robot, inst.module) not in seen
            seen.add((robot, inst.module))
        u = used[node.name]
        u[0] += inst.cpu_millis
        u[1] += inst.memory_bytes
        u[2] += inst.gpu
        u[3] += 1
    assert seen == {(r, m) for r in robots for m in modules}, "every module of every robot is placed exactly once"
    for name, (cpu, memory, gpu, pods) in used.items():
        node = inventory.nodes[name]
        assert cpu <= node.cpu_millis and memory <= node.memory_bytes and gpu <= node.gpu and pods <= node.pods


@SETTINGS
@given(site=sites(), data=specs())
def test_valid_specs_place_within_hard_requirements_or_explain(site, data):
    inventory = load_inventory(site)
    try:
        dep = parse_rosdeployment(data, "p.yml")
    except SpecError as exc:
        # Only the documented contradictions are rejected for generated specs.
        assert all(("contradicts" in p.message or "cannot run onboard" in p.message) for p in exc.problems), exc
        return
    try:
        placement = place_modules([dep], inventory)
    except SpecError as exc:
        assert dep.fleet not in inventory.fleets and "is not a fleet" in str(exc)
        return
    except PlacementError as exc:
        event("infeasible")
        assert "has no feasible node" in str(exc) or "discovery server" in str(exc)
        for failure in exc.failures:
            assert failure.count("\n") >= 1, "every failure explains at least one rejected node"
        return
    event("placed")
    check_hard_requirements(placement, dep, inventory)
    again = place_modules([dep], inventory)
    assert again.to_dict() == placement.to_dict()


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=10), children, max_size=4),
    max_leaves=25,
)
keys = st.sampled_from(
    [
        "metadata",
        "rosModules",
        "name",
        "image",
        "launch",
        "preference",
        "requirements",
        "resources",
        "targetFleet",
        "robotSelector",
        "robot",
        "max_latency",
        "onboard",
        "env",
        "strategy",
        "gpu",
        "cpu",
    ]
)
specish = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 300) | st.floats() | st.sampled_from(["edge", "200 ms", "2Gi", "x", ""]),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(keys, children, max_size=5),
    max_leaves=30,
)


@settings(max_examples=400, deadline=None)
@given(data=st.one_of(json_values, specish))
def test_any_data_is_a_deployment_or_a_spec_error(data):
    try:
        parse_rosdeployment(data, "fuzz.yml")
    except SpecError as exc:
        assert exc.problems and all(p.source == "fuzz.yml" for p in exc.problems)


yaml_tokens = st.sampled_from([*list("ab:-[]{}&*!|>'\"#\n\t ,?%@`"), "metadata:", "rosModules:", "name: ", "- ", "&x ", "*x"])


@settings(max_examples=300, deadline=None)
@given(text=st.lists(yaml_tokens, max_size=40).map("".join))
def test_any_text_is_a_deployment_or_a_spec_error(text):
    try:
        load_rosdeployments(text, "fuzz.yml")
    except SpecError as exc:
        assert exc.problems and str(exc).startswith("fuzz.yml")


topic_keys = st.sampled_from(
    [
        "publishes",
        "subscribes",
        "name",
        "type",
        "qos",
        "reliability",
        "durability",
        "depth",
        "rate",
        "min",
        "max",
        "external",
        "deadline",
        "liveliness",
        "lease_duration",
    ]
)
topicish = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-3, 2000)
    | st.floats()
    | st.sampled_from(
        [
            "chatter",
            "/{robot}/scan",
            "{robot}",
            "/a//b",
            "std_msgs/msg/String",
            "reliable",
            "best_effort",
            "transient_local",
            "volatile",
            "",
            "x y",
        ]
    ),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(topic_keys, children, max_size=4),
    max_leaves=30,
)


odd = st.none() | st.booleans() | st.integers(-3, 2000) | st.floats() | st.text(max_size=6)
declared = st.fixed_dictionaries(
    {"name": st.sampled_from(["chatter", "/{robot}/chatter", "/chatter"]), "type": st.sampled_from(["std_msgs/msg/String",
                                                                                                  "std_msgs/msg/Int32"])},
    optional={
        "qos": st.fixed_dictionaries(
            {},
            optional={
                "reliability": st.sampled_from(["reliable", "best_effort"]) | odd,
                "durability": st.sampled_from(["volatile", "transient_local"]) | odd,
                "depth": st.integers(-1, 5000) | odd,
                "deadline": st.sampled_from([0, 50, "100 ms", "0.2 s", "-1 ms", "fast"]) | odd,
                "liveliness": st.sampled_from(["automatic", "manual_by_topic"]) | odd,
                "lease_duration": st.sampled_from([0, 1000, "1 s", "2 s"]) | odd,
            },
        ),
        "rate": st.fixed_dictionaries({}, optional={"min": st.floats(0, 100) | odd, "max": st.floats(0, 100) | odd}),
        "external": st.booleans() | odd,
    },
)  # fmt: skip
graphs = st.fixed_dictionaries({}, optional={"publishes": st.lists(declared, max_size=3),
                                            "subscribes": st.lists(declared, max_size=3)})  # fmt: skip


@settings(max_examples=400, deadline=None)
@given(talker=st.one_of(topicish, graphs), listener=st.one_of(topicish, graphs))
def test_any_declared_topics_are_a_deployment_or_a_located_spec_error(talker, listener):
    """Whatever two modules declare as their topics, the spec loads or every problem names its file and field."""
    data = {
        "apiVersion": "kuberos.io/v1alpha1",
        "kind": "RosDeployment",
        "metadata": {"name": "graph", "targetFleet": "f"},
        "rosModules": [
            {"name": "talker", "image": "reg/talker:1", "launch": "talker", "topics": talker},
            {"name": "listener", "image": "reg/listener:1", "launch": "listener", "topics": listener},
        ],
    }
    try:
        parse_rosdeployment(data, "fuzz.yml")
    except SpecError as exc:
        event("refused")
        assert exc.problems and all(p.source == "fuzz.yml" for p in exc.problems)
        assert all(p.path.startswith("rosModules[") for p in exc.problems), [str(p) for p in exc.problems]
    else:
        event("loaded")
