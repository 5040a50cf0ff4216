"""The repository agrees with itself: published schema, role argument specs, documented variables."""

from __future__ import annotations

import json
import os
import re

import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.schema import SCHEMA

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ROLES = sorted(d for d in os.listdir(os.path.join(ROOT, "roles")) if not d.startswith("."))


def test_published_schema_matches_the_validator():
    with open(os.path.join(ROOT, "docs", "rosdeployment.schema.json"), encoding="utf-8") as handle:
        assert json.load(handle) == json.loads(json.dumps(SCHEMA)), "run `make schema`"


@pytest.mark.parametrize("role", ROLES)
def test_role_argument_specs_match_defaults(role):
    with open(os.path.join(ROOT, "roles", role, "defaults", "main.yml"), encoding="utf-8") as handle:
        defaults = yaml.safe_load(handle) or {}
    with open(os.path.join(ROOT, "roles", role, "meta", "argument_specs.yml"), encoding="utf-8") as handle:
        specs = yaml.safe_load(handle)["argument_specs"]["main"]["options"]
    assert set(defaults) == set(specs)
    assert all(name.startswith(role + "_") for name in defaults), "role variables carry the role's name"


@pytest.mark.parametrize("role", ROLES)
def test_role_readme_lists_every_default(role):
    with open(os.path.join(ROOT, "roles", role, "defaults", "main.yml"), encoding="utf-8") as handle:
        defaults = yaml.safe_load(handle) or {}
    with open(os.path.join(ROOT, "roles", role, "README.md"), encoding="utf-8") as handle:
        readme = handle.read()
    missing = [name for name in defaults if f"`{name}`" not in readme]
    assert not missing, f"roles/{role}/README.md does not document {missing}"


def test_inventory_variables_are_documented():
    with open(os.path.join(ROOT, "docs", "inventory.md"), encoding="utf-8") as handle:
        doc = handle.read()
    source = "".join(
        open(os.path.join(MODULE_UTILS, name), encoding="utf-8").read()
        for name in ("kuberos/inventory.py", "kuberos_cluster/kubeadm_config.py")
    )
    variables = sorted(set(re.findall(r'"(kuberos_[a-z_]+)"', source)))
    assert variables, "inventory.py reads kuberos_* host variables"
    missing = [v for v in variables if f"`{v}`" not in doc]
    assert not missing, f"docs/inventory.md does not document {missing}"


# The layout (docs/architecture.md): inventory + spec -> place -> render -> apply -> reconcile.
MODULE_UTILS = os.path.join(ROOT, "plugins", "module_utils")
PREFIX = "ansible_collections.kuberos.platform.plugins."
CORE = "kuberos"  # the pure deploy core
CLUSTER = "kuberos_cluster"  # the pure cluster-setup models
SITE = "kuberos_site"  # site helpers: the PKI, robot registration, the Ansible inventory read back
DEPLOY = "kuberos_deploy"  # the deploy's I/O: render directories, the cluster's state, deploy, rollout, batch
KUBE = "kuberos_kube"  # the one Kubernetes access layer: clients, the kind table, get/list/apply/delete, errors
ANSIBLE = "kuberos_ansible"  # what the collection's modules share: their Python packages checked, errors as results
CONTROLLER = "kuberos_controller"  # the controller program
BRIDGE = "kuberos_bridge"  # the bridge program
LAB = "kuberos_lab"  # the local lab: control plane, real nodes, images, delay fabric, registry, lab machines
ROS = "kuberos_ros"  # the ROS-level checks run in the cluster: the live graph check's pod
# Which packages of module_utils each may import (besides itself). Nothing but the lab's own modules, the lab's
# two modules (local_cluster, controller_process), the simulator, the benchmarks and the tests import the lab.
MAY_IMPORT = {
    CORE: set(),
    CLUSTER: {CORE},
    SITE: {CORE},
    KUBE: {CORE},
    ANSIBLE: {CORE, KUBE},
    DEPLOY: {CORE, SITE, KUBE, ROS},  # bridge certificates come from the one PKI; the graph check after deploy
    CONTROLLER: {CORE, KUBE, ROS},  # the controller keeps the dashboard's ROS graph current
    ROS: {CORE, KUBE},
    BRIDGE: {SITE},  # its certificates: the one PKI
    LAB: {CORE, CLUSTER, DEPLOY, SITE, KUBE},  # the lab checks what deploy renders; its registry client builds on deploy's
}
LAB_ADAPTERS = ("plugins/modules/local_cluster.py", "plugins/modules/controller_process.py")
PURE = (CORE, CLUSTER)
IMPORT = re.compile(r"^\s*(?:from\s+(\S+)\s+import\s+(\([^)]*\)|[^\n]+)|import\s+(\S+))", re.M)


