"""Objects as YAML for people to read: block strings, no aliases, keys in the order they were built (pure)."""

from __future__ import annotations

from .third_party import yaml


def _represent_str(dumper: yaml.SafeDumper, data: str):
    style = "|" if "\n" in data and not data.endswith((" ", "\t")) else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style=style)


if yaml is not None:  # without PyYAML (third_party.py) nothing here is used: the modules check for it first

    class _NoAliasDumper(yaml.SafeDumper):
        """Writes repeated values in full: manifests are read by people, not only by parsers."""

        def ignore_aliases(self, data):
            return True

    _NoAliasDumper.add_representer(str, _represent_str)


def dump_object(obj: dict) -> str:
    return yaml.dump(obj, Dumper=_NoAliasDumper, sort_keys=False, default_flow_style=False, width=120)
