"""The deployment record: what deploy decided, kept in the cluster for the controller.

Deploy writes one ConfigMap per RosDeployment into the fleet's namespace (``kuberos-record-<name>``)
holding that deployment's own document of the spec file, the fleet resource model, the render options
and the placement. The controller reads it back, re-places instances when nodes fail or links degrade,
and writes the new placement into it, so a restarted controller (or a second one) continues from the
truth in the cluster rather than from memory.

Bounded (format 2): the document (not the whole file: a file of 40 documents gives 40 records of one
document each), the placement, the inventory and the catalog entries are gzip-compressed (binaryData);
a 1,000-robot placement is about 1 MB as plain JSON, the size limit of a ConfigMap. The document is kept
as written, preceded by blank lines, so that line numbers in problems read back from a record are those
of the spec file it was deployed from. A record or revision that would hold more than ``RECORD_BUDGET``
bytes is refused with a ``SpecError`` naming the file, the document's line and the deployment, before
anything is written. Records of format 1 (the whole file as text in ``data``) are still read.

Pure: plain dicts in, plain dicts out.
"""

from __future__ import annotations

import base64
import dataclasses
import gzip
import hashlib
import json
from dataclasses import dataclass, field

from . import naming
from .errors import Problem, SpecError
from .inventory import Inventory, load_inventory
from .labels import COMPONENT, DEPLOYMENT, FIELD_MANAGER, MANAGED_BY
from .manifests import RenderOptions, device_options
from .placement import Placement
from .spec import RosDeployment, file_reader, load_rosdeployments
from .third_party import yaml

RECORD_LABEL = "kuberos.io/record"
STATUS_LABEL = "kuberos.io/status"
REVISION_LABEL = "kuberos.io/revision"
CATALOG_LABEL = "kuberos.io/catalog"
CATALOG_NAME = "kuberos-catalog"
RECORD_PREFIX = "kuberos-record-"
STATUS_PREFIX = "kuberos-status-"
REVISION_PREFIX = "kuberos-rev-"
REVISION_HISTORY = 10  # revisions kept per deployment (older ones are removed by the prune)
FORMAT = "2"  # the document compressed in binaryData (spec.yaml.gz); format 1 kept the whole file in data
FORMATS_READ = ("1", "2")
CATALOG_FORMAT = "1"
SPEC_KEY = "spec.yaml.gz"
LEGACY_SPEC_KEY = "spec.yaml"
# Kubernetes refuses a ConfigMap whose data and binaryData values hold more than 1 MiB together. Deploy fills at
# most RECORD_BUDGET of it; the rest is room for what others add later: the controller's placements (an
# instance moved keeps its size, within a few bytes) and a rollout's marker (rollout.json, plain JSON).
CONFIGMAP_LIMIT = 1024 * 1024
RECORD_BUDGET = 768 * 1024
# Who wrote the placement last. The controller re-pins Deployments only to finish its own moves: while
# deploy is applying a placement it wrote, the Deployments are deploy's to change.
WRITER_DEPLOY = "deploy"
WRITER_CONTROLLER = "controller"


def record_name(deployment: str) -> str:
    return naming.dns_label(RECORD_PREFIX + deployment, max_len=253)


def status_name(deployment: str) -> str:
    return naming.dns_label(STATUS_PREFIX + deployment, max_len=253)


def revision_name(deployment: str, number: int) -> str:
    return naming.dns_label(f"{REVISION_PREFIX}{deployment}-{number}", max_len=253)


def fingerprint(dep: RosDeployment) -> str:
    """A digest of what a deployment asks for (its modules, versions, images, parameters...), not where it was read."""
    data = dataclasses.asdict(dep)
    data.pop("source", None)
    data.pop("lines", None)
    data.pop("document", None)  # its text as written (comments, layout): where it was read, not what it asks for
    for module in data.get("modules", []):
        module.pop("index", None)
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


