"""Strict YAML loading that remembers where every field was written.

Specs are user input, possibly hostile: duplicate keys are errors, files are bounded in size (checked
on the bytes, before decoding) and number of documents, documents in node count and depth, control
characters are refused (``CONTROL_CHARACTERS``), and every failure becomes a ``Problem`` naming file and line.
"""

from __future__ import annotations

import bisect
import os
import re
import stat
from dataclasses import dataclass, field

from .errors import Problem, SpecError
from .third_party import yaml

MAX_BYTES = 1024 * 1024
YAML_EXTENSIONS = (".yml", ".yaml")
MAX_NODES = 100_000  # nodes of one document, each alias counted again as the nodes it stands for
MAX_TOTAL_NODES = 200_000  # the same, summed over the documents of one file (aliases bound the work of a file too)
MAX_FILE_NODES = 50_000  # nodes (keys included) written in one file: bounds the work before a refusal
MAX_DEPTH = 64
MAX_DOCUMENTS = 200
MAX_INTEGER_DIGITS = 1000  # Python reads no longer decimal integer (4300 digits); every field's bound is far below
# Refused anywhere in a file and in any value (also when written as an escape such as "\\x00"): the C0 controls but
# tab, line feed and carriage return; DEL; the C1 controls (YAML reads U+0085 as a line break); the Unicode line
# and paragraph separators (line breaks to YAML, not to most editors); and the bidirectional controls, which make
# text display in another order than it is read ("Trojan Source"); and the noncharacters U+FFFE and U+FFFF.
CONTROL_CHARACTERS = re.compile("[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f\u061c\u200e\u200f\u2028-\u202e\u2066-\u2069\ufffe\uffff]")
_MAX_REPORTED = 10
_SPECIAL_FILES = {
    stat.S_IFIFO: "a FIFO", stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device", stat.S_IFSOCK: "a socket",
}  # fmt: skip
# libyaml's loader when PyYAML was built with it (about ten times faster: a hostile 1 MiB file is refused in a
# fraction of a second instead of several), else PyYAML's own; both build the same nodes with the same marks.
# None without PyYAML (third_party.py: the modules check for it before any work).
if yaml is None:
    LOADER = None
else:
    LOADER = yaml.CSafeLoader if getattr(yaml, "__with_libyaml__", False) else yaml.SafeLoader
_LINE_BREAK = re.compile("\r\n|\r|\n")
_DIRECTIVE = re.compile(r"^%", re.M)


def format_path(parts) -> str:
    """``('rosModules', 1, 'image')`` -> ``rosModules[1].image``."""
    text = ""
    for part in parts:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += f".{part}" if text else str(part)
    return text


def path_prefix(path: str, prefixes) -> str | None:
    """The longest of ``prefixes`` (formatted paths) that is ``path`` or holds it (a field or item of it), or None:
    what renames a path from one format's field names to another's."""
    matches = [prefix for prefix in prefixes if path == prefix or path.startswith((prefix + ".", prefix + "["))]
    return max(matches, key=len, default=None)


@dataclass
class Document:
    """One YAML document: its data, the line of each path in it, and its text as written (from the start of the line
    its root node starts on: ``line``), and whether a directive above it (``%TAG``, ``%YAML``) gives that text a
    meaning it would not have alone."""

    data: object
    source: str
    index: int = 0
    lines: dict = field(default_factory=dict)
    line: int = 1
    text: str = ""
    directives: bool = False

    def line_of(self, parts) -> int | None:
        parts = tuple(parts)
        while parts:
            if parts in self.lines:
                return self.lines[parts]
            parts = parts[:-1]
        return self.lines.get(())


_TYPED_KEY_TAGS = {f"tag:yaml.org,2002:{name}" for name in ("bool", "int", "float", "null")}


