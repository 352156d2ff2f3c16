"""``msdnet-node --params-file``: a ROS 2 parameters file, read with the limits a config file deserves.

The file is refused in one line naming it, before anything else is done, when it is larger than
``MAX_BYTES``, not UTF-8 text (Latin-1, UTF-16, a gzip archive, NUL bytes), not YAML, nests deeper
than ``MAX_DEPTH``, holds more than ``MAX_ALIASES`` aliases or expands through them to more than
``MAX_VALUES`` values (an alias bomb is refused from its events, never expanded), or repeats a key
in one mapping. Values are shown cut to ``SHOWN_CHARS`` in every message.

Sections follow ROS 2's form: ``<node>: ros__parameters: {...}`` where ``<node>`` is a node's
fully qualified name (``/ns/name``; ``name`` alone is ``/name``), ``/**`` (every node) or a pattern
with ``*`` (one name token) and ``**`` (any number of tokens); a namespace may also nest
(``ns: name: ros__parameters:``), and nested parameter mappings are dotted names (``a: {b: 1}`` is
``a.b``). :func:`load` returns every section; ``params.file_values`` picks the node's.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from msdnet.runtime.errors import MsdnetError

MAX_BYTES = 256 * 1024  # a parameters file is a few kB; larger is not one
MAX_DEPTH = 16  # nested mappings and lists (namespaces, nodes, parameter groups, lists)
MAX_ALIASES = 32  # YAML aliases (*name) in the whole file
MAX_VALUES = 10_000  # scalars, mappings and lists once every alias is expanded
SHOWN_CHARS = 60  # a value quoted in an error message is cut to this many characters
PARAMS_KEY = "ros__parameters"
_TOKEN = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def shown(value: Any) -> str:
    """``repr(value)`` cut to ``SHOWN_CHARS`` (never expanding more than that: aliases share)."""
    import reprlib

    short = reprlib.Repr()
    short.maxstring = short.maxother = SHOWN_CHARS
    short.maxlist = short.maxdict = short.maxtuple = 4
    short.maxlevel = 2
    text = short.repr(value)
    return text if len(text) <= SHOWN_CHARS else text[: SHOWN_CHARS - 3] + "..."


def _read_text(path: Path) -> str:
    """The file as text: at most MAX_BYTES, UTF-8 (a UTF-8 byte-order mark is allowed)."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_BYTES + 1)
    except OSError as err:
        raise MsdnetError(path, f"cannot read: {err.strerror or err}") from None
    if len(data) > MAX_BYTES:
        raise MsdnetError(path, f"larger than {MAX_BYTES // 1024} KiB: not a parameters file")
    if data.startswith(b"\x1f\x8b"):
        raise MsdnetError(path, "is gzip-compressed: a parameters file is UTF-8 text")
    if data.startswith((b"\xff\xfe", b"\xfe\xff")) or (len(data) > 1 and data[1:2] == b"\x00"):
        raise MsdnetError(path, "is UTF-16 (or UTF-32) text: save it as UTF-8")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as err:
        byte = data[err.start]
        raise MsdnetError(
            path, f"is not UTF-8 text (byte 0x{byte:02x} at offset {err.start}; Latin-1?): save it as UTF-8"
        ) from None
    if "\x00" in text:
        raise MsdnetError(path, f"holds a NUL byte at offset {text.index(chr(0))}: not text")
    return text.removeprefix("\ufeff")


def _loader() -> Any:
    import yaml

    return getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _yaml_error(path: Path, err: Exception) -> MsdnetError:
    mark = getattr(err, "problem_mark", None)
    at = f" at line {mark.line + 1}" if mark is not None else ""
    problem = " ".join(str(getattr(err, "problem", None) or type(err).__name__).split())
    return MsdnetError(path, f"not YAML{at}: {problem[:100]}")