def next_revision(dep: RosDeployment, current: dict | None) -> int:
    """The revision number an applied state gets: the current one when nothing it asks for changed, else one more.
    ``current`` is ``{"revision": n, "hash": fingerprint}`` of the record in the cluster (None: not deployed)."""
    if not current or not current.get("revision"):
        return 1
    if current.get("hash") == fingerprint(dep):
        return int(current["revision"])
    return int(current["revision"]) + 1


def module_versions(dep: RosDeployment) -> dict[str, str]:
    """Per module, its catalog module and version, or its image when it names no catalog module."""
    return {m.name: (f"{m.catalog_module}@{m.version}" if getattr(m, "version", "") else m.image) for m in dep.modules}


def _pack(data) -> str:
    raw = json.dumps(data, sort_keys=True, separators=(",", ":")).encode()
    return base64.b64encode(gzip.compress(raw, mtime=0)).decode()


def _unpack(text: str):
    return json.loads(gzip.decompress(base64.b64decode(text)))


def configmap_bytes(configmap: dict) -> int:
    """What Kubernetes counts against a ConfigMap's 1 MiB: the bytes of every data value and binaryData value."""
    data = configmap.get("data") or {}
    binary = configmap.get("binaryData") or {}
    return sum(len(str(v).encode("utf-8")) for v in data.values()) + sum(len(base64.b64decode(v)) for v in binary.values())


@dataclass(frozen=True)
class SpecDocument:
    """One RosDeployment document of a spec file: the line it starts on, and its text as written, preceded by
    blank lines so that every line keeps its number in the file."""

    line: int
    text: str
    data: object


def _root_name(node) -> str | None:
    """``metadata.name`` of a composed document, when it is a plain scalar there."""
    if not isinstance(node, yaml.MappingNode):
        return None
    for key, value in node.value:
        if isinstance(key, yaml.ScalarNode) and key.value == "metadata" and isinstance(value, yaml.MappingNode):
            for inner_key, inner_value in value.value:
                if isinstance(inner_key, yaml.ScalarNode) and inner_key.value == "name":
                    return inner_value.value if isinstance(inner_value, yaml.ScalarNode) else None
    return None


def spec_documents(spec_text: str) -> dict[str, SpecDocument]:
    """Each document of a (validated) spec file's text, by its ``metadata.name`` (the first one of a name)."""
    found: dict[str, SpecDocument] = {}
    loader = _loader()(spec_text)
    try:
        while loader.check_node():
            node = loader.get_node()
            if node is None:
                continue
            data = loader.construct_document(node)
            name = _root_name(node)
            if name is None or name in found:
                continue
            start = node.start_mark.index - node.start_mark.column  # from the start of its line: indentation stays
            text = spec_text[start : node.end_mark.index]
            text += "" if text.endswith("\n") else "\n"
            found[name] = SpecDocument(node.start_mark.line + 1, "\n" * node.start_mark.line + text, data)
    finally:
        loader.dispose()
    return found


def _loader():
    # libyaml's loader when there is one: its marks count characters too, and it is many times faster
    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _same_document(text: str, data) -> bool:
    """Whether ``text`` alone loads as ``data`` (a NaN is equal to itself here)."""
    try:
        loaded = yaml.load(text, Loader=_loader())
    except yaml.YAMLError:
        return False
    return loaded == data or repr(loaded) == repr(data)


def _document(dep: RosDeployment, documents: dict[str, SpecDocument]) -> SpecDocument:
    document = documents.get(dep.name)
    if document is None:
        raise SpecError([Problem(dep.source, "metadata.name", f"the spec text has no RosDeployment named {dep.name!r}")])
    return document


