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
import gzip
import json
from dataclasses import dataclass

from . import naming
from .errors import Problem, SpecError
from .inventory import Inventory, load_inventory
from .manifests import DEPLOYMENT, MANAGED_BY, RenderOptions
from .scheduler import Placement
from .spec import RosDeployment, load_rosdeployments

RECORD_LABEL = "kuberos.io/record"
STATUS_LABEL = "kuberos.io/status"
RECORD_PREFIX = "kuberos-record-"
STATUS_PREFIX = "kuberos-status-"
FORMAT = "1"
# Who wrote the placement last. The controller re-pins Deployments only to finish its own moves: while
# deploy is applying a placement it wrote, the Deployments are deploy's to change.
WRITER_DEPLOY = "deploy"
WRITER_CONTROLLER = "controller"


def record_name(deployment: str) -> str:
    return naming.dns_label(RECORD_PREFIX + deployment, max_len=253)


def status_name(deployment: str) -> str:
    return naming.dns_label(STATUS_PREFIX + deployment, max_len=253)


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
) -> list[dict]:
    """One record ConfigMap per deployment, ready for server-side apply."""
    records = []
    for dep in deployments:
        namespace = naming.fleet_namespace(dep.fleet)
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
                },
            }
        )
    return records


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
        deployments = load_rosdeployments(data["spec.yaml"], f"{where} (spec of {data.get('source', '?')})")
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
    )
