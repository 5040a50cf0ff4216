"""Without PyYAML, jsonschema, grpcio and protobuf every module and module_utils file still imports (ansible-test's
import check, a Python that lacks them); the modules then fail with missing_required_lib, the core with
MissingPackage (a KuberosError that the filters report like bad input)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

from helpers import ROOT

PLUGINS = os.path.join(ROOT, "plugins")
GENERATED = {"bridge_pb2", "bridge_pb2_grpc"}  # grpc_tools.protoc's code imports its libraries unguarded

# Runs in a fresh interpreter where importing the four packages fails as if they were not installed.
PROBE = textwrap.dedent(
    """
    import importlib, json, sys
    BLOCKED = ("yaml", "jsonschema", "grpc", "google.protobuf")

    class Blocker:
        def find_spec(self, name, path=None, target=None):
            if any(name == b or name.startswith(b + ".") for b in BLOCKED):
                raise ImportError(f"No module named {name!r} (blocked)")

    sys.meta_path.insert(0, Blocker())
    failed = {}
    for name in json.loads(sys.argv[1]):
        try:
            importlib.import_module(name)
        except Exception as exc:
            failed[name] = repr(exc)

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import third_party, validation
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_ansible.python_packages import require_packages

    try:
        validation.strict_validator({})
        raised = None
    except third_party.MissingPackage as exc:
        raised = str(exc)
    except Exception as exc:
        raised = "not MissingPackage: " + repr(exc)

    class Module:
        def fail_json(self, **result):
            print(json.dumps({"failed": failed, "missing": sorted(third_party.IMPORT_ERRORS), "raised": raised,
                              "fail_json": result["msg"]}))
            sys.exit(0)

    require_packages(Module())
    print(json.dumps({"failed": failed, "missing": sorted(third_party.IMPORT_ERRORS), "raised": raised}))
    """
)


def module_names() -> list[str]:
    names = []
    for folder in ("modules", "module_utils", "plugin_utils", "filter"):  # not action/: Ansible's own plugins need PyYAML
        for directory, _subdirectories, files in os.walk(os.path.join(PLUGINS, folder)):
            for name in sorted(files):
                stem = name[:-3]
                if name.endswith(".py") and stem not in GENERATED and stem != "__main__":
                    relative = os.path.relpath(os.path.join(directory, stem), PLUGINS).replace(os.sep, ".")
                    names.append(f"ansible_collections.kuberos.platform.plugins.{relative}".removesuffix(".__init__"))
    return names


def test_everything_imports_without_the_third_party_packages_and_says_what_is_missing():
    env = dict(os.environ, PYTHONPATH=os.path.join(ROOT, ".collections"))
    command = [sys.executable, "-c", PROBE, json.dumps(module_names())]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, env=env, check=False)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout.splitlines()[-1])
    assert result["failed"] == {}
    assert result["missing"] == ["PyYAML", "jsonschema"]
    # The spec's and the catalog's validators, built on first use, name the package (not an AttributeError on None).
    assert result["raised"].startswith("the Python package jsonschema is needed and not installed for ")
    assert "pip install jsonschema" in result["raised"]
    assert result["fail_json"].startswith("Failed to import the required Python library (PyYAML)")
