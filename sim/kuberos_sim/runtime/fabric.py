"""The delay fabric lives in the collection (plugins/module_utils/kuberos_lab/delay_fabric.py): the simulator and the local
cluster's real nodes both carry their hosts' packets through it."""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.delay_fabric import *  # noqa: F403
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_lab.delay_fabric import __file__ as SCRIPT  # noqa: F401