def _python_files(*parts):
    top = os.path.join(ROOT, *parts)
    for folder, _dirs, files in os.walk(top):
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                with open(path, encoding="utf-8") as handle:
                    yield os.path.relpath(path, ROOT), handle.read()


def _imports(text: str):
    """(module, [names]) of every import statement; relative imports keep their dots."""
    for match in IMPORT.finditer(text):
        if match.group(3):
            yield match.group(3), []
        else:
            names = [n.strip().split(" as ")[0] for n in match.group(2).strip("()").replace("\n", " ").split(",")]
            yield match.group(1), [n for n in names if n and not n.startswith("#")]


def _packages_of(module: str, names: list[str]) -> set:
    """The module_utils packages an absolute import reaches ("loose" for a file of module_utils' own)."""
    if not module.startswith(PREFIX + "module_utils"):
        return set()
    rest = module[len(PREFIX + "module_utils") :].lstrip(".").split(".")[0]
    return {n if n in MAY_IMPORT else "loose" for n in (names if not rest else [rest])}


def _layout_problems(package: str, files) -> tuple[list[str], int]:
    """What ``files`` ((path, text) of ``package``) import against the layout, and how many module_utils imports
    the rule was applied to."""
    found, seen = [], 0
    for path, text in files:
        for module, names in _imports(text):
            if module.startswith("."):  # resolved against the importer's package, so that it cannot escape the rule
                dots = len(module) - len(module.lstrip("."))
                module = ".".join([PREFIX + "module_utils", *([package] if dots == 1 else []), module.lstrip(".")]).rstrip(".")
            if module.startswith(PREFIX) and not module.startswith(PREFIX + "module_utils"):
                found.append(f"{path}: imports {module} (plugins are adapters; module_utils never imports them)")
            reached = _packages_of(module, names)
            seen += bool(reached)
            for other in reached - {package} - MAY_IMPORT[package]:
                found.append(f"{path}: imports {module} ({other}; {package} may import {sorted(MAY_IMPORT[package])})")
    return found, seen


def test_module_utils_has_rooms_and_no_loose_files():
    """Every file of module_utils lives in a named package that the layout rules on."""
    entries = sorted(e for e in os.listdir(MODULE_UTILS) if e != "__pycache__")
    loose = [e for e in entries if e.endswith(".py") and e != "__init__.py"]
    unruled = [e for e in entries if os.path.isdir(os.path.join(MODULE_UTILS, e)) and e not in MAY_IMPORT]
    assert (loose, unruled) == ([], [])
    assert sorted(MAY_IMPORT) == sorted(e for e in entries if os.path.isdir(os.path.join(MODULE_UTILS, e)))


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_packages_import_only_what_the_layout_allows(package):
    found, seen = _layout_problems(package, _python_files("plugins", "module_utils", package))
    assert found == []
    assert seen > 0, f"no module_utils import seen in {package}: has the import prefix changed?"


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_the_layout_check_refuses_a_planted_wrong_import(package):
    """The rule can fail: an import of a package ``package`` may not reach is reported, also written relatively."""
    forbidden = sorted(set(MAY_IMPORT) - MAY_IMPORT[package] - {package})[0]
    planted = [
        (f"plugins/module_utils/{package}/planted.py", f"from {PREFIX}module_utils.{forbidden}.x import y\n"),
        (f"plugins/module_utils/{package}/planted2.py", f"from ..{forbidden} import y\n"),
        (f"plugins/module_utils/{package}/allowed.py", "from . import y\n"),
    ]
    found, seen = _layout_problems(package, planted)
    assert len(found) == 2 and all(forbidden in problem for problem in found), found
    assert seen == 3


def test_only_the_lab_and_its_adapters_import_the_lab():
    found = []
    sources = [*_python_files("plugins")]
    for path, text in sources:
        if path.startswith(f"plugins/module_utils/{LAB}/") or path in LAB_ADAPTERS:
            continue
        for module, names in _imports(text):
            if LAB in _packages_of(module, names):
                found.append(f"{path}: imports {module} (the lab is for the lab's own modules)")
    assert found == []


@pytest.mark.parametrize("package", PURE)
def test_pure_packages_have_no_ansible_or_kubernetes_imports(package):
    for path, text in _python_files("plugins", "module_utils", package):
        assert not re.search(r"^\s*(from|import)\s+(ansible|kubernetes)\b", text, re.M), path


