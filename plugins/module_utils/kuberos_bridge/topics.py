"""The topics file: which ROS 2 topics the bridge carries, of which type, in which direction.

```yaml
topics:
- {name: /planning/request, type: std_msgs/msg/String, direction: to_client}
- {name: /planning/response, type: std_msgs/msg/String, direction: to_server, depth: 10}
```

``to_client`` topics are subscribed in the main cluster (by the server) and republished beside the module
(by the client); ``to_server`` the other way. ``depth`` (optional, default 10) is the KEEP_LAST history
depth of the bridge's subscription and of the far side's publisher: DDS does not announce a publisher's
depth, only its reliability and durability, which the bridge copies.

Every problem of a file is reported at once, each naming the file and the field
(``topics.yml: topics[1].direction: ...``). Message types are looked up by name when the bridge starts
(``load_message_type``): a type whose package is not installed disables its topic, with an error, and the
bridge carries the others.
"""

from __future__ import annotations

import difflib
import importlib
import re
from dataclasses import dataclass

TO_CLIENT = "to_client"
TO_SERVER = "to_server"
DIRECTIONS = (TO_CLIENT, TO_SERVER)
DEFAULT_DEPTH = 10
MAX_DEPTH = 10000
MAX_TOPICS = 1000
MAX_FILE_BYTES = 1 << 20

_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
TOPIC_RE = re.compile(rf"^(/{_TOKEN})+\Z")
TYPE_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(?:msg/)?([A-Za-z][A-Za-z0-9_]*)\Z")
FIELDS = ("name", "type", "direction", "depth")


class TopicsError(ValueError):
    """A topics file that cannot be used; ``problems`` lists every problem, one per line of the message."""

    def __init__(self, source: str, problems: list[str]):
        self.source, self.problems = source, problems
        super().__init__("\n".join(f"{source}: {p}" for p in problems))


class TypeLookupError(LookupError):
    """A message type name that names no installed ROS 2 message."""


@dataclass(frozen=True)
class Topic:
    name: str
    type: str  # normalized: pkg/msg/Type
    direction: str
    depth: int = DEFAULT_DEPTH

    def outgoing_for(self, role: str) -> bool:
        """True when ``role`` ("server" or "client") subscribes to this topic and sends it to its peer."""
        return (self.direction == TO_CLIENT) == (role == "server")


def normalize_type(name: str) -> str:
    """'pkg/msg/Type' or 'pkg/Type' -> 'pkg/msg/Type'; TypeLookupError for anything else."""
    match = TYPE_RE.match(name) if isinstance(name, str) else None
    if not match:
        raise TypeLookupError(f"{name!r} is not a message type name of the form pkg/msg/Type")
    return f"{match.group(1)}/msg/{match.group(2)}"


def load_message_type(name: str):
    """The Python class of a ROS 2 message type, imported from ``pkg.msg``; TypeLookupError if there is none."""
    normalized = normalize_type(name)
    package, _interface, type_name = normalized.split("/")
    try:
        module = importlib.import_module(f"{package}.msg")
    except ImportError as error:
        raise TypeLookupError(
            f"unknown message type {normalized!r}: the Python package {package}.msg cannot be imported ({error}); "
            f"is the ROS 2 package {package} installed?"
        ) from None
    cls = getattr(module, type_name, None)
    if cls is None or not callable(getattr(cls, "__import_type_support__", None)):
        known = sorted(
            n
            for n in dir(module)
            if not n.startswith("_") and callable(getattr(getattr(module, n), "__import_type_support__", None))
        )
        close = difflib.get_close_matches(type_name, known, n=3)
        if close:
            hint = f" (did you mean {' or '.join(close)}?)"
        else:
            hint = f" (it has {', '.join(known[:12])}{', ...' if len(known) > 12 else ''})" if known else ""
        raise TypeLookupError(f"unknown message type {normalized!r}: {package}.msg has no message {type_name}{hint}")
    return cls


def parse_topics(data, source: str) -> list[Topic]:
    """Validate the loaded YAML document of a topics file; TopicsError with every problem."""
    problems: list[str] = []
    if not isinstance(data, dict):
        raise TopicsError(source, [f"the file must be a mapping with the key 'topics', not {type(data).__name__}"])
    for key in sorted(set(data) - {"topics"}, key=str):
        problems.append(f"{key}: unknown key (the file has only 'topics')")
    entries = data.get("topics")
    if not isinstance(entries, list) or not entries:
        problems.append("topics: must be a non-empty list of {name, type, direction}")
        raise TopicsError(source, problems)
    if len(entries) > MAX_TOPICS:
        raise TopicsError(source, [*problems, f"topics: {len(entries)} entries, at most {MAX_TOPICS}"])
    topics: list[Topic] = []
    seen: dict[str, int] = {}
    for index, entry in enumerate(entries):
        where = f"topics[{index}]"
        if not isinstance(entry, dict):
            problems.append(f"{where}: must be a mapping with name, type and direction, not {type(entry).__name__}")
            continue
        before = len(problems)
        for key in sorted(set(entry) - set(FIELDS), key=str):
            problems.append(f"{where}.{key}: unknown field (fields: {', '.join(FIELDS)})")
        name = entry.get("name")
        if name is None:
            problems.append(f"{where}.name: missing")
        elif not isinstance(name, str) or not TOPIC_RE.match(name):
            problems.append(f"{where}.name: {name!r} is not an absolute ROS 2 topic name such as /planning/request")
        elif name in seen:
            problems.append(f"{where}.name: {name} is already topics[{seen[name]}] (a topic crosses in one direction only)")
        else:
            seen[name] = index
        type_name = entry.get("type")
        if type_name is None:
            problems.append(f"{where}.type: missing")
        else:
            try:
                type_name = normalize_type(type_name)
            except TypeLookupError as error:
                problems.append(f"{where}.type: {error}")
        direction = entry.get("direction")
        if direction is None:
            problems.append(f"{where}.direction: missing (to_client or to_server)")
        elif direction not in DIRECTIONS:
            problems.append(f"{where}.direction: {direction!r} is neither to_client nor to_server")
        depth = entry.get("depth", DEFAULT_DEPTH)
        if isinstance(depth, bool) or not isinstance(depth, int) or not 1 <= depth <= MAX_DEPTH:
            problems.append(f"{where}.depth: {depth!r} is not a whole number from 1 to {MAX_DEPTH}")
        if len(problems) == before:
            topics.append(Topic(name=name, type=type_name, direction=direction, depth=depth))
    if problems:
        raise TopicsError(source, problems)
    return topics


def load_topics(path: str) -> list[Topic]:
    """Read and validate a topics file (YAML); TopicsError naming the file and every bad field."""
    import yaml

    try:
        with open(path, "rb") as handle:
            raw = handle.read(MAX_FILE_BYTES + 1)
    except OSError as error:
        raise TopicsError(path, [f"cannot read: {error.strerror or error}"]) from None
    if len(raw) > MAX_FILE_BYTES:
        raise TopicsError(path, [f"larger than {MAX_FILE_BYTES} bytes"])
    try:
        data = yaml.safe_load(raw.decode("utf-8"))
    except (UnicodeDecodeError, yaml.YAMLError) as error:
        raise TopicsError(path, [f"not valid YAML: {error}".replace("\n", " ")]) from None
    return parse_topics(data, path)
