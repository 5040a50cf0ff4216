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
CONTROLLER = "kuberos_controller"  # the controller program
BRIDGE = "kuberos_bridge"  # the bridge program
LAB = "kuberos_lab"  # the local lab (the registry); nothing outside the lab's own I/O may import it
DEPLOY = "kuberos_deploy"  # the deploy's I/O beyond Kubernetes (registries)
# Which packages of module_utils each may import (besides itself); I/O helpers are module_utils' loose files.
# The lab checks what deploy renders with the core's own models (site_lab: the fleets' NetworkPolicies, pod security).
MAY_IMPORT = {
    CORE: set(),
    CLUSTER: {CORE},
    CONTROLLER: {CORE, "io"},
    BRIDGE: {"io"},
    LAB: {CORE, DEPLOY, "io"},  # the lab's registry client builds on the deploy's registry API
    DEPLOY: {CORE},
}  # the bridge: pki.py
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


def _packages_of(module: str, names: list[str], importer_package: str) -> set:
    """The module_utils packages an import reaches ("io" for the loose I/O helpers); empty outside module_utils."""
    if module.startswith("."):
        return {importer_package}
    if not module.startswith(PREFIX + "module_utils"):
        return set()
    rest = module[len(PREFIX + "module_utils") :].lstrip(".").split(".")[0]
    return {n if n in MAY_IMPORT else "io" for n in (names if not rest else [rest])}


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_packages_import_only_what_the_layout_allows(package):
    found = []
    for path, text in _python_files("plugins", "module_utils", package):
        for module, names in _imports(text):
            if module.startswith(PREFIX) and not module.startswith(PREFIX + "module_utils"):
                found.append(f"{path}: imports {module} (plugins are adapters; module_utils never imports them)")
            for reached in _packages_of(module, names, package) - {package} - MAY_IMPORT[package]:
                found.append(f"{path}: imports {module} ({reached}; {package} may import {sorted(MAY_IMPORT[package])})")
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
    assert builders == ["plugins/module_utils/pki.py"]


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