def _check_events(path: Path, text: str) -> None:
    """Depth and alias count from the event stream, before anything is composed or expanded."""
    import yaml

    depth = aliases = 0
    for event in yaml.parse(text, Loader=_loader()):
        if isinstance(event, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
            depth += 1
            if depth > MAX_DEPTH:
                line = event.start_mark.line + 1 if event.start_mark else "?"
                raise MsdnetError(path, f"nests deeper than {MAX_DEPTH} levels (line {line})")
        elif isinstance(event, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
            depth -= 1
        elif isinstance(event, yaml.AliasEvent):
            aliases += 1
            if aliases > MAX_ALIASES:
                raise MsdnetError(path, f"holds more than {MAX_ALIASES} YAML aliases")


def _check_nodes(path: Path, root: Any) -> None:
    """Every value once aliases are expanded (at most MAX_VALUES, so a cycle or a bomb stops
    early), and no key twice in one mapping."""
    import yaml

    budget = MAX_VALUES
    stack = [root] if root is not None else []
    while stack:
        node = stack.pop()
        budget -= 1
        if budget < 0:
            raise MsdnetError(path, f"expands through its aliases to more than {MAX_VALUES} values")
        if isinstance(node, yaml.MappingNode):
            seen: set[str] = set()
            for key, value in node.value:
                if isinstance(key, yaml.ScalarNode):
                    if key.value in seen:
                        line = key.start_mark.line + 1 if key.start_mark else "?"
                        twice = f"key {shown(key.value)} given twice in one mapping (line {line})"
                        raise MsdnetError(path, twice)
                    seen.add(key.value)
                stack += [key, value]
        elif isinstance(node, yaml.SequenceNode):
            stack += node.value


def read_document(path: Path) -> Any:
    """The YAML document of ``path`` within the limits (module docstring); MsdnetError otherwise."""
    import yaml

    text = _read_text(Path(path))
    try:
        _check_events(path, text)
        _check_nodes(path, yaml.compose(text, Loader=_loader()))
        return yaml.load(text, Loader=_loader())  # noqa: S506 - a safe loader
    except yaml.YAMLError as err:
        raise _yaml_error(path, err) from None
    except RecursionError:
        raise MsdnetError(path, f"nests deeper than {MAX_DEPTH} levels") from None


def _join(prefix: str, name: str) -> str:
    return "/" + "/".join(t for t in f"{prefix}/{name}".split("/") if t)


def _flatten(path: Path, where: str, params: Any, out: dict[str, Any], prefix: str = "") -> None:
    """ros__parameters -> {dotted name: value} (a nested mapping is a parameter group)."""
    if not isinstance(params, dict):
        raise MsdnetError(path, f"{where}.{PARAMS_KEY}: expected a mapping, got {shown(params)}")
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            _flatten(path, where, value, out, f"{name}.")
        else:
            out[name] = value


def load(path: Path) -> dict[str, dict[str, Any]]:
    """{section key ('/**', '/ns/name', patterns): {parameter: value}} of the file, in file order."""
    doc = read_document(path)
    if not isinstance(doc, dict) or not doc:
        raise MsdnetError(path, f"expected '<node name>: {PARAMS_KEY}: ...' at the top, got {shown(doc)}")
    sections: dict[str, dict[str, Any]] = {}

    def walk(prefix: str, body: dict[Any, Any]) -> None:
        for key, value in body.items():
            where = _join(prefix, str(key)) if str(key) != "/**" else "/**"
            if isinstance(value, dict) and PARAMS_KEY in value:
                if set(value) != {PARAMS_KEY}:
                    others = ", ".join(str(k) for k in value if k != PARAMS_KEY)
                    got = shown(others)[1:-1]
                    raise MsdnetError(path, f"{where}: expected only '{PARAMS_KEY}:', got {got}")
                params: dict[str, Any] = {}
                _flatten(path, where, value[PARAMS_KEY] or {}, params)
                sections[where] = {**sections.get(where, {}), **params}
            elif isinstance(value, dict) and value and all(isinstance(v, dict) for v in value.values()):
                walk(where, value)  # a namespace holding nodes
            else:
                got = ", ".join(map(str, value)) if isinstance(value, dict) else shown(value)
                raise MsdnetError(path, f"{where}: expected only '{PARAMS_KEY}:', got {shown(got)[1:-1]}")

    walk("", doc)
    return sections


def matches(pattern: str, fqn: str) -> bool:
    """Whether section key ``pattern`` applies to the node ``fqn`` (``/ns/name``): ``*`` is one
    token, ``**`` any number of them, as ROS 2's parameter files match node names."""
    want = [t for t in pattern.split("/") if t]
    have = [t for t in fqn.split("/") if t]

    def go(i: int, j: int) -> bool:
        if i == len(want):
            return j == len(have)
        if want[i] == "**":
            return any(go(i + 1, k) for k in range(j, len(have) + 1))
        return j < len(have) and (want[i] == "*" or want[i] == have[j]) and go(i + 1, j + 1)

    return go(0, 0)


def is_pattern(key: str) -> bool:
    """A section key with a wildcard."""
    return "*" in key


def valid_token(text: str) -> bool:
    """A ROS 2 name token: letters, digits and underscores, not starting with a digit."""
    return bool(_TOKEN.match(text))
