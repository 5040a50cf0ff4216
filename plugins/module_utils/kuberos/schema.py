"""The JSON Schema of a RosDeployment.

This dictionary is the single definition of the spec's shape: the validator uses it, and
``docs/rosdeployment.schema.json`` is generated from it (``make schema``; a test keeps the
two equal). ``x-expected`` holds the phrase error messages use to say what is expected.
"""

from __future__ import annotations

API_VERSION = "kuberos.io/v1alpha1"
KIND = "RosDeployment"
TIERS = ("onboard", "edge", "cloud")
STRATEGIES = ("dedicated", "shared")
MAX_MODULES = 100  # modules of one RosDeployment
MAX_MODULES_PER_FILE = 1000  # modules of all documents of one file: bounds the time a refusal takes

# The end of the text, read alike by both dialects that read these patterns. JSON Schema's (ECMA-262, the editors that
# read docs/rosdeployment.schema.json) '$' is the end, but Python's (jsonschema, and code that matches these constants
# with re) is also the place before a final line feed, so that 'alice\n' would pass '^[a-z]+$'; '(?!\n)' refuses that
# place. Python's '\Z' is not ECMA-262 (a literal 'Z' there, or an error), so the published schema cannot use it.
# Quantities allow blanks around them ('200 ms '), spaces and tabs only: a line break is not a blank here.
END = r"$(?!\n)"
DNS_LABEL = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?" + END
DNS_SUBDOMAIN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*" + END
# Fleet, robot and device names as the inventory writes them (docs/inventory.md).
INVENTORY_NAME = r"^[a-z0-9]([-a-z0-9.]*[a-z0-9])?" + END
ARCH_NAME = r"^[A-Za-z0-9]([-A-Za-z0-9_.]*[A-Za-z0-9])?" + END
ENV_NAME = r"^[A-Za-z_][A-Za-z0-9_]*" + END
LABEL_KEY = (
    r"^([a-z0-9]([-a-z0-9]*[a-z0-9])?(\.[a-z0-9]([-a-z0-9]*[a-z0-9])?)*/)?[A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?" + END
)
LABEL_VALUE = r"^([A-Za-z0-9]([-A-Za-z0-9_.]{0,61}[A-Za-z0-9])?)?" + END
LATENCY = r"^[ \t]*[0-9]+(\.[0-9]+)?[ \t]*(ms|s)?[ \t]*" + END
CPU = r"^[ \t]*[0-9]+(\.[0-9]+)?[ \t]*m?[ \t]*" + END
MEMORY = r"^[ \t]*[0-9]+(\.[0-9]+)?[ \t]*(Ki|Mi|Gi|Ti|k|K|M|G|T)?[ \t]*" + END
ROS_TOPIC = r"^/[A-Za-z0-9_~{}]+(/[A-Za-z0-9_{}]+)*" + END
ROS_TYPE = r"^[A-Za-z][A-Za-z0-9_]*/msg/[A-Z][A-Za-z0-9]*" + END
DIRECTIONS = ("to_module", "from_module")
UPGRADES = ("surge", "recreate")
RMWS = ("fastdds", "cyclonedds")
MAP_TYPES = ("key-value", "yaml")
PULL_POLICIES = ("Always", "IfNotPresent", "Never")
# A parameter map, registry or resource group name: lowercase letters, digits, '-', '_' and '.' (the reference
# format's names, e.g. 'publisher-param.yaml'); ConfigMap names are derived from it (naming.parameter_map_name).
MAP_NAME = r"^[a-z0-9]([-a-z0-9_.]*[a-z0-9])?" + END
# A launch argument's name: what `name:=value` sets in `ros2 launch`.
LAUNCH_ARGUMENT = r"^[A-Za-z_][A-Za-z0-9_.-]*" + END
ABSOLUTE_PATH = r"^/[^\x00-\x1f\x7f]*" + END  # no control character, no line break
# A catalog module: its name, then optionally '@' and a version range (docs/software.md).
DEVELOPER = r"^[A-Za-z0-9]([-A-Za-z0-9_.@]*[A-Za-z0-9])?" + END  # who holds robots of the pool: 'alice', 'alice@example.com'
MODULE_REF = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?(@.*\S.*)?" + END

