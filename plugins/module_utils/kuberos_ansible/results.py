"""How every module of the collection turns an error of its work into its failed result, one way.

A KubeROS error (a spec, an inventory, a render directory, a rollout in progress, a registration: every
``KuberosError``) gives its headline as ``msg``, which Ansible repeats in its error line, and its problems once, one
line each, in ``problems``. Anything else is a failure to talk to a cluster, said in one sentence
(``kuberos_kube.api.message``): unreachable, refused, or what the API server said. No traceback either way.
"""

from __future__ import annotations

import textwrap

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import message


def failure(exc: BaseException, kubeconfig: str = "") -> dict:
    """``fail_json``'s ``msg`` (and ``problems``) for ``exc``; ``kubeconfig`` names the cluster in a cluster's failure."""
    if isinstance(exc, KuberosError):
        headline, _sep, rest = str(exc).partition("\n")
        return {"msg": headline.rstrip(":"), **({"problems": textwrap.dedent(rest) + "\n"} if rest.strip() else {})}
    return {"msg": message(exc, kubeconfig)}


def fail(module, exc: BaseException, kubeconfig: str = "", **result) -> None:
    """End ``module`` with the failed result of ``exc`` and what ``result`` adds (progress, what was removed, ...)."""
    module.fail_json(**failure(exc, kubeconfig), **result)
