"""The core's third-party Python packages, PyYAML and jsonschema, imported here and nowhere else in the core.

The core must import without them: ansible-test's import check loads every module_utils file where only the
standard library and Ansible are installed, and a module may run under a Python that lacks them. A missing package
leaves its name ``None`` and its import error in ``IMPORT_ERRORS``. The modules check the packages they need before
any work (module_utils/kuberos_ansible/python_packages.py: Ansible's missing_required_lib message); ``require`` raises
``MissingPackage``, a KuberosError that the filters report like bad input, where the controller may lack one
(jsonschema: Ansible itself needs PyYAML).
"""

from __future__ import annotations

import sys
import traceback

from .errors import KuberosError

__all__ = ["IMPORT_ERRORS", "MissingPackage", "jsonschema", "require", "yaml"]

# The pip package of each guarded import that failed -> the traceback of the failure.
IMPORT_ERRORS: dict[str, str] = {}

try:
    import yaml
except ImportError:
    yaml = None
    IMPORT_ERRORS["PyYAML"] = traceback.format_exc()

try:
    import jsonschema
except ImportError:
    jsonschema = None
    IMPORT_ERRORS["jsonschema"] = traceback.format_exc()


class MissingPackage(KuberosError):
    """A Python package the core needs is not installed for the Python that runs it."""

    def __init__(self, package: str):
        self.package = package
        super().__init__(f"the Python package {package} is needed and not installed for {sys.executable} (pip install {package})")


def require(package: str) -> None:
    """Raise ``MissingPackage`` unless ``package`` (its pip name) was imported."""
    if package in IMPORT_ERRORS:
        raise MissingPackage(package)