_ONE_OR_MORE_STRINGS = {
    "anyOf": [
        {"type": "string", "minLength": 1},
        {"type": "array", "minItems": 1, "items": {"type": "string", "minLength": 1}},
    ]
}
# A Prometheus metric name (the module's own load signal), or "cpu".
METRIC_NAME = r"^[a-zA-Z_:][a-zA-Z0-9_:]*" + END


def at_most(quantity: str, value: int, shown: str) -> dict:
    """The bound of a quantity written as a number or as text ('30 s', '500m', '2Gi'): ``maximum`` for the number
    (in the quantity's unit: milliseconds, millicores or bytes... as ``quantities`` parses it), ``x-maximum`` for both
    (the validator parses the text; validation.py), and how the bound reads in a refusal."""
    number = value if quantity != "cpu" else value // 1000  # a CPU number is in cores, its text may be in millicores
    return {"maximum": number, "x-maximum": {"quantity": quantity, "value": value, "shown": shown}}


# Durations (milliseconds as numbers): a QoS deadline or lease up to a day, a scaling window up to an hour (the longest
# stabilization window Kubernetes' HorizontalPodAutoscaler takes), a network latency up to a minute.
MAX_QOS_DURATION = at_most("latency", 86_400_000, "86400 s (a day)")
MAX_WINDOW = at_most("latency", 3_600_000, "3600 s (an hour)")
MAX_LATENCY = at_most("latency", 60_000, "60 s")
MAX_CPU = at_most("cpu", 1_024_000, "1024 CPUs (1024000m)")
MAX_MEMORY = at_most("memory", 64 * 1024**4, "64Ti")


def _duration(bound: dict) -> dict:
    return {
        "type": ["string", "number"],
        "pattern": LATENCY,
        "minimum": 0,
        **bound,
        "x-expected": "a duration such as '30 s' or '500 ms' (a number means milliseconds)",
    }


SCALING = {
    "type": "object",
    "x-expected": "a mapping with maxInstances and optionally minInstances, metric, target, metricsPort and windows",
    "additionalProperties": False,
    "required": ["maxInstances"],
    "description": (
        "With strategy shared: the controller adds and removes instances between minInstances and maxInstances to "
        "keep the load signal per instance near target (docs/scaling.md)."
    ),
    "properties": {
        "minInstances": {
            "type": "integer",
            "minimum": 1,
            "maximum": 1000,
            "default": 1,
            "description": "Fewest instances (default 1; never fewer than the robots need at robotsPerInstance).",
            "x-expected": "a whole number from 1 to 1000",
        },
        "maxInstances": {
            "type": "integer",
            "minimum": 1,
            "maximum": 1000,
            "description": "Most instances (never more than the robots served).",
            "x-expected": "a whole number from 1 to 1000",
        },
        "metric": {
            "type": "string",
            "pattern": METRIC_NAME,
            "maxLength": 200,
            "default": "cpu",
            "description": (
                "The load signal: cpu (CPU use against the module's cpu request, from the Kubernetes metrics API) or "
                "the name of a gauge the module serves in Prometheus format, averaged over the instances."
            ),
            "x-expected": "cpu or a Prometheus metric name such as 'kuberos_planner_queue_depth'",
        },
        "target": {
            "type": "number",
            "exclusiveMinimum": 0,
            "maximum": 1000000,
            "description": "The signal per instance to keep: for cpu a fraction of the request (0.8), else the gauge's value.",
            "x-expected": "a number above 0, such as 0.8 for cpu or 2 for a queue length",
        },
        "metricsPort": {
            "type": "integer",
            "minimum": 1,
            "maximum": 65535,
            "default": 9464,
            "description": "Where each instance serves /metrics, for a module metric (default 9464).",
            "x-expected": "a port number from 1 to 65535",
        },
        "scaleUpWindow": {
            **_duration(MAX_WINDOW),
            "description": "Scale up only to the lowest recommendation of this window (default 0 s).",
        },
        "scaleDownWindow": {
            **_duration(MAX_WINDOW),
            "description": "Scale down only to the highest recommendation of this window (default 60 s).",
        },
        "drainTime": {
            **_duration(MAX_WINDOW),
            "description": "How long a removed instance keeps running after its robots moved away (default 15 s).",
        },
    },
}

