# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""rosdeployment_validate on the controller: the spec file is read where the playbook runs, without shipping a module
(documented in plugins/modules/rosdeployment_validate.py)."""

from __future__ import annotations

import textwrap

from ansible.plugins.action import ActionBase

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.catalog import load_catalog
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.service import load_and_place, load_specs

ARGUMENT_SPEC = {"src": {"type": "path", "required": True}, "catalog": {"type": "path"}, "inventory": {"type": "dict"}}


def validate(src: str, catalog_path: str | None, inventory: dict | None) -> dict:
    """The deployments of the file (and, with an inventory, their placement on an empty cluster); raises KuberosError."""
    catalog = load_catalog(catalog_path) if catalog_path else None
    if inventory is None:
        return {"deployments": [{"name": d.name, "fleet": d.fleet} for d in load_specs(src, catalog=catalog)]}
    deployments, placement = load_and_place(src, inventory, catalog=catalog)
    return {"deployments": [{"name": d.name, "fleet": d.fleet} for d in deployments], "placement": placement.to_dict()}


def failure(exc: KuberosError) -> dict:
    """The headline as msg (Ansible repeats msg in its error line), the problems once, one line each, below it."""
    headline, _sep, rest = str(exc).partition("\n")
    return {"failed": True, "changed": False, "msg": headline.rstrip(":"), "problems": textwrap.dedent(rest) + "\n"}


class ActionModule(ActionBase):
    TRANSFERS_FILES = False
    _requires_connection = False
    _supports_check_mode = True
    _supports_async = False

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        _validation, args = self.validate_argument_spec(argument_spec=ARGUMENT_SPEC)
        try:
            result.update(validate(args["src"], args["catalog"], args["inventory"]), changed=False)
        except KuberosError as exc:
            result.update(failure(exc))
        except OSError as exc:  # the catalog or the spec cannot be read at all
            result.update(failed=True, changed=False, msg=f"cannot read {exc.filename or args['src']}: {exc.strerror or exc}")
        return result