def document_of(dep: RosDeployment, documents: dict[str, SpecDocument]) -> str:
    """The text a record keeps of ``dep``: its document as written when that alone loads as the same data (it does
    unless it leans on a YAML directive above it), else the document's data written out again, its first line still
    where it was. Raises ``SpecError`` when the spec text has no such document."""
    document = _document(dep, documents)
    if _same_document(document.text, document.data):
        return document.text
    return "\n" * (document.line - 1) + yaml.safe_dump(document.data, sort_keys=False, default_flow_style=False)


def _too_large(dep: RosDeployment, line: int, configmap: dict, parts: dict[str, int]) -> Problem | None:
    size = configmap_bytes(configmap)
    if size <= RECORD_BUDGET:
        return None
    name = configmap["metadata"]["name"]
    detail = ", ".join(f"{key} {value:,}" for key, value in sorted(parts.items(), key=lambda kv: -kv[1]) if value)
    return Problem(
        dep.source,
        "",
        f"the deployment {dep.name!r} needs a ConfigMap {name} of {size:,} bytes ({detail}), over the {RECORD_BUDGET:,} "
        f"a record may hold (a ConfigMap holds at most {CONFIGMAP_LIMIT:,}; the rest is kept for the controller and "
        "rollouts); make its document smaller (comments count too) or, when the placement is the larger part, spread "
        "its robots over more deployments",
        line,
    )


def restrict_placement(placement: Placement, deployment: str) -> Placement:
    """The part of a placement that belongs to one deployment, with its fleet's discovery servers."""
    return split_placement(placement, [deployment])[deployment]


def split_placement(placement: Placement, deployments: list[str]) -> dict[str, Placement]:
    """``restrict_placement`` for each of ``deployments``, in one pass over the placement (a file of many
    documents gives many records)."""
    instances: dict[str, list] = {name: [] for name in deployments}
    described: dict[str, list[dict]] = {name: [] for name in deployments}
    for inst in placement.instances:
        if inst.deployment in instances:
            instances[inst.deployment].append(inst)
    for dep in placement.deployments:
        if dep["name"] in described:
            described[dep["name"]].append(dep)
    out = {}
    for name in deployments:
        fleets = {d["fleet"] for d in described[name]}
        out[name] = Placement(
            instances[name], {f: s for f, s in placement.discovery.items() if f in fleets}, described[name], [],
            robot_servers=[r for r in placement.robot_servers if r.deployment == name],
        )  # fmt: skip
    return out


def build_records(
    spec_text: str,
    source: str,
    deployments: list[RosDeployment],
    placement: Placement,
    inventory_raw: dict,
    options: RenderOptions,
    field_manager: str,
    revisions: dict | None = None,
    catalog=None,
    cause: str = "deploy",
) -> list[dict]:
    """One record ConfigMap per deployment, and one ConfigMap of its revision, ready for server-side apply.

    ``spec_text`` is the text of the spec file (or of a revision) the deployments were read from; each record keeps
    only its own deployment's document of it. ``revisions`` maps a deployment to its record's ``{"revision",
    "hash"}`` in the cluster; ``catalog`` (a ``Catalog``) holds the catalog entries the spec resolved: each record
    keeps those its deployment uses, so that it reads back alone. Raises ``SpecError`` (every deployment's problem
    at once) when a record or revision would not fit in a ConfigMap."""
    documents = None if all(d.document for d in deployments) else spec_documents(spec_text)  # read with the spec
    inventory_packed = _pack(inventory_raw)
    placements = split_placement(placement, [d.name for d in deployments])
    records, problems = [], []
    for dep in deployments:
        if dep.document:
            text = dep.document
            line = len(text) - len(text.lstrip("\n")) + 1
        else:
            line, text = _document(dep, documents).line, document_of(dep, documents)
        spec_packed = pack_text(text)
        number = next_revision(dep, (revisions or {}).get(dep.name))
        placement_packed = _pack(placements[dep.name].to_dict())
        revision, record = _record_pair(dep, number, cause, source, line, spec_packed, options, field_manager, catalog)
        record["binaryData"].update({"inventory.json.gz": inventory_packed, "placement.json.gz": placement_packed})
        parts = {
            "spec document (gzip)": _packed_size(spec_packed),
            "inventory (gzip)": _packed_size(inventory_packed),
            "placement (gzip)": _packed_size(placement_packed),
            "catalog entries (gzip)": _packed_size(record["binaryData"].get("catalog.json.gz", "")),
        }
        problem = _too_large(dep, line, record, parts) or _too_large(dep, line, revision, parts)
        if problem:
            problems.append(problem)
        records.extend([revision, record])
    if problems:
        raise SpecError(problems, title=f"{source}: a deployment record would not fit in a ConfigMap")
    return records


