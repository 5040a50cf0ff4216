# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""The label changes in the result of a kubernetes.core.k8s batch, one line per node."""

from __future__ import annotations

DOCUMENTATION = r"""
name: label_changes
short_description: What a kubernetes.core.k8s batch changed in each object's labels
version_added: 0.1.0
description:
  - Takes the registered result of P(kubernetes.core.k8s#module) run with C(--diff) over a list of objects and
    returns, for each changed object, the labels set (with their new values) and the labels removed, leaving out
    the bookkeeping (managedFields, resourceVersion) that a full object diff is full of.
options:
  _input:
    description: The registered result of P(kubernetes.core.k8s#module).
    type: dict
    required: true
"""

EXAMPLES = r"""
- name: Show the label changes
  ansible.builtin.debug:
    msg: "{{ applied | kuberos.platform.label_changes }}"
  when: ansible_diff_mode
"""

RETURN = r"""
_value:
  description: One C({name, set, removed}) per changed object.
  type: list
  elements: dict
"""


def _labels(side):
    return ((side or {}).get("metadata") or {}).get("labels") or {}


def label_changes(result):
    results = (result.get("result") or {}).get("results") if isinstance(result, dict) else None
    changes = []
    for item in results if results is not None else [result]:
        if not isinstance(item, dict) or not item.get("changed"):
            continue
        diff = item.get("diff") or {}
        before, after = _labels(diff.get("before")), _labels(diff.get("after"))
        name = ((item.get("result") or {}).get("metadata") or {}).get("name")
        changes.append(
            {
                "name": name,
                "set": {k: v for k, v in sorted(after.items()) if before.get(k) != v},
                "removed": sorted(k for k in before if k not in after),
            }
        )
    return changes


class FilterModule:
    def filters(self):
        return {"label_changes": label_changes}
