# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""A control plane's certificate expiry: a thin adapter over module_utils/kuberos_cluster/kubeadm_certificates.py."""

from __future__ import annotations

DOCUMENTATION = r"""
name: kubeadm_cert_expiry
short_description: Each kubeadm certificate's notAfter and days left, before and after a renewal
version_added: 0.3.0
description:
  - Reads C(kubeadm certs check-expiration -o json) (kubeadm's structured output, not its text table).
  - With O(before), the same command's output before a renewal, each row also says what its notAfter was and
    whether it moved later, and C(moved) whether every certificate kubeadm manages moved (authorities are not
    renewed by C(kubeadm certs renew)).
options:
  _input:
    description: kubeadm's standard output.
    type: str
    required: true
  before:
    description: kubeadm's standard output before the renewal.
    type: str
  host:
    description: A host name to head the table's lines with.
    type: str
    default: ""
"""

EXAMPLES = r"""
- name: Report this control plane's certificates
  ansible.builtin.debug:
    msg: "{{ (expiry.stdout | kuberos.platform.kubeadm_cert_expiry(host=inventory_hostname)).lines }}"
"""

RETURN = r"""
_value:
  description: The certificates' expiry.
  type: dict
  contains:
    rows:
      description: >-
        One per certificate and authority: C(name), C(kind) (certificate or authority), C(expires) (RFC 3339, UTC),
        C(residual_days), C(ca), C(externally_managed), C(missing); with O(before) also C(expires_before), C(moved).
      type: list
      elements: dict
    soonest_days:
      description: The fewest whole days any of them has left.
      type: int
    moved:
      description: With O(before), whether every certificate kubeadm manages moved later; else null.
      type: bool
    lines:
      description: The rows as an aligned table.
      type: list
      elements: str
"""

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_cluster import kubeadm_certificates
from ansible_collections.kuberos.platform.plugins.plugin_utils.filter_errors import reports_kuberos_errors


@reports_kuberos_errors
def kubeadm_cert_expiry(text, before=None, host=""):
    result = kubeadm_certificates.expiration(str(text or ""), None if before is None else str(before))
    return {**result, "lines": kubeadm_certificates.table(result, str(host or ""))}


class FilterModule:
    def filters(self):
        return {"kubeadm_cert_expiry": kubeadm_cert_expiry}