def _record_pair(dep, number, cause, source, line, spec_packed, options, field_manager, catalog) -> tuple[dict, dict]:
    """A deployment's revision and record (without inventory and placement)."""
    namespace = naming.fleet_namespace(dep.fleet)
    used = _catalog_for(dep, catalog)
    catalog_packed = {"catalog.json.gz": _pack(used.to_dict())} if used is not None else {}
    if dep.files:
        catalog_packed[FILES_KEY] = _pack(dict(dep.files))
    revision = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": revision_name(dep.name, number),
            "namespace": namespace,
            "labels": {MANAGED_BY: "kuberos", REVISION_LABEL: str(number), DEPLOYMENT: dep.name},
        },
        "data": {
            "format": FORMAT,
            "deployment": dep.name,
            "revision": str(number),
            "hash": fingerprint(dep),
            "cause": cause,
            "source": source,
            "spec-line": str(line),
            "versions.json": json.dumps(module_versions(dep), sort_keys=True),
        },
        "binaryData": {SPEC_KEY: spec_packed, **catalog_packed},
    }
    record = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": record_name(dep.name),
            "namespace": namespace,
            "labels": {MANAGED_BY: "kuberos", RECORD_LABEL: "true", DEPLOYMENT: dep.name},
        },
        "data": {
            "format": FORMAT,
            "writer": WRITER_DEPLOY,
            "deployment": dep.name,
            "revision": str(number),
            "revision-hash": fingerprint(dep),
            "source": source,
            "spec-line": str(line),
            "options.json": json.dumps(
                {
                    "cluster_domain": options.cluster_domain,
                    "discovery_image": options.discovery_image,
                    "image_pull_policy": options.image_pull_policy,
                    "field_manager": field_manager,
                    # the digest each image was pinned to (image_pins): the controller and rollback render the same
                    **({"image_digests": dict(options.image_digests)} if options.image_digests else {}),
                },
                sort_keys=True,
            ),
        },
        "binaryData": {SPEC_KEY: spec_packed, **catalog_packed},
    }
    return revision, record


def _catalog_for(dep: RosDeployment, catalog):
    """The catalog entries ``dep``'s modules resolved to (None when it names no catalog module)."""
    refs = [(m.catalog_module, m.version) for m in dep.modules if getattr(m, "version", "")]
    if catalog is None or not refs:
        return None
    return catalog.subset(refs)


def pack_text(text: str) -> str:
    return base64.b64encode(gzip.compress(text.encode("utf-8"), mtime=0)).decode()


def unpack_text(packed: str) -> str:
    return gzip.decompress(base64.b64decode(packed)).decode("utf-8")


def _packed_size(packed: str) -> int:
    return len(base64.b64decode(packed))


FILES_KEY = "files.json.gz"  # the files a deployment's parameter maps were read from: {path as the spec wrote it: text}


def files_of(configmap: dict):
    """A ``read_file`` for the files a record or revision keeps (``spec.file_reader``)."""
    packed = (configmap.get("binaryData") or {}).get(FILES_KEY)
    return file_reader("", _unpack(packed) if packed else {})