class _Walker:
    def __init__(self, source: str, loader=None, file_left: int = MAX_TOTAL_NODES):
        self.source = source
        self.loader = loader
        self.lines: dict = {}
        self.problems: list[Problem] = []
        self.count = 0
        self.file_left = file_left  # nodes the file's earlier documents left of MAX_TOTAL_NODES
        self.escapes = 0  # control characters written as escapes, reported up to _MAX_REPORTED

    def walk(self, node, path, depth):
        self.count += 1
        if self.count > MAX_NODES:
            raise _TooLarge(f"more than {MAX_NODES} YAML nodes (aliases included)")
        if self.count > self.file_left:
            raise _TooLarge(
                f"more than {MAX_TOTAL_NODES} YAML nodes in the file's documents together (aliases included)",
                "file too large",
                node.start_mark.line + 1,
            )
        if depth > MAX_DEPTH:
            raise _TooLarge(f"nested deeper than {MAX_DEPTH} levels")
        self.lines.setdefault(path, node.start_mark.line + 1)
        if isinstance(node, yaml.ScalarNode):
            self._check_characters(node, path)
            _check_integer(node, path)
        if isinstance(node, yaml.MappingNode):
            seen = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key is not None and CONTROL_CHARACTERS.search(key):
                    self._check_characters(key_node, (*path, ascii(key)[1:-1]))
                    key = ascii(key)[1:-1]
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
                if isinstance(key_node, yaml.ScalarNode):
                    _check_integer(key_node, (*path, str(key)[:40]))
                if self.loader is not None and isinstance(key_node, yaml.ScalarNode) and key_node.tag in _TYPED_KEY_TAGS:
                    # A key YAML reads as another type (yes -> True, ~ -> None) is named by its value in messages.
                    constructed = str(self.loader.construct_object(key_node))
                    self.lines.setdefault((*path, constructed), key_node.start_mark.line + 1)
                self.walk(value_node, (*path, str(key)), depth + 1)
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                self.walk(item, (*path, index), depth + 1)

    def _check_characters(self, node, path):
        """A control character written as an escape ("\\x00", "\\u2028") in a quoted scalar."""
        found = CONTROL_CHARACTERS.search(node.value)
        if found and self.escapes < _MAX_REPORTED:
            self.escapes += 1
            reason = control_character_reason(found.group(), " (written as an escape)")
            self.problems.append(Problem(self.source, format_path(path), f"{reason}", node.start_mark.line + 1))


def _check_integer(node, path) -> None:
    """Refuse an integer longer than Python reads (``int()`` raises past 4300 decimal digits) at its field."""
    if node.tag == "tag:yaml.org,2002:int" and len(node.value) > MAX_INTEGER_DIGITS:
        message = f"an integer of {len(node.value)} characters; expected at most {MAX_INTEGER_DIGITS} digits"
        raise _TooLarge(message, format_path(path), node.start_mark.line + 1)


class _TooLarge(Exception):
    def __init__(self, message: str, what: str = "document too large", line: int | None = None):
        super().__init__(message)
        self.what = what
        self.line = line


if yaml is None:
    _OPENING = _CLOSING = _NODE_TOKENS = ()
else:
    _OPENING = (
        yaml.FlowSequenceStartToken,
        yaml.FlowMappingStartToken,
        yaml.BlockSequenceStartToken,
        yaml.BlockMappingStartToken,
    )
    _CLOSING = (yaml.FlowSequenceEndToken, yaml.FlowMappingEndToken, yaml.BlockEndToken)
    _NODE_TOKENS = (yaml.ScalarToken, yaml.AliasToken, *_OPENING)  # keys counted too: a bound, not an exact count


def _at_most(count: int, limit: int, what: str, token) -> None:
    if count > limit:
        raise _TooLarge(
            f"more than {limit} {what}; expected at most {limit} in one file", "file too large", token.start_mark.line + 1
        )