_TIER = {"type": "string", "enum": list(TIERS), "x-expected": "one of onboard, edge, cloud"}

# Fragments shared with the software catalog's schema (catalog.py).
IMAGE = {
    "type": "string",
    "minLength": 1,
    "pattern": r"^\S+" + END,
    "description": "Container image of the module.",
    "x-expected": "a container image reference without spaces, such as 'registry/planner:1.0'",
}
LAUNCH = {
    **_ONE_OR_MORE_STRINGS,
    "description": "Command line(s) that start the module, e.g. 'ros2 launch pkg file.launch.py'.",
    "x-expected": "a command line or a non-empty list of command lines",
}
PREFERENCE = {
    "anyOf": [
        _TIER,
        {"type": "array", "minItems": 1, "uniqueItems": True, "items": _TIER},
    ],
    "description": (
        "Where the module should run. A single tier falls back to the others in a fixed "
        "order; a list is the exact order of tiers to try."
    ),
    "x-expected": "one of onboard, edge, cloud, or an ordered list of them without repeats",
}
REQUIREMENTS = {
    "type": "object",
    "x-expected": "a mapping of requirements",
    "additionalProperties": False,
    "properties": {
        "onboard": {
            "type": "boolean",
            "description": "The module must run on the robot's own computer.",
            "x-expected": "true or false",
        },
        "max_latency": {
            "type": ["string", "number"],
            "pattern": LATENCY,
            "minimum": 0,
            **MAX_LATENCY,
            "description": "Largest network latency allowed between the robot and the node.",
            "x-expected": "a latency such as '200 ms', '0.5 s' or a number of milliseconds",
        },
        "arch": {
            "anyOf": [
                {"type": "string", "pattern": ARCH_NAME, "maxLength": 63},
                {"type": "array", "minItems": 1, "items": {"type": "string", "pattern": ARCH_NAME, "maxLength": 63}},
            ],
            "description": "CPU architecture(s) the image runs on, e.g. amd64 or [amd64, arm64].",
            "x-expected": "an architecture such as 'amd64' or a list of them",
        },
        "devices": {
            "type": "array",
            "uniqueItems": True,
            "items": {
                "type": "string",
                "pattern": INVENTORY_NAME,
                "maxLength": 63,
                "x-expected": "a device name of lowercase letters, digits, '-' and '.', such as 'camera'",
            },
            "description": "Devices the node must carry, e.g. [camera, lidar].",
            "x-expected": "a list of distinct device names",
        },
    },
}
RESOURCES = {
    "type": "object",
    "x-expected": "a mapping with cpu, memory and gpu",
    "additionalProperties": False,
    "properties": {
        "cpu": {
            "type": ["string", "number"],
            "pattern": CPU,
            "minimum": 0,
            **MAX_CPU,
            "default": "100m",
            "description": "CPU requested, e.g. 2 or '500m'.",
            "x-expected": "a CPU quantity such as 2, 0.5 or '500m'",
        },
        "memory": {
            "type": ["string", "integer"],
            "pattern": MEMORY,
            "minimum": 0,
            **MAX_MEMORY,
            "default": "128Mi",
            "description": "Memory requested and limited to, e.g. '512Mi'.",
            "x-expected": "a memory quantity such as '512Mi', '2Gi' or '1G'",
        },
        "gpu": {
            "type": "integer",
            "minimum": 0,
            "maximum": 16,
            "default": 0,
            "description": "Number of GPUs (nvidia.com/gpu).",
            "x-expected": "a whole number of GPUs from 0 to 16",
        },
    },
}
ENV = {
    "type": "object",
    "propertyNames": {
        "type": "string",
        "pattern": ENV_NAME,
        "x-expected": "an environment variable name of letters, digits and '_', not starting with a digit",
    },
    "additionalProperties": {
        "type": ["string", "number", "boolean"],
        "x-expected": "a string, number or boolean",
    },
    "description": "Extra environment variables of the module's container.",
    "x-expected": "a mapping of variable names to values",
}
ROS_PARAMETERS = {
    "type": "object",
    "description": "ROS parameters, written to a ConfigMap and mounted as a parameter file.",
    "x-expected": "a mapping of parameter names to values",
}
_MAP_REF = {
    "type": "string",
    "pattern": MAP_NAME,
    "maxLength": 100,
    "x-expected": "the name of an entry of parameterMaps",
}
LAUNCH_ARGUMENTS = {
    "type": "object",
    "maxProperties": 200,
    "propertyNames": {
        "type": "string",
        "pattern": LAUNCH_ARGUMENT,
        "maxLength": 100,
        "x-expected": "a launch argument name of letters, digits, '_', '.' and '-'",
    },
    "additionalProperties": {
        "type": ["string", "number", "boolean"],
        "maxLength": 4096,
        "x-expected": "a value, '{map.key}' (a key of a parameter map) or '{device:name.parameter}' (the node's device)",
    },
    "description": (
        "Appended to the first launch line as name:=value. A value '{map.key}' takes the key of a parameter map; "
        "'{device:<device>.<parameter>}' takes the parameter the inventory gives that device of the node the "
        "instance runs on (kuberos_device_parameters)."
    ),
    "x-expected": "a mapping of launch argument names to values",
}
ENV_FROM = {
    "type": "array",
    "uniqueItems": True,
    "maxItems": 50,
    "items": _MAP_REF,
    "description": "key-value parameter maps whose keys become environment variables of the module's containers.",
    "x-expected": "a list of distinct parameter map names",
}
PARAMETER_FILES = {
    "type": "array",
    "maxItems": 50,
    "items": {
        "type": "object",
        "x-expected": "a mapping with map and mountPath",
        "additionalProperties": False,
        "required": ["map", "mountPath"],
        "properties": {
            "map": {**_MAP_REF, "description": "A yaml parameter map."},
            "mountPath": {
                "type": "string",
                "pattern": ABSOLUTE_PATH,
                "maxLength": 1024,
                "description": "Directory the map's file is mounted in (read-only).",
                "x-expected": "an absolute directory path such as '/workspace/config'",
            },
        },
    },
    "description": "yaml parameter maps mounted as files in the module's containers.",
    "x-expected": "a list of mappings with map and mountPath",
}
UPGRADE = {
    "type": "string",
    "enum": list(UPGRADES),
    "description": (
        "How a new version replaces a running one: surge starts the new instance before the old one stops; "
        "recreate stops the old one first, so that two never run at once (modules that hold hardware). "
        "Default: recreate with requirements.devices, surge otherwise."
    ),
    "x-expected": "surge or recreate",
}

