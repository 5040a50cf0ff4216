"""The modules' check of the Python packages the core needs (kuberos/third_party.py), before any work: Ansible's
missing_required_lib message (which package, for which Python, how to install it) instead of a traceback."""

from __future__ import annotations

from ansible.module_utils.basic import missing_required_lib

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.third_party import IMPORT_ERRORS

CORE_PACKAGES = ("PyYAML", "jsonschema")


def require_packages(module, packages=CORE_PACKAGES) -> None:
    """Fail ``module`` when one of ``packages`` (pip names) could not be imported."""
    for package in packages:
        if package in IMPORT_ERRORS:
            module.fail_json(msg=missing_required_lib(package), exception=IMPORT_ERRORS[package])
