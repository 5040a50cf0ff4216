"""How the filter plugins report bad input: a KubeROS error becomes an AnsibleFilterError with the
same message (every problem, with file, field and reason), never a traceback."""

from __future__ import annotations

import functools

from ansible.errors import AnsibleFilterError

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError


def reports_kuberos_errors(func):
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except KuberosError as exc:
            raise AnsibleFilterError(str(exc)) from None

    return wrapper