def _check_tokens(text: str) -> None:
    """Refuse deep nesting and too many nodes from the token stream, before a composer builds any node: libyaml's
    composer recurses on the C stack (200,000 nested '[' crash the process), and composing a file of half a
    million one-character scalars takes seconds before the node count could be checked on the nodes."""
    scanner = LOADER(text)
    depth = nodes = documents = 0
    try:
        while True:
            token = scanner.get_token()
            if token is None or isinstance(token, yaml.StreamEndToken):
                return
            if isinstance(token, _NODE_TOKENS):
                nodes += 1
                _at_most(nodes, MAX_FILE_NODES, "YAML nodes", token)
            elif isinstance(token, yaml.DocumentStartToken):
                documents += 1
                _at_most(documents, MAX_DOCUMENTS, "documents", token)
            if isinstance(token, _OPENING):
                depth += 1
                if depth > MAX_DEPTH:
                    raise _TooLarge(f"nested deeper than {MAX_DEPTH} levels (line {token.start_mark.line + 1})")
            elif isinstance(token, _CLOSING):
                depth -= 1
    finally:
        scanner.dispose()


def character_name(character: str) -> str:
    """``U+0000`` and, for the characters people know by name, the name: ``U+0000 (NUL)``."""
    names = {"\x00": "NUL", "\x1b": "ESC", "\x7f": "DEL", "\x85": "NEL", "\u2028": "LINE SEPARATOR"}
    names.update({"\u2029": "PARAGRAPH SEPARATOR", "\u202e": "RIGHT-TO-LEFT OVERRIDE", "\u202d": "LEFT-TO-RIGHT OVERRIDE"})
    code = f"U+{ord(character):04X}"
    return f"{code} ({names[character]})" if character in names else code


def control_character_reason(character: str, where: str = "") -> str:
    """Why a control character is refused; ``where`` says where it is (" in column 7")."""
    expected = "expected printable text (of the controls, only tab and line breaks)"
    return f"control character {character_name(character)}{where}; {expected}"


def read_text(path: str, display: str, what: str = "file") -> str:
    """The UTF-8 text of ``path``, its size checked on the bytes before decoding; ``SpecError`` naming ``display``."""
    try:
        kind = _SPECIAL_FILES.get(stat.S_IFMT(os.stat(path).st_mode))
        if kind:  # opening a FIFO blocks until someone writes to it; a device never ends
            raise SpecError([Problem(display, "", f"is {kind}, not a regular file")], title=f"cannot read {display}")
        with open(path, "rb") as handle:
            raw = handle.read(MAX_BYTES + 1)
    except OSError as exc:
        raise SpecError(
            [Problem(display, "", f"cannot read the {what}: {exc.strerror or exc}")], title=f"cannot read {display}"
        ) from None
    if len(raw) > MAX_BYTES:
        raise SpecError([Problem(display, "", f"file is larger than {MAX_BYTES} bytes")], title=f"{display} is not valid")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise SpecError(
            [Problem(display, "", f"not UTF-8 text (byte {exc.start})", line)], title=f"{display} is not valid"
        ) from None


def yaml_files(path: str, display: str, problems: list[Problem], limit: int, what: str) -> list[tuple[str, str]]:
    """``path`` when it is a file, else the YAML files of the directory (sorted, no hidden ones), each with its
    display name; a problem (and nothing) when the directory cannot be read or holds more than ``limit``."""
    if not os.path.isdir(path):
        return [(path, display)]
    try:
        names = sorted(os.listdir(path))
    except OSError as exc:
        problems.append(Problem(display, "", f"cannot read the directory: {exc.strerror or exc}"))
        return []
    names = [n for n in names if n.endswith(YAML_EXTENSIONS) and not n.startswith(".") and os.path.isfile(os.path.join(path, n))]
    if len(names) > limit:
        problems.append(Problem(display, "", f"more than {limit} {what}"))
        return []
    return [(os.path.join(path, n), os.path.join(display, n)) for n in names]


def _line_of(starts: list[int], position: int) -> int:
    return bisect.bisect_right(starts, position)


def _fields_by_line(text: str, source: str) -> dict[int, tuple[str, str]]:
    """For each line of ``text`` (its control characters replaced), the source and the deepest field written on
    it or above it; empty when the text does not parse."""
    try:
        documents = load_documents(CONTROL_CHARACTERS.sub("x", text), source)
    except SpecError:
        return {}
    by_line: dict[int, tuple[str, str]] = {}
    for doc in documents:
        where = f"{source} (document {doc.index + 1})" if len(documents) > 1 else source
        for parts, line in doc.lines.items():
            if parts and (line not in by_line or len(by_line[line][2]) < len(parts)):
                by_line[line] = (where, format_path(parts), parts)
    return {line: (where, path) for line, (where, path, _parts) in sorted(by_line.items())}


