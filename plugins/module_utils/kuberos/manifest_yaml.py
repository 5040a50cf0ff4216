"""Objects as YAML for people to read: block strings, no aliases, keys in the order they were built (pure)."""

from __future__ import annotations

from .third_party import yaml


def _represent_str(dumper: yaml.SafeDumper, data: str):
    style = "|" if "\n" in data and not data.endswith((" ", "\t")) else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", data, style=style)


def _no_alias_dumper(base):
    """Writes repeated values in full: manifests are read by people, not only by parsers."""

    class NoAliasDumper(base):
        def ignore_aliases(self, data):
            return True

    NoAliasDumper.add_representer(str, _represent_str)
    return NoAliasDumper


if yaml is not None:  # without PyYAML (third_party.py) nothing here is used: the modules check for it first
    # libyaml's emitter when PyYAML has it (five times as fast, the same text: test_manifests checks both agree).
    PURE_DUMPER = _no_alias_dumper(yaml.SafeDumper)
    DUMPER = _no_alias_dumper(yaml.CSafeDumper) if getattr(yaml, "__with_libyaml__", False) else PURE_DUMPER


def dump_object(obj: dict, dumper=None) -> str:
    return yaml.dump(obj, Dumper=dumper or DUMPER, sort_keys=False, default_flow_style=False, width=120)