WRITES = re.compile(r"\bopen\([^)]*[\"'][wax]|os\.(fdopen|replace|rename|remove|unlink|makedirs|mkdir|rmdir)\b|tempfile|shutil")


@pytest.mark.parametrize("package", PURE)
def test_pure_packages_write_no_files_and_read_only_through_yaml_source(package):
    """The core reads its input files in one place (yaml_source: bounded, checked) and writes none."""
    for path, text in _python_files("plugins", "module_utils", package):
        assert not WRITES.search(text), f"{path} writes files: that is an I/O helper's work (render_dir.py)"
        if not path.endswith("kuberos/yaml_source.py"):
            assert not re.search(r"\bopen\(|os\.(stat|listdir|walk|scandir)\b", text), f"{path} reads files itself"


def test_adapters_and_the_simulator_use_only_public_names():
    """Filters, modules, the controller and the simulator reach the core through its public functions:
    no underscore names, no filter or module imported from elsewhere, no Ansible internals in the simulator."""
    found = []
    sources = [
        *_python_files("plugins", "filter"),
        *_python_files("plugins", "modules"),
        *_python_files("plugins", "action"),
        *_python_files("plugins", "module_utils", CONTROLLER),
        *_python_files("sim"),
    ]
    for path, text in sources:
        for module, names in _imports(text):
            if module.startswith(PREFIX + "module_utils"):
                private = [n for n in names if n.startswith("_") and n != "__file__"]
                if private:
                    found.append(f"{path}: imports private {private} from {module}")
            if path.startswith("sim/") and (module.startswith(PREFIX + "filter") or module.startswith(PREFIX + "modules")):
                found.append(f"{path}: imports the Ansible plugin {module} (use the core)")
            if path.startswith("sim/") and (module == "ansible" or module.startswith("ansible.")):
                found.append(f"{path}: imports Ansible's {module} (use the core and module_utils' I/O helpers)")
    assert found == []


def test_the_core_imports_pyyaml_and_jsonschema_in_one_place():
    """third_party.py guards them, so that the core imports without them (ansible-test's import check)."""
    for package in PURE:
        for path, text in _python_files("plugins", "module_utils", package):
            if not path.endswith("kuberos/third_party.py"):
                assert not re.search(r"^\s*(from|import)\s+(yaml|jsonschema)\b", text, re.M), path


def test_one_x509_authority_builder():
    """Certificates are built in one place (pki.py): the bridge, the local control plane and the real nodes use it."""
    builders = [path for path, text in _python_files("plugins") if "x509.CertificateBuilder(" in text]
    assert builders == ["plugins/module_utils/kuberos_site/pki.py"]


def test_test_files_have_unique_names():
    """pytest imports test modules by basename here (no packages): two files of one name break collection."""
    names = {}
    for folder, _dirs, files in os.walk(os.path.join(ROOT, "tests")):
        for name in files:
            if name.startswith("test_") and name.endswith(".py"):
                names.setdefault(name, []).append(os.path.relpath(os.path.join(folder, name), ROOT))
    assert {n: p for n, p in names.items() if len(p) > 1} == {}


def test_only_the_collection_link_is_a_tracked_link():
    """A link in git (a .venv, a cache) points at this machine; only .collections' link to the checkout is portable."""
    import subprocess

    listing = subprocess.run(["git", "ls-files", "-s"], cwd=ROOT, capture_output=True, text=True, check=False)
    if listing.returncode != 0:
        pytest.skip("not a git checkout")
    links = sorted(line.split("\t", 1)[1] for line in listing.stdout.splitlines() if line.startswith("120000 "))
    assert links == [".collections/ansible_collections/kuberos/platform"]


def test_nothing_builds_from_sources_outside_the_registries():
    """Every build here takes its sources from a package registry (the Go module proxy, PyPI, Debian, ...): no file
    names a source tree handed in beside the repository (the shared folder's third-party trees)."""
    import subprocess

    listing = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=False)
    if listing.returncode != 0:
        pytest.skip("not a git checkout")
    needle = "/".join(("shared", "third_party")).encode()  # not spelled whole here, so that this file passes
    found = []
    for path in listing.stdout.decode().split("\0"):
        full = os.path.join(ROOT, path)
        if path and os.path.isfile(full) and not os.path.islink(full):
            with open(full, "rb") as handle:
                if needle in handle.read():
                    found.append(path)
    assert found == [], f"these files name a source tree outside the registries: {found}"
