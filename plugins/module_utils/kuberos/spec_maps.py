"""Parameter maps of a spec (``parameterMaps``): their content inline or read from files beside the spec, checked."""

from __future__ import annotations

from .errors import Problem, SpecError, describe
from .spec_model import ParameterMap, _env_value, _problem
from .third_party import yaml
from .yaml_source import Document, format_path, load_documents


def _broken(broken: set, prefix: str) -> bool:
    return any(path == prefix or path.startswith(prefix + ".") or path.startswith(prefix + "[") for path in broken)


def _map_content(raw: dict, parts: tuple, doc: Document, read_file, problems: list[Problem], files: list):
    """A parameter map's data: inline, or the YAML file ``path`` names (read with ``read_file``)."""
    if ("data" in raw) == ("path" in raw):
        problems.append(_problem(doc, parts, "needs data (the map inline) or path (a file), one of the two"))
        return None, ""
    if "data" in raw:
        return raw["data"], ""
    if read_file is None:
        problems.append(_problem(doc, (*parts, "path"), "files cannot be read here (the spec has no directory); give data"))
        return None, ""
    try:
        display, text = read_file(raw["path"])
        documents = [d for d in load_documents(text, display) if d.data is not None]
    except SpecError as exc:
        problems.append(_problem(doc, (*parts, "path"), f"cannot be used: {exc.problems[0].message} ({exc.problems[0].source})"))
        return None, ""
    if len(documents) != 1 or not isinstance(documents[0].data, dict):
        problems.append(_problem(doc, (*parts, "path"), f"{display} does not hold one YAML mapping; expected a parameter file"))
        return None, ""
    files.append((raw["path"], text))
    return documents[0].data, text


def _parameter_maps(
    data: dict, doc: Document, broken: set, read_file, problems: list[Problem], files: list, unreadable: set
) -> dict:
    maps: dict[str, ParameterMap] = {}
    for index, raw in enumerate(data.get("parameterMaps") or ()):
        parts = ("parameterMaps", index)
        if _broken(broken, format_path(parts)):
            continue
        if raw["name"] in maps:
            problems.append(_problem(doc, (*parts, "name"), f"'{raw['name']}' is already a parameter map; expected unique names"))
            continue
        content, text = _map_content(raw, parts, doc, read_file, problems, files)
        if content is None:
            unreadable.add(raw["name"])
            continue
        if raw["type"] == "yaml":
            text = text or yaml.safe_dump(content, sort_keys=False, default_flow_style=False)
            maps[raw["name"]] = ParameterMap(raw["name"], "yaml", text=text, path=raw.get("path", ""))
            continue
        bad = [k for k, v in content.items() if not isinstance(k, str) or not k or not isinstance(v, (str, int, float, bool))]
        if bad:
            problems.append(
                _problem(
                    doc, parts, f"key-value map has {describe(bad[0])} with a value that is no text, number or boolean; "
                    "expected flat key: value pairs (a yaml map holds nested parameters)",
                )
            )  # fmt: skip
            continue
        values = tuple((k, _env_value(v)) for k, v in content.items())
        maps[raw["name"]] = ParameterMap(raw["name"], "key-value", values=values, path=raw.get("path", ""))
    return maps
