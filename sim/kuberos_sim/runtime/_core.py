"""The collection's pure core (plugins/module_utils/kuberos), importable from a checkout.

The simulator lives beside the collection (sim/), not inside it; when ``ansible_collections`` is not on the
path already (an installed collection, pytest's pythonpath), the checkout's ``.collections`` link tree is used.
"""

from __future__ import annotations

import os
import sys

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
SIM_DIR = os.path.join(REPO_ROOT, "sim")
COLLECTIONS_DIR = os.path.join(REPO_ROOT, ".collections")

try:
    import ansible_collections.kuberos.platform.plugins.module_utils.kuberos  # noqa: F401
except ImportError:
    sys.path.insert(0, COLLECTIONS_DIR)

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import inventory, labels, manifests, naming  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError  # noqa: E402
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab import ros_wheels  # noqa: E402

__all__ = [
    "COLLECTIONS_DIR",
    "REPO_ROOT",
    "SIM_DIR",
    "Problem",
    "SpecError",
    "inventory",
    "labels",
    "manifests",
    "naming",
    "ros_wheels",
]