def spec_text_of(configmap: dict) -> str:
    """The spec text a record or revision keeps: its deployment's document (format 2), or the whole file (format 1)."""
    if (configmap.get("data") or {}).get("format") == "1":
        return configmap["data"][LEGACY_SPEC_KEY]
    return unpack_text((configmap.get("binaryData") or {})[SPEC_KEY])


def catalog_configmap(namespace: str, catalog) -> dict:
    """The whole software catalog as deploy saw it, in a fleet's namespace: what the controller and the dashboard
    read to show which versions exist (a record keeps only the entries its deployment uses)."""
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": CATALOG_NAME,
            "namespace": namespace,
            # The fleet's, like its discovery servers: it goes with the fleet's last deployment.
            "labels": {MANAGED_BY: "kuberos", CATALOG_LABEL: "true", COMPONENT: "catalog"},
        },
        "data": {"format": CATALOG_FORMAT, "modules": ", ".join(catalog.names())},
        "binaryData": {"catalog.json.gz": _pack(catalog.to_dict())},
    }


def catalog_of(configmap: dict):
    """The catalog entries kept with a record or a revision ConfigMap (None when it used none)."""
    packed = (configmap.get("binaryData") or {}).get("catalog.json.gz")
    if not packed:
        return None
    from .catalog import Catalog

    return Catalog.from_dict(_unpack(packed))


def parse_revision(configmap: dict):
    """A revision ConfigMap (plain dict): (number, cause, the deployment's RosDeployment, its spec text, catalog)."""
    meta = configmap.get("metadata") or {}
    where = f"ConfigMap {meta.get('namespace', '?')}/{meta.get('name', '?')}"
    data = configmap.get("data") or {}
    try:
        name = data["deployment"]
        catalog = catalog_of(configmap)
        text = spec_text_of(configmap)
        found = list(
            load_rosdeployments(
                text, f"{where} (revision {data.get('revision')})", catalog=catalog, read_file=files_of(configmap)
            )
        )
        dep = next(d for d in found if d.name == name)
        return int(data["revision"]), data.get("cause", ""), dep, text, catalog
    except SpecError:
        raise
    except (KeyError, ValueError, TypeError, OSError, EOFError, StopIteration) as exc:
        raise SpecError([Problem(where, "", f"not a readable KubeROS revision ({exc!r})")]) from None


SCALING_KEY = "scaling.json"


def placement_patch(name: str, namespace: str, placement: Placement, scaling: dict | None = None) -> dict:
    """The controller's update of a record: the placement, that the controller wrote it, and with ``scaling`` the
    changes of scaled modules in progress (``"<deployment>/<module>"`` -> ``ScaleState.to_dict()``)."""
    data = {"writer": WRITER_CONTROLLER}
    if scaling is not None:
        data[SCALING_KEY] = json.dumps(scaling, sort_keys=True)
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": name, "namespace": namespace},
        "data": data,
        "binaryData": {"placement.json.gz": _pack(placement.to_dict())},
    }


def record_placement(configmap: dict) -> Placement:
    """Only the placement of a record ConfigMap (plain dict): what deploy keeps where it runs."""
    meta = configmap.get("metadata") or {}
    try:
        return Placement.from_dict(_unpack((configmap.get("binaryData") or {})["placement.json.gz"]))
    except (KeyError, ValueError, TypeError, OSError, EOFError) as exc:
        where = f"ConfigMap {meta.get('namespace', '?')}/{meta.get('name', '?')}"
        raise SpecError([Problem(where, "", f"not a readable KubeROS record ({exc!r})")]) from None


def pin_live_discovery(record: Record, live: dict) -> None:
    """A fleet's discovery servers are the fleet's: where their live Deployments pin them (``live``, fleet -> servers,
    from ``manifests.discovery_from_deployments``) is the truth for every record of the fleet."""
    for fleet in record.placement.discovery:
        if live.get(fleet):
            record.placement.discovery[fleet] = live[fleet]


