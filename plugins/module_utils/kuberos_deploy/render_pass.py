"""Rendering a placed RosDeployment into its render directory (manifests, placement, picture, the bridges' TLS
Secrets), shared by the ``rosdeployment_render`` and ``rosdeployment`` modules. The objects come from the pure core
(``kuberos/manifests.py``, ``kuberos/record.py``); this file writes the files."""

from __future__ import annotations

from dataclasses import replace

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import naming
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, Problem, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import (
    bridge_secret_name,
    device_options,
    launch_argument_problems,
    object_order,
    render_deployment,
    render_remote,
)
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement import Placement
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.placement_map import render_placement_svg
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import build_records, catalog_configmap
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import placement_table
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_args import render_options
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.render_dir import apply_plan, plan_render_dir


def bridge_secrets(dest: str, placement: Placement, check_mode: bool) -> list[dict]:
    """Certificates of every bridge, made once and kept in dest/tls; Secret manifests for both ends beside them.
    Each entry names the cluster a Secret goes to ('' for this one), its bridge, its file and the Secret itself
    (``secret``; None in check mode before its certificates exist), which the deploy applies as it is."""
    import base64
    import os

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.labels import COMPONENT, DEPLOYMENT, FLEET, MANAGED_BY
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifest_yaml import dump_object
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.naming import BRIDGE_CLIENT
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.bridge_certs import generate_certificates

    files = []
    for fleet, bridges in sorted(placement.bridges.items()):
        for bridge in bridges:
            folder = os.path.join(dest, "tls", fleet, bridge.cluster)
            first = next(i.deployment for i in placement.instances if i.cluster == bridge.cluster and i.fleet == fleet)
            server = {"cluster": "", "bridge": bridge.cluster, "path": os.path.join(folder, "secret-server.yaml"), "secret": None}
            client = {"cluster": bridge.cluster, "bridge": bridge.cluster, "path": os.path.join(folder, "secret-client.yaml"),
                      "secret": None}  # fmt: skip
            files += [server, client]
            names = ("ca.crt", "server.crt", "server.key", "client.crt", "client.key")
            if not all(os.path.exists(os.path.join(folder, n)) for n in names):
                if check_mode:
                    continue
                os.makedirs(folder, mode=0o700, exist_ok=True)
                generate_certificates(folder, bridge.name)

            def read(name, folder=folder):
                with open(os.path.join(folder, name), "rb") as handle:
                    return base64.b64encode(handle.read()).decode()

            for entry, side, secret_name, cert, key in (
                (server, "server", bridge_secret_name(bridge.name), "server.crt", "server.key"),
                (client, "client", bridge_secret_name(BRIDGE_CLIENT), "client.crt", "client.key"),
            ):
                secret = {
                    "apiVersion": "v1",
                    "kind": "Secret",
                    "type": "kubernetes.io/tls",
                    "metadata": {
                        "name": secret_name,
                        "namespace": bridge.namespace,
                        "labels": {
                            MANAGED_BY: "kuberos",
                            COMPONENT: f"bridge-{side}",
                            FLEET: bridge.fleet,
                            DEPLOYMENT: first,
                        },
                    },
                    "data": {"tls.crt": read(cert), "tls.key": read(key), "ca.crt": read("ca.crt")},
                }
                entry["secret"] = secret
                if not check_mode:
                    fd = os.open(entry["path"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                    with os.fdopen(fd, "w", encoding="utf-8") as handle:
                        handle.write(dump_object(secret))
    return files


def render_to_dir(
    params: dict,
    deployments,
    placement: Placement,
    catalog,
    check_mode: bool,
    revisions=None,
    spec_text=None,
    clusters=None,
    model=None,
) -> dict:
    """Render ``deployments`` as ``placement`` places them into ``params["dest"]`` (written unless ``check_mode``).

    ``params`` holds the render options (``render_args.RENDER_ARGS``), ``src``, ``dest``, ``inventory`` (raw, for the
    records; None renders no record) and ``field_manager``. ``spec_text`` is the spec file's text when the caller has
    read it already; ``clusters`` the inventory's third-party clusters (``Inventory.clusters``); ``model`` the inventory's
    model when the caller has it (else it is read from ``params["inventory"]``), for the nodes' device parameters."""
    options = render_options(params)
    if model is None and params["inventory"] is not None:
        model = load_inventory(params["inventory"])
    if model is not None:
        options = replace(options, **device_options(model))
    missing = launch_argument_problems(deployments, placement, options)
    if missing:
        raise SpecError(
            [
                Problem(
                    "inventory",
                    f"node {node}.kuberos_device_parameters.{device}",
                    f"has no parameter {parameter!r}, which launch argument {argument} of module {module} "
                    f"(deployment {deployment}) takes; expected it in the node's kuberos_device_parameters",
                )
                for deployment, module, node, argument, device, parameter in missing
            ],
            title="a launch argument takes a device parameter the inventory does not give",
        )
    objects = render_deployment(deployments, placement, options)
    remote = {}
    if placement.bridges:
        if clusters is None:
            raise KuberosError("modules in third-party clusters need the inventory (the inventory option) to render")
        remote = render_remote(deployments, placement, clusters, options)
    if params["inventory"] is not None:
        if spec_text is None:
            with open(params["src"], encoding="utf-8") as handle:
                spec_text = handle.read()
        used = (
            catalog.subset((m.catalog_module, m.version) for d in deployments for m in d.modules if m.version)
            if catalog
            else None
        )
        records = build_records(
            spec_text, params["src"], deployments, placement, params["inventory"], options, params["field_manager"],
            revisions or {}, used,
        )  # fmt: skip
        if catalog is not None and not catalog.missing:
            records += [catalog_configmap(ns, catalog) for ns in sorted({naming.fleet_namespace(d.fleet) for d in deployments})]
        objects = sorted(objects + records, key=object_order)
    table = placement_table(placement)
    plan = plan_render_dir(params["dest"], objects, placement.to_dict(), table, render_placement_svg(placement), remote)
    if plan.changed and not check_mode:
        apply_plan(plan)
    secrets = bridge_secrets(plan.root, placement, check_mode) if placement.bridges else []
    others = [o for o in objects if o["kind"] != "Namespace"]
    return {
        "changed": plan.changed,
        "plan": plan,
        "objects": objects,
        "namespaces": [o for o in objects if o["kind"] == "Namespace"],
        "apply_objects": others,
        "object_refs": [
            {"apiVersion": o["apiVersion"], "kind": o["kind"], "metadata": {k: o["metadata"][k] for k in ("name", "namespace")}}
            for o in others
        ]
        + [  # the bridge servers' TLS Secrets, applied from their files
            {"apiVersion": "v1", "kind": "Secret", "metadata": {"name": bridge_secret_name(b.name), "namespace": b.namespace}}
            for bridges in placement.bridges.values()
            for b in bridges
        ],
        "remote": {
            cluster: {
                "namespaces": [o for o in cluster_objects if o["kind"] == "Namespace"],
                "apply_objects": [o for o in cluster_objects if o["kind"] != "Namespace"],
            }
            for cluster, cluster_objects in remote.items()
        },
        "secret_files": [{k: v for k, v in entry.items() if k != "secret"} for entry in secrets],
        "secrets": secrets,  # with the Secrets themselves, for the deploy (never in a module's result: keys)
        "table": table,
        "dest": plan.root,
        "files": {"created": plan.created, "updated": plan.updated, "removed": plan.removed},
    }