# A declared topic's name: relative (in the robot's namespace: 'detections' is /fetch_1/detections) or absolute, where
# a whole '{robot}' segment stands for the robot ('/{robot}/detections' is the same topic as 'detections').
DECLARED_TOPIC = r"^/?(\{robot\}|[A-Za-z_][A-Za-z0-9_]*)(/(\{robot\}|[A-Za-z_][A-Za-z0-9_]*))*" + END
RELIABILITIES = ("reliable", "best_effort")
DURABILITIES = ("volatile", "transient_local")
LIVELINESSES = ("automatic", "manual_by_topic")
MAX_TOPICS = 200  # declarations of one direction of one module
MAX_RATE_HZ = 100000
_RATE_HZ = {
    "type": "number",
    "exclusiveMinimum": 0,
    "maximum": MAX_RATE_HZ,
    "x-expected": f"a rate in Hz above 0 and at most {MAX_RATE_HZ}",
}


def _declared_topic(subscription: bool) -> dict:
    properties = {
        "name": {
            "type": "string",
            "pattern": DECLARED_TOPIC,
            "maxLength": 256,
            "description": (
                "The topic: relative names are in the robot's namespace ('detections' is /fetch_1/detections on "
                "fetch-1); absolute names are fleet-wide, with '{robot}' as a whole segment for the robot."
            ),
            "x-expected": "a ROS topic name such as 'detections', '/{robot}/detections' or '/fleet/status'",
        },
        "type": {
            "type": "string",
            "pattern": ROS_TYPE,
            "maxLength": 256,
            "description": "Message type, e.g. geometry_msgs/msg/PoseArray.",
            "x-expected": "a message type such as 'std_msgs/msg/String'",
        },
        "qos": {
            "type": "object",
            "additionalProperties": False,
            "x-expected": "a mapping with reliability, durability, depth, deadline, liveliness and lease_duration",
            "properties": {
                "reliability": {
                    "type": "string",
                    "enum": list(RELIABILITIES),
                    "description": "reliable (the ROS default) or best_effort.",
                    "x-expected": "reliable or best_effort",
                },
                "durability": {
                    "type": "string",
                    "enum": list(DURABILITIES),
                    "description": "volatile (the ROS default) or transient_local (latched).",
                    "x-expected": "volatile or transient_local",
                },
                "depth": {
                    "type": "integer",
                    "minimum": 1,
                    "maximum": 100000,
                    "description": "History depth (keep last); does not decide whether endpoints match.",
                    "x-expected": "a whole number from 1 to 100000",
                },
                "deadline": {
                    **_duration(MAX_QOS_DURATION),
                    "description": (
                        "The longest time between two messages: a publisher offers it, a subscription requests it "
                        "(matched when the publisher's is at most the subscription's). Default: none."
                    ),
                },
                "liveliness": {
                    "type": "string",
                    "enum": list(LIVELINESSES),
                    "description": (
                        "automatic (the ROS default) or manual_by_topic; a manual_by_topic subscription gets nothing "
                        "from an automatic publisher."
                    ),
                    "x-expected": "automatic or manual_by_topic",
                },
                "lease_duration": {
                    **_duration(MAX_QOS_DURATION),
                    "description": (
                        "The liveliness lease: matched when the publisher's is at most the subscription's. Default: none."
                    ),
                },
            },
            "description": (
                "The QoS the module's endpoint uses (defaults: reliable, volatile, depth 10, no deadline, automatic "
                "liveliness, no lease); endpoints whose QoS never match are refused, by ROS 2's request-offered rules."
            ),
        },
        "rate": {
            "type": "object",
            "additionalProperties": False,
            "minProperties": 1,
            "x-expected": "a mapping with min and/or max, in Hz",
            "properties": {"min": _RATE_HZ, "max": _RATE_HZ},
            "description": "The rate the topic must have on each robot, in Hz; checked live after deploy and each rollout wave.",
        },
    }
    if subscription:
        properties["external"] = {
            "type": "boolean",
            "description": (
                "Published outside this deployment (a driver on the robot): no module of the deployment need "
                "publish it; the live check still wants a publisher."
            ),
            "x-expected": "true or false",
        }
    return {
        "type": "array",
        "maxItems": MAX_TOPICS,
        "x-expected": f"a list of at most {MAX_TOPICS} topics",
        "items": {
            "type": "object",
            "additionalProperties": False,
            "required": ["name", "type"],
            "x-expected": "a mapping with name and type",
            "properties": properties,
        },
    }


