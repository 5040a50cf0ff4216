"""The control planes' certificate expiry (kuberos_cluster/kubeadm_certificates.py, filter kubeadm_cert_expiry), read
from what the real kubeadm v1.34.4 printed: `kubeadm certs check-expiration -o json` on a control plane's PKI made by
`kubeadm init phase certs all` and `kubeconfig all`, before and after `kubeadm certs renew all` a minute later
(tests/unit/data/kubeadm/)."""

from __future__ import annotations

import json
import os

import pytest
from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.filter.kubeadm_cert_expiry import kubeadm_cert_expiry

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "kubeadm")
RENEWED = [
    "admin.conf", "apiserver", "apiserver-etcd-client", "apiserver-kubelet-client", "controller-manager.conf",
    "etcd-healthcheck-client", "etcd-peer", "etcd-server", "front-proxy-client", "scheduler.conf", "super-admin.conf",
]  # fmt: skip


def _read(name: str) -> str:
    with open(os.path.join(DATA, name), encoding="utf-8") as handle:
        return handle.read()


BEFORE, AFTER = _read("check-expiration-before.json"), _read("check-expiration-after.json")


def test_each_certificate_and_authority_is_a_row_with_its_expiry_and_days_left():
    result = kubeadm_cert_expiry(BEFORE)
    rows = {(row["kind"], row["name"]): row for row in result["rows"]}
    assert [name for kind, name in rows if kind == "certificate"] == RENEWED
    assert [name for kind, name in rows if kind == "authority"] == ["ca", "etcd-ca", "front-proxy-ca"]
    apiserver = rows[("certificate", "apiserver")]
    assert apiserver == {"name": "apiserver", "kind": "certificate", "expires": "2027-12-07T03:49:25Z", "residual_days": 364,
                         "ca": "ca", "externally_managed": False, "missing": False}  # fmt: skip
    assert rows[("authority", "ca")]["residual_days"] == 3649 and result["soonest_days"] == 364 and result["moved"] is None
    lines = kubeadm_cert_expiry(BEFORE, host="edge-a")["lines"]
    assert lines[0] == "edge-a:" and lines[1].split() == ["CERTIFICATE", "EXPIRES", "RESIDUAL", "DAYS"]
    assert lines[3].split() == ["apiserver", "2027-12-07T03:49:25Z", "364"]
    assert lines[-1].split()[:2] == ["front-proxy-ca", "(CA)"]


def test_after_a_renewal_every_managed_certificate_moved_and_the_authorities_did_not():
    result = kubeadm_cert_expiry(AFTER, before=BEFORE, host="edge-a")
    moved = {row["name"]: row["moved"] for row in result["rows"]}
    assert all(moved[name] for name in RENEWED) and not any(moved[name] for name in ("ca", "etcd-ca", "front-proxy-ca"))
    apiserver = next(row for row in result["rows"] if row["name"] == "apiserver")
    assert (apiserver["expires_before"], apiserver["expires"]) == ("2027-12-07T03:49:25Z", "2027-12-07T03:50:27Z")
    assert result["moved"] is True
    assert result["lines"][1].split() == ["CERTIFICATE", "EXPIRES", "RESIDUAL", "DAYS", "BEFORE", "RENEWAL", "MOVED"]
    assert result["lines"][3].split() == ["apiserver", "2027-12-07T03:50:27Z", "364", "2027-12-07T03:49:25Z", "yes"]
    # the same output twice: nothing moved
    assert kubeadm_cert_expiry(BEFORE, before=BEFORE)["moved"] is False


def test_missing_expired_and_externally_managed_certificates():
    info = json.loads(BEFORE)
    info["certificates"][0] = {"name": "admin.conf", "expirationDate": None, "residualTime": 0, "externallyManaged": False,
                               "missing": True}  # fmt: skip
    info["certificates"][1]["residualTime"] = -3 * 86400 - 5  # expired three days ago
    info["certificates"][2]["externallyManaged"] = True
    result = kubeadm_cert_expiry(json.dumps(info), host="edge-b")
    rows = {row["name"]: row for row in result["rows"]}
    assert rows["admin.conf"]["missing"] and rows["admin.conf"]["residual_days"] is None and rows["admin.conf"]["expires"] == ""
    assert rows["apiserver"]["residual_days"] == -4 and result["soonest_days"] == -4
    assert "MISSING" in next(line for line in result["lines"] if "admin.conf" in line)
    # an externally managed certificate is not expected to move; a missing one cannot
    after = json.loads(AFTER)
    after["certificates"][0] = info["certificates"][0]
    after["certificates"][2]["externallyManaged"] = True
    after["certificates"][2]["expirationDate"] = info["certificates"][2]["expirationDate"]
    assert kubeadm_cert_expiry(json.dumps(after), before=json.dumps(info))["moved"] is True


@pytest.mark.parametrize("text", ["", "CERTIFICATE   EXPIRES\nadmin.conf   Dec 07, 2027", '{"kind": "Status"}', "{not json"])
def test_anything_but_kubeadms_json_is_refused(text):
    with pytest.raises(AnsibleFilterError, match="not kubeadm's JSON expiration info"):
        kubeadm_cert_expiry(text)
