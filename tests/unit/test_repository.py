"""The repository agrees with itself: published schema, role argument specs, documented variables."""

from __future__ import annotations

import json
import os

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
    core = os.path.join(ROOT, "plugins", "module_utils", "kuberos")
    source = "".join(open(os.path.join(core, name), encoding="utf-8").read() for name in ("inventory.py", "kubeadm_config.py"))
    import re

    variables = sorted(set(re.findall(r'"(kuberos_[a-z_]+)"', source)))
    assert variables, "inventory.py reads kuberos_* host variables"
    missing = [v for v in variables if f"`{v}`" not in doc]
    assert not missing, f"docs/inventory.md does not document {missing}"


def test_pure_core_has_no_ansible_or_kubernetes_imports():
    import re

    core = os.path.join(ROOT, "plugins", "module_utils", "kuberos")
    for name in sorted(os.listdir(core)):
        if name.endswith(".py"):
            with open(os.path.join(core, name), encoding="utf-8") as handle:
                text = handle.read()
            assert not re.search(r"^\s*(from|import)\s+(ansible|kubernetes)\b", text, re.M), name


def test_the_core_imports_pyyaml_and_jsonschema_in_one_place():
    """third_party.py guards them, so that the core imports without them (ansible-test's import check)."""
    import re

    core = os.path.join(ROOT, "plugins", "module_utils", "kuberos")
    for name in sorted(os.listdir(core)):
        if name.endswith(".py") and name != "third_party.py":
            with open(os.path.join(core, name), encoding="utf-8") as handle:
                text = handle.read()
            assert not re.search(r"^\s*(from|import)\s+(yaml|jsonschema)\b", text, re.M), name


def test_test_files_have_unique_names():
    """pytest imports test modules by basename here (no packages): two files of one name break collection."""
    names = {}
    for folder, _dirs, files in os.walk(os.path.join(ROOT, "tests")):
        for name in files:
            if name.startswith("test_") and name.endswith(".py"):
                names.setdefault(name, []).append(os.path.relpath(os.path.join(folder, name), ROOT))
    assert {n: p for n, p in names.items() if len(p) > 1} == {}