TOPICS = {
    "type": "object",
    "additionalProperties": False,
    "x-expected": "a mapping with publishes and subscribes",
    "properties": {"publishes": _declared_topic(False), "subscribes": _declared_topic(True)},
    "description": (
        "The module's ROS 2 interfaces: the topics it publishes and subscribes, with type, QoS and rate. Deploy "
        "refuses declarations that cannot match; the ROS probe checks them live (docs/software.md, 'Declared topics')."
    ),
}

SCHEMA = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://kuberos.io/schemas/rosdeployment-v1alpha1.json",
    "title": "RosDeployment",
    "description": "Deploys ROS 2 modules to the robots of one fleet, onboard, at the edge or in the cloud.",
    "type": "object",
    "x-expected": "a mapping with metadata and rosModules",
    "additionalProperties": False,
    "required": ["metadata", "rosModules"],
    "properties": {
        "apiVersion": {"const": API_VERSION, "x-expected": f"'{API_VERSION}'"},
        "kind": {"const": KIND, "x-expected": f"'{KIND}'"},
        "metadata": {
            "type": "object",
            "x-expected": "a mapping with name and targetFleet",
            "additionalProperties": False,
            "required": ["name", "targetFleet"],
            "properties": {
                "name": {
                    "type": "string",
                    "pattern": DNS_LABEL,
                    "maxLength": 40,
                    "description": "Name of the deployment; lowercase letters, digits and '-'.",
                    "x-expected": "a name of at most 40 lowercase letters, digits and '-', such as 'picking-demo'",
                },
                "targetFleet": {
                    "type": "string",
                    "pattern": INVENTORY_NAME,
                    "maxLength": 63,
                    "description": "The fleet (from the inventory) whose robots this deployment serves.",
                    "x-expected": "the name of a fleet in the inventory (lowercase letters, digits, '-' and '.')",
                },
                "developer": {
                    "type": "string",
                    "pattern": DEVELOPER,
                    "maxLength": 63,
                    "description": (
                        "A development deployment: the developer who holds its robots in the robot pool "
                        "(playbooks/pool.yml). It runs only on the robots of robotSelector, each reserved by this "
                        "developer; production deployments leave reserved robots out."
                    ),
                    "x-expected": "the name the robots were reserved with, such as 'alice'",
                },
                "robotSelector": {
                    "type": "object",
                    "x-expected": "a mapping with a 'robot' list",
                    "additionalProperties": False,
                    "properties": {
                        "robot": {
                            "type": "array",
                            "minItems": 1,
                            "uniqueItems": True,
                            "items": {"type": "string", "pattern": INVENTORY_NAME, "maxLength": 63, "x-expected": "a robot name"},
                            "description": "Robots of the fleet to deploy to; all robots of the fleet when absent.",
                            "x-expected": "a non-empty list of distinct robot names",
                        }
                    },
                },
                "labels": {
                    "type": "object",
                    "propertyNames": {
                        "type": "string",
                        "pattern": LABEL_KEY,
                        "x-expected": "a label name such as 'team' or 'example.com/team' (at most 63 characters after the '/')",
                    },
                    "additionalProperties": {
                        "type": "string",
                        "pattern": LABEL_VALUE,
                        "x-expected": "a label value of at most 63 letters, digits, '-', '_' and '.', alphanumeric at both ends",
                    },
                    "description": "Extra labels put on every object of the deployment.",
                    "x-expected": "a mapping of label names to strings",
                },
            },
        },
        "rosDomainId": {
            "type": "integer",
            "minimum": 0,
            "maximum": 232,
            "default": 0,
            "description": "ROS_DOMAIN_ID of every module.",
            "x-expected": "an integer from 0 to 232",
        },
        "discovery": {
            "type": "object",
            "x-expected": "a mapping with servers, port and robotServers",
            "additionalProperties": False,
            "properties": {
                "servers": {
                    "type": "integer",
                    "minimum": 1,
                    "maximum": 8,
                    "default": 2,
                    "description": "Number of redundant Fast DDS discovery servers for the fleet.",
                    "x-expected": "an integer from 1 to 8",
                },
                "port": {
                    "type": "integer",
                    "minimum": 1024,
                    "maximum": 65535,
                    "default": 11811,
                    "description": "UDP port of the discovery servers.",
                    "x-expected": "a port number from 1024 to 65535",
                },
                "robotServers": {
                    "type": "boolean",
                    "default": True,
                    "description": "A discovery server on each robot computer that runs onboard modules of this deployment, "
                    "listed after the fleet's servers in those modules' ROS_DISCOVERY_SERVER: they meet each other while "
                    "the robot is cut off from the edge servers, also a module that starts during the cut "
                    "(docs/connectivity.md). Fast DDS only.",
                    "x-expected": "true or false",
                },
            },
        },
        "rmw": {
            "type": "string",
            "enum": list(RMWS),
            "default": "fastdds",
            "description": (
                "The ROS 2 middleware of every module: fastdds (Fast DDS with the fleet's discovery servers) or cyclonedds "
                "(Cyclone DDS with unicast peer lists of the placed instances; no multicast)."
            ),
            "x-expected": "fastdds or cyclonedds",
        },
        "resourceGroups": {
            "type": "array",
            "minItems": 1,
            "uniqueItems": True,
            "items": {"type": "string", "pattern": MAP_NAME, "maxLength": 63, "x-expected": "a resource group name"},
            "description": "Edge and cloud nodes the modules may use: those whose kuberos_resource_group is one of these.",
            "x-expected": "a non-empty list of distinct resource group names",
        },
        "parameterMaps": {
            "type": "array",
            "maxItems": 100,
            "x-expected": "a list of parameter maps",
            "items": {
                "type": "object",
                "x-expected": "a mapping with name, type and data or path",
                "additionalProperties": False,
                "required": ["name", "type"],
                "properties": {
                    "name": {
                        **_MAP_REF,
                        "description": "Name the modules use.",
                        "x-expected": "a name of lowercase letters, digits, '-', '_' and '.'",
                    },
                    "type": {
                        "type": "string",
                        "enum": list(MAP_TYPES),
                        "description": "key-value: environment variables and launch values; yaml: a mounted file.",
                        "x-expected": "key-value or yaml",
                    },
                    "data": {
                        "type": "object",
                        "description": "The map inline: key-value pairs, or the yaml file's content.",
                        "x-expected": "a mapping",
                    },
                    "path": {
                        "type": "string",
                        "minLength": 1,
                        "maxLength": 1024,
                        "description": "A file holding the map (YAML), relative to the spec file.",
                        "x-expected": "a file path relative to the spec file",
                    },
                },
            },
            "description": "Parameter maps, each a ConfigMap of the fleet's namespace.",
        },
        "imageRegistries": {
            "type": "array",
            "maxItems": 50,
            "x-expected": "a list of registries",
            "items": {
                "type": "object",
                "x-expected": "a mapping with name, pullSecret and pullPolicy",
                "additionalProperties": False,
                "required": ["name"],
                "properties": {
                    "name": {
                        "type": "string",
                        "pattern": MAP_NAME,
                        "maxLength": 100,
                        "description": "Name modules use in imageRegistry; 'default' serves modules that name none.",
                        "x-expected": "a registry name such as 'default'",
                    },
                    "pullSecret": {
                        "type": "string",
                        "pattern": DNS_SUBDOMAIN,
                        "maxLength": 253,
                        "description": (
                            "A Secret of type kubernetes.io/dockerconfigjson in the fleet's namespace (KubeROS never "
                            "reads or prints it)."
                        ),
                        "x-expected": "a Secret name of lowercase letters, digits, '-' and '.'",
                    },
                    "pullPolicy": {
                        "type": "string",
                        "enum": list(PULL_POLICIES),
                        "description": "When the kubelet pulls the image.",
                        "x-expected": "Always, IfNotPresent or Never",
                    },
                },
            },
            "description": "Container registries the modules' images are pulled from.",
        },
        "rosModules": {
            "type": "array",
            "minItems": 1,
            "maxItems": MAX_MODULES,
            "x-expected": f"a non-empty list of at most {MAX_MODULES} modules",
            "items": {
                "type": "object",
                "x-expected": "a mapping with name, image and launch",
                "additionalProperties": False,
                "required": ["name"],
                # A module names a catalog module, or gives its image and launch itself; not both.
                "if": {"type": "object", "required": ["module"]},
                "then": {
                    "not": {"required": ["image"]},
                    "x-message": "give either module or image and launch, not both",
                    "x-field": "module",
                },
                "else": {"required": ["image", "launch"]},
                "properties": {
                    "name": {
                        "type": "string",
                        "pattern": DNS_LABEL,
                        "maxLength": 40,
                        "description": "Module name, unique in the deployment.",
                        "x-expected": "a name of at most 40 lowercase letters, digits and '-', such as 'motion-planner'",
                    },
                    "module": {
                        "type": "string",
                        "pattern": MODULE_REF,
                        "maxLength": 300,
                        "description": (
                            "A module of the software catalog instead of image and launch: its name, optionally with "
                            "'@' and a version range, e.g. 'pnp-planner@^0.2'; the highest matching version is used."
                        ),
                        "x-expected": "a catalog module reference such as 'pnp-planner@^0.2' or 'pnp-planner'",
                    },
                    "image": IMAGE,
                    "launch": LAUNCH,
                    "preference": PREFERENCE,
                    "requirements": REQUIREMENTS,
                    "resources": RESOURCES,
                    "strategy": {
                        "type": "string",
                        "enum": list(STRATEGIES),
                        "default": "dedicated",
                        "description": "dedicated: one instance per robot; shared: one instance serves several robots.",
                        "x-expected": "dedicated or shared",
                    },
                    "upgrade": UPGRADE,
                    "robotsPerInstance": {
                        "type": "integer",
                        "minimum": 1,
                        "maximum": 1000,
                        "description": "With strategy shared: most robots one instance serves (default 4).",
                        "x-expected": "a whole number from 1 to 1000",
                    },
                    "scaling": SCALING,
                    "env": ENV,
                    "envFrom": ENV_FROM,
                    "launchArguments": LAUNCH_ARGUMENTS,
                    "parameterFiles": PARAMETER_FILES,
                    "imageRegistry": {
                        "type": "string",
                        "pattern": MAP_NAME,
                        "maxLength": 100,
                        "description": "The entry of imageRegistries the image is pulled with (default: the one named default).",
                        "x-expected": "the name of an entry of imageRegistries",
                    },
                    "privileged": {
                        "type": "boolean",
                        "description": (
                            "Run the containers privileged (host devices, real-time scheduling); the module's fleet "
                            "namespace then enforces only the privileged Pod Security level."
                        ),
                        "x-expected": "true or false",
                    },
                    "user": {
                        "type": "integer",
                        "minimum": 0,
                        "maximum": 2147483647,
                        "description": (
                            "The user ID the containers run as (default 1000, not root: the restricted Pod Security "
                            "level; 0 when privileged). 0 runs them as root, which only the baseline level admits."
                        ),
                        "x-expected": "a user ID such as 1000, or 0 for root",
                    },
                    "workspace": {
                        "type": "string",
                        "pattern": ABSOLUTE_PATH,
                        "maxLength": 1024,
                        "description": (
                            "A ROS workspace's install directory whose setup.bash is sourced (after /opt/ros/$ROS_DISTRO's) "
                            "before each launch line runs."
                        ),
                        "x-expected": "an absolute directory path such as '/workspace/install'",
                    },
                    "shell": {
                        "type": "boolean",
                        "description": (
                            "Run each launch line with /bin/bash -c as written (';', '&&', variables), as the reference "
                            "format does; default false: a literal argv, no shell."
                        ),
                        "x-expected": "true or false",
                    },
                    "rosParameters": ROS_PARAMETERS,
                    "topics": TOPICS,
                    "cluster": {
                        "type": "string",
                        "pattern": DNS_LABEL,
                        "maxLength": 40,
                        "description": (
                            "Run the module in this third-party cluster (registered in the inventory's kuberos_clusters); "
                            "its ROS 2 topics cross over the KubeROS-Bridge."
                        ),
                        "x-expected": "the name of a cluster registered in kuberos_clusters",
                    },
                    "bridge": {
                        "type": "object",
                        "x-expected": "a mapping with topics",
                        "additionalProperties": False,
                        "required": ["topics"],
                        "properties": {
                            "topics": {
                                "type": "array",
                                "minItems": 1,
                                "x-expected": "a non-empty list of topics",
                                "items": {
                                    "type": "object",
                                    "x-expected": "a mapping with name, type and direction",
                                    "additionalProperties": False,
                                    "required": ["name", "type", "direction"],
                                    "properties": {
                                        "name": {
                                            "type": "string",
                                            "pattern": ROS_TOPIC,
                                            "description": "Fully qualified ROS 2 topic name.",
                                            "x-expected": "a topic name such as '/planning/request'",
                                        },
                                        "type": {
                                            "type": "string",
                                            "pattern": ROS_TYPE,
                                            "description": "Message type, e.g. std_msgs/msg/String.",
                                            "x-expected": "a message type such as 'std_msgs/msg/String'",
                                        },
                                        "direction": {
                                            "type": "string",
                                            "enum": list(DIRECTIONS),
                                            "description": "to_module: robots' side to the module; from_module: back.",
                                            "x-expected": "to_module or from_module",
                                        },
                                    },
                                },
                            }
                        },
                        "description": "The topics the module exchanges with the robots' side, through the bridge.",
                    },
                },
            },
        },
    },
}
