"""The render directory: one YAML file per object, written only when changed (an I/O helper of the deploy).

No Ansible: ``plan_render_dir`` says what would change; ``apply_plan`` does it.
A directory is only pruned when it carries the marker file KubeROS writes, so that pointing
the render directory at an unrelated folder never deletes anything.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifest_yaml import dump_object
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.files import text_or_none

MARKER = ".kuberos-render"
MANIFEST_DIR = "manifests"
CLUSTERS_DIR = "clusters"  # manifests for third-party clusters, one folder each
PRUNED_DIRS = (MANIFEST_DIR, CLUSTERS_DIR)


def object_path(obj: dict) -> str:
    namespace = obj["metadata"].get("namespace") or "_cluster"
    return os.path.join(MANIFEST_DIR, namespace, f"{obj['kind'].lower()}-{obj['metadata']['name']}.yaml")


@dataclass
class RenderPlan:
    root: str
    files: dict[str, str] = field(default_factory=dict)  # relative path -> desired text
    before: dict[str, str] = field(default_factory=dict)  # relative path -> current text (changed files only)
    created: list[str] = field(default_factory=list)
    updated: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)

    @property
    def changed(self) -> bool:
        return bool(self.created or self.updated or self.removed)

    def diff(self) -> list[dict]:
        out = []
        for rel in sorted(self.created + self.updated + self.removed):
            out.append(
                {
                    "before_header": rel if rel not in self.created else "/dev/null",
                    "after_header": rel if rel not in self.removed else "/dev/null",
                    "before": self.before.get(rel, ""),
                    "after": self.files.get(rel, ""),
                }
            )
        return out


class RenderDirError(KuberosError):
    """The render directory cannot be written as planned; the message says which file and why."""


def plan_render_dir(
    root: str, objects: list[dict], placement: dict, table: str, picture: str = "", remote: dict[str, list[dict]] | None = None
) -> RenderPlan:
    """What to write under ``root``: one file per object in manifests/, one per object of each third-party cluster
    in clusters/<cluster>/, the placement in three forms; files no longer rendered in those folders go."""
    files = {"placement.json": json.dumps(placement, indent=2, sort_keys=True) + "\n", "placement.txt": table + "\n"}
    if picture:
        files["placement.svg"] = picture
    return plan_files(root, objects, files, remote)


def plan_files(root: str, objects: list[dict], files: dict[str, str], remote: dict[str, list[dict]] | None = None) -> RenderPlan:
    """``plan_render_dir`` with other files beside the manifests (``files``: relative path -> text): a batch job's
    plan, for one."""
    root = os.path.abspath(root)
    if os.path.isdir(root) and os.listdir(root) and not os.path.exists(os.path.join(root, MARKER)):
        raise RenderDirError(
            f"{root} exists, is not empty and was not written by KubeROS (no {MARKER} file); "
            "choose an empty or new render directory"
        )
    plan = RenderPlan(root)
    for obj in objects:
        rel = object_path(obj)
        if rel in plan.files:
            raise RenderDirError(f"two objects render to the same file {rel}")
        plan.files[rel] = dump_object(obj)
    for cluster, cluster_objects in sorted((remote or {}).items()):
        for obj in cluster_objects:
            plan.files[os.path.join(CLUSTERS_DIR, cluster, object_path(obj))] = dump_object(obj)
    plan.files.update(files)
    plan.files[MARKER] = "Rendered by the kuberos.platform collection; files here are replaced on every render.\n"
    for rel, text in sorted(plan.files.items()):
        current = text_or_none(os.path.join(root, rel))
        if current is None:
            plan.created.append(rel)
        elif current != text:
            plan.updated.append(rel)
            plan.before[rel] = current
    for folder in PRUNED_DIRS:
        for dirpath, _dirs, names in os.walk(os.path.join(root, folder)):
            for name in names:
                rel = os.path.relpath(os.path.join(dirpath, name), root)
                if rel not in plan.files:
                    plan.removed.append(rel)
                    plan.before[rel] = text_or_none(os.path.join(root, rel)) or ""
    plan.removed.sort()
    return plan


def apply_plan(plan: RenderPlan) -> None:
    for rel in plan.created + plan.updated:
        path = os.path.join(plan.root, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=".tmp-")
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(plan.files[rel])
        os.replace(tmp, path)
    for rel in plan.removed:
        os.remove(os.path.join(plan.root, rel))
    for folder in PRUNED_DIRS:
        top = os.path.join(plan.root, folder)
        for dirpath, _dirs, _names in sorted(os.walk(top), reverse=True):
            if not os.listdir(dirpath) and dirpath != top:
                os.rmdir(dirpath)