def merge_previous(records: list[Placement], discovery: dict) -> Placement:
    """What runs now, for sticky placement: the instances of the records, and the fleets' live discovery servers."""
    return Placement([i for p in records for i in p.instances], dict(discovery), [], [])


@dataclass
class Record:
    name: str
    namespace: str
    deployment: str
    deployments: list[RosDeployment]  # the one this record is about, first; the rest of its file after
    inventory_raw: dict
    inventory: Inventory
    placement: Placement
    options: RenderOptions
    field_manager: str
    resource_version: str = ""
    writer: str = WRITER_DEPLOY
    revision: int = 0
    revision_hash: str = ""
    rollout: dict | None = None  # a rollout in progress: {"revision", "instances", ...}; the controller holds them
    scaling: dict = field(default_factory=dict)  # "<deployment>/<module>" -> a scaled module's change in progress

    @property
    def spec(self) -> RosDeployment:
        return self.deployments[0]


def parse_record(configmap: dict) -> Record:
    """Read a record ConfigMap (as a plain dict); a damaged record raises SpecError naming it."""
    meta = configmap.get("metadata") or {}
    where = f"ConfigMap {meta.get('namespace', '?')}/{meta.get('name', '?')}"
    data = configmap.get("data") or {}
    binary = configmap.get("binaryData") or {}
    try:
        if data.get("format") not in FORMATS_READ:
            raise ValueError(f"format {data.get('format')!r}, expected one of {', '.join(FORMATS_READ)}")
        name = data["deployment"]
        deployments = load_rosdeployments(
            spec_text_of(configmap),
            f"{where} (spec of {data.get('source', '?')})",
            catalog=catalog_of(configmap),
            read_file=files_of(configmap),
        )
        ordered = [d for d in deployments if d.name == name] + [d for d in deployments if d.name != name]
        if not ordered or ordered[0].name != name:
            raise ValueError(f"its spec has no RosDeployment named {name!r}")
        inventory_raw = _unpack(binary["inventory.json.gz"])
        options = json.loads(data["options.json"])
        defaults = RenderOptions()  # a record written before an option existed renders with the option's default
        placement = Placement.from_dict(_unpack(binary["placement.json.gz"]))
        inventory = load_inventory(inventory_raw, f"{where} inventory")
    except SpecError:
        raise
    except (KeyError, ValueError, TypeError, OSError, EOFError) as exc:
        raise SpecError([Problem(where, "", f"not a readable KubeROS record ({exc!r})")]) from None
    return Record(
        name=meta.get("name", ""),
        namespace=meta.get("namespace", ""),
        deployment=name,
        deployments=ordered[:1],
        inventory_raw=inventory_raw,
        inventory=inventory,
        placement=placement,
        options=RenderOptions(
            cluster_domain=options.get("cluster_domain", defaults.cluster_domain),
            discovery_image=options.get("discovery_image", defaults.discovery_image),
            image_pull_policy=options.get("image_pull_policy", defaults.image_pull_policy),
            image_digests=tuple(sorted((options.get("image_digests") or {}).items())),
            **device_options(inventory),
        ),
        field_manager=options.get("field_manager", FIELD_MANAGER),
        resource_version=meta.get("resourceVersion", ""),
        writer=data.get("writer", WRITER_DEPLOY),
        revision=int(data.get("revision") or 0),
        revision_hash=data.get("revision-hash", ""),
        rollout=_rollout_of(data),
        scaling=_json_mapping(data.get(SCALING_KEY)),
    )


ROLLOUT_KEY = "rollout.json"


def _json_mapping(text) -> dict:
    try:
        value = json.loads(text) if text else {}
    except ValueError:
        return {}
    return value if isinstance(value, dict) else {}


def _rollout_of(data: dict) -> dict | None:
    try:
        value = json.loads(data[ROLLOUT_KEY]) if data.get(ROLLOUT_KEY) else None
    except ValueError:
        return None
    return value if isinstance(value, dict) else None
