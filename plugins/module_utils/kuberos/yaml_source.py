"""Strict YAML loading that remembers where every field was written.

Specs are user input, possibly hostile: duplicate keys are errors, documents are bounded in
size, node count and depth, and every failure becomes a ``Problem`` naming file and line.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import yaml

from .errors import Problem, SpecError

MAX_BYTES = 1024 * 1024
MAX_NODES = 100_000
MAX_DEPTH = 64


def format_path(parts) -> str:
    """``('rosModules', 1, 'image')`` -> ``rosModules[1].image``."""
    text = ""
    for part in parts:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text


@dataclass
class Document:
    """One YAML document: its data and the line of each path in it."""

    data: object
    source: str
    index: int = 0
    lines: dict = field(default_factory=dict)

    def line_of(self, parts) -> int | None:
        parts = tuple(parts)
        while parts:
            if parts in self.lines:
                return self.lines[parts]
            parts = parts[:-1]
        return self.lines.get(())


class _Walker:
    def __init__(self, source: str):
        self.source = source
        self.lines: dict = {}
        self.problems: list[Problem] = []
        self.count = 0

    def walk(self, node, path, depth):
        self.count += 1
        if self.count > MAX_NODES:
            raise _TooLarge(f"more than {MAX_NODES} YAML nodes (aliases included)")
        if depth > MAX_DEPTH:
            raise _TooLarge(f"nested deeper than {MAX_DEPTH} levels")
        self.lines.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key in seen:
                    self.problems.append(
                        Problem(
                            self.source,
                            format_path((*path, str(key))),
                            f"duplicate key (first written on line {seen[key]})",
                            key_node.start_mark.line + 1,
                        )
                    )
                seen[key] = key_node.start_mark.line + 1
                # A field's line is where its key is written, even when its value starts below.
                self.lines.setdefault((*path, str(key)), key_node.start_mark.line + 1)
                self.walk(value_node, (*path, str(key)), depth + 1)
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.walk(item, (*path, index), depth + 1)


class _TooLarge(Exception):
    pass


_OPENING = (yaml.FlowSequenceStartToken, yaml.FlowMappingStartToken, yaml.BlockSequenceStartToken, yaml.BlockMappingStartToken)
_CLOSING = (yaml.FlowSequenceEndToken, yaml.FlowMappingEndToken, yaml.BlockEndToken)


def _check_depth(text: str) -> None:
    """Refuse deep nesting from the token stream, before PyYAML's recursive composer sees it."""
    scanner = yaml.SafeLoader(text)
    depth = 0
    try:
        while True:
            token = scanner.get_token()
            if token is None or isinstance(token, yaml.StreamEndToken):
                return
            if isinstance(token, _OPENING):
                depth += 1
                if depth > MAX_DEPTH:
                    raise _TooLarge(f"nested deeper than {MAX_DEPTH} levels (line {token.start_mark.line + 1})")
            elif isinstance(token, _CLOSING):
                depth -= 1
    finally:
        scanner.dispose()


def load_documents(text: str, source: str) -> list[Document]:
    """Parse every YAML document in ``text``; raise ``SpecError`` naming ``source`` on failure."""
    if len(text.encode("utf-8", "surrogatepass")) > MAX_BYTES:
        raise SpecError([Problem(source, "", f"file is larger than {MAX_BYTES} bytes")])
    documents: list[Document] = []
    problems: list[Problem] = []
    try:
        loader = yaml.SafeLoader(text)
    except yaml.reader.ReaderError as exc:  # the reader refuses control characters before parsing starts
        position = exc.position if isinstance(exc.position, int) else 0
        character = f"#x{exc.character:04x}" if isinstance(exc.character, int) else repr(exc.character)
        problem = Problem(
            source, "", f"not valid YAML: unacceptable character {character} ({exc.reason})", text.count("\n", 0, position) + 1
        )
        raise SpecError([problem], title=f"{source} is not valid") from None
    try:
        _check_depth(text)
        index = 0
        while loader.check_node():
            node = loader.get_node()
            if node is None:
                continue
            walker = _Walker(source)
            walker.walk(node, (), 0)
            problems.extend(walker.problems)
            data = loader.construct_document(node)
            documents.append(Document(data, source, index, walker.lines))
            index += 1
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        reason = exc.problem or exc.context or "invalid YAML"
        problems.append(Problem(source, "", f"not valid YAML: {reason}", line))
    except yaml.YAMLError as exc:
        problems.append(Problem(source, "", f"not valid YAML: {exc}"))
    except _TooLarge as exc:
        problems.append(Problem(source, "", f"document too large: {exc}"))
    except RecursionError:
        problems.append(Problem(source, "", f"document too large: nested deeper than {MAX_DEPTH} levels"))
    finally:
        loader.dispose()
    if problems:
        raise SpecError(problems, title=f"{source} is not valid")
    return documents
