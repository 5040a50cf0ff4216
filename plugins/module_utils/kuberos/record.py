"""The deployment record: what deploy decided, kept in the cluster for the controller.

Deploy writes one ConfigMap per RosDeployment into the fleet's namespace (``kuberos-record-<name>``)
holding the spec text, the fleet resource model, the render options and the placement. The
controller reads it back, re-places instances when nodes fail or links degrade, and writes the
new placement into it, so a restarted controller (or a second one) continues from the truth in the
cluster rather than from memory. Placement and inventory are gzip-compressed JSON (binaryData):
a 1,000-robot placement is about 1 MB as plain JSON, the size limit of a ConfigMap.

Pure: plain dicts in, plain dicts out.
"""

from __future__ import annotations

import base64
import dataclasses
import gzip
import hashlib
import json
from dataclasses import dataclass

from . import naming
from .errors import Problem, SpecError
from .inventory import Inventory, load_inventory
from .manifests import COMPONENT, DEPLOYMENT, MANAGED_BY, RenderOptions
from .scheduler import Placement
from .spec import RosDeployment, load_rosdeployments

RECORD_LABEL = "kuberos.io/record"
STATUS_LABEL = "kuberos.io/status"
REVISION_LABEL = "kuberos.io/revision"
CATALOG_LABEL = "kuberos.io/catalog"
CATALOG_NAME = "kuberos-catalog"
RECORD_PREFIX = "kuberos-record-"
STATUS_PREFIX = "kuberos-status-"
REVISION_PREFIX = "kuberos-rev-"
REVISION_HISTORY = 10  # revisions kept per deployment (older ones are removed by the prune)
FORMAT = "1"
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


def restrict_placement(placement: Placement, deployment: str) -> Placement:
    """The part of a placement that belongs to one deployment, with its fleet's discovery servers."""
    deps = [d for d in placement.deployments if d["name"] == deployment]
    fleets = {d["fleet"] for d in deps}
    return Placement(
        [i for i in placement.instances if i.deployment == deployment],
        {f: s for f, s in placement.discovery.items() if f in fleets},
        deps,
        [],
    )


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

    ``revisions`` maps a deployment to its record's ``{"revision", "hash"}`` in the cluster; ``catalog`` (a
    ``Catalog``) holds the catalog entries the spec resolved, kept with the record so that it reads back alone."""
    records = []
    for dep in deployments:
        namespace = naming.fleet_namespace(dep.fleet)
        number = next_revision(dep, (revisions or {}).get(dep.name))
        used = catalog.to_dict() if catalog is not None else None
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
                "spec.yaml": spec_text,
                "versions.json": json.dumps(module_versions(dep), sort_keys=True),
            },
        }
        if used:
            revision["binaryData"] = {"catalog.json.gz": _pack(used)}
        records.append(revision)
        records.append(
            {
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
                    "spec.yaml": spec_text,
                    "options.json": json.dumps(
                        {
                            "cluster_domain": options.cluster_domain,
                            "discovery_image": options.discovery_image,
                            "image_pull_policy": options.image_pull_policy,
                            "field_manager": field_manager,
                        },
                        sort_keys=True,
                    ),
                },
                "binaryData": {
                    "inventory.json.gz": _pack(inventory_raw),
                    "placement.json.gz": _pack(restrict_placement(placement, dep.name).to_dict()),
                    **({"catalog.json.gz": _pack(used)} if used else {}),
                },
            }
        )
    return records


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
        "data": {"format": FORMAT, "modules": ", ".join(catalog.names())},
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
        found = [d for d in load_rosdeployments(data["spec.yaml"], f"{where} (revision {data.get('revision')})", catalog=catalog)]
        dep = next(d for d in found if d.name == name)
        return int(data["revision"]), data.get("cause", ""), dep, data["spec.yaml"], catalog
    except SpecError:
        raise
    except (KeyError, ValueError, TypeError, OSError, EOFError, StopIteration) as exc:
        raise SpecError([Problem(where, "", f"not a readable KubeROS revision ({exc!r})")]) from None


def placement_patch(name: str, namespace: str, placement: Placement) -> dict:
    """The controller's update of a record: the placement, and that the controller wrote it."""
    return {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {"name": name, "namespace": namespace},
        "data": {"writer": WRITER_CONTROLLER},
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
        if data.get("format") != FORMAT:
            raise ValueError(f"format {data.get('format')!r}, expected {FORMAT!r}")
        name = data["deployment"]
        deployments = load_rosdeployments(
            data["spec.yaml"], f"{where} (spec of {data.get('source', '?')})", catalog=catalog_of(configmap)
        )
        ordered = [d for d in deployments if d.name == name] + [d for d in deployments if d.name != name]
        if not ordered or ordered[0].name != name:
            raise ValueError(f"its spec has no RosDeployment named {name!r}")
        inventory_raw = _unpack(binary["inventory.json.gz"])
        options = json.loads(data["options.json"])
        placement = Placement.from_dict(_unpack(binary["placement.json.gz"]))
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
        inventory=load_inventory(inventory_raw, f"{where} inventory"),
        placement=placement,
        options=RenderOptions(
            cluster_domain=options.get("cluster_domain", "cluster.local"),
            discovery_image=options.get("discovery_image", "ros:jazzy-ros-base"),
            image_pull_policy=options.get("image_pull_policy", "IfNotPresent"),
        ),
        field_manager=options.get("field_manager", "kuberos"),
        resource_version=meta.get("resourceVersion", ""),
        writer=data.get("writer", WRITER_DEPLOY),
        revision=int(data.get("revision") or 0),
        revision_hash=data.get("revision-hash", ""),
        rollout=_rollout_of(data),
    )


ROLLOUT_KEY = "rollout.json"


def _rollout_of(data: dict) -> dict | None:
    try:
        value = json.loads(data[ROLLOUT_KEY]) if data.get(ROLLOUT_KEY) else None
    except ValueError:
        return None
    return value if isinstance(value, dict) else None