def _control_character_problems(text: str, source: str) -> list[Problem]:
    """The first refused control character of each line that has one, at most ``_MAX_REPORTED`` lines."""
    starts = [0] + [match.end() for match in _LINE_BREAK.finditer(text)]
    first: dict[int, tuple[int, str]] = {}
    for match in CONTROL_CHARACTERS.finditer(text):
        first.setdefault(_line_of(starts, match.start()), (match.start(), match.group()))
    if not first:
        return []
    fields = _fields_by_line(text, source)
    lines_with_fields = sorted(fields)
    problems = []
    for line, (position, character) in sorted(first.items())[:_MAX_REPORTED]:
        index = bisect.bisect_right(lines_with_fields, line) - 1
        where, path = fields[lines_with_fields[index]] if index >= 0 else (source, "")
        column = position - starts[line - 1] + 1
        problems.append(Problem(where, path, control_character_reason(character, f" in column {column}"), line))
    if len(first) > _MAX_REPORTED:
        problems.append(Problem(source, "", f"... and control characters on {len(first) - _MAX_REPORTED} more lines"))
    return problems


def load_documents(text: str, source: str) -> list[Document]:
    """Parse every YAML document in ``text``; raise ``SpecError`` naming ``source`` on failure."""
    if len(text) > MAX_BYTES or len(text.encode("utf-8", "surrogatepass")) > MAX_BYTES:
        raise SpecError([Problem(source, "", f"file is larger than {MAX_BYTES} bytes")], title=f"{source} is not valid")
    control = _control_character_problems(text, source)
    if control:
        raise SpecError(control, title=f"{source} is not valid")
    documents: list[Document] = []
    problems: list[Problem] = []
    try:
        loader = LOADER(text)
    except yaml.reader.ReaderError as exc:  # the reader refuses control characters before parsing starts
        position = exc.position if isinstance(exc.position, int) else 0
        character = f"#x{exc.character:04x}" if isinstance(exc.character, int) else repr(exc.character)
        problem = Problem(
            source, "", f"not valid YAML: unacceptable character {character} ({exc.reason})", text.count("\n", 0, position) + 1
        )
        raise SpecError([problem], title=f"{source} is not valid") from None
    try:
        _check_tokens(text)
        index = 0
        previous_end = 0
        file_left = MAX_TOTAL_NODES
        while loader.check_node():
            node = loader.get_node()
            if node is None:
                continue
            if index >= MAX_DOCUMENTS:
                message = f"file too large: more than {MAX_DOCUMENTS} documents; expected at most {MAX_DOCUMENTS} in one file"
                problems.append(Problem(source, "", message, node.start_mark.line + 1))
                break
            walker = _Walker(source, loader, file_left)
            walker.walk(node, (), 0)
            file_left -= walker.count
            problems.extend(walker.problems)
            data = loader.construct_document(node)
            start = node.start_mark.index - node.start_mark.column  # from the start of its line: indentation stays
            span = text[start : node.end_mark.index]
            directives = bool(_DIRECTIVE.search(text, previous_end, start))
            previous_end = node.end_mark.index
            line = node.start_mark.line + 1
            documents.append(Document(data, source, index, walker.lines, line, span, directives))
            index += 1
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        reason = exc.problem or exc.context or "invalid YAML"
        problems.append(Problem(source, "", f"not valid YAML: {reason}", line))
    except yaml.YAMLError as exc:
        problems.append(Problem(source, "", f"not valid YAML: {exc}"))
    except _TooLarge as exc:
        problems.append(Problem(source, "", f"{exc.what}: {exc}", exc.line))
    except RecursionError:
        problems.append(Problem(source, "", f"document too large: nested deeper than {MAX_DEPTH} levels"))
    finally:
        loader.dispose()
    if problems:
        raise SpecError(problems, title=f"{source} is not valid")
    return documents
