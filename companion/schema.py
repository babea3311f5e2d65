"""Typed, validated YAML: the shared edge where files become frozen objects.

Every config file the product reads comes through here, so here are the bounds
that keep a broken or hostile one harmless: only a regular file is opened (a
FIFO would block, ``/dev/zero`` never ends), it holds at most
:data:`MAX_FILE_BYTES`, its YAML stays within :data:`MAX_YAML_NODES`,
:data:`MAX_YAML_CHARS` and :data:`MAX_YAML_DEPTH` once aliases are expanded
(a "billion laughs" is 2 KB of text and 10**9 values), and an error shows a
cut-down excerpt of a value, never the whole of it.

Numbers in a file are numbers: a :class:`StrictModel` refuses a boolean
(``true``, ``yes``, ``on``) and a quoted number (``"1.5"``) where a number
belongs, though pydantic would read them as 1 and 1.5; an int stands for a
float. YAML numbers are read as YAML 1.2 writes them: ``1e-5`` is a number, as
it is to every YAML 1.2 reader (PyYAML, a YAML 1.1 reader, would make it text).
"""

from __future__ import annotations

import math
import os
import re
import reprlib
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, GetCoreSchemaHandler, ValidationError
from pydantic_core import CoreSchema, core_schema

from companion.errors import ConfigError

__all__ = [
    "MAX_FILE_BYTES",
    "MAX_MESSAGE_CHARS",
    "MAX_PROBLEMS",
    "MAX_YAML_CHARS",
    "MAX_YAML_DEPTH",
    "MAX_YAML_NODES",
    "Count",
    "Real",
    "StrictModel",
    "format_validation_error",
    "load_yaml_model",
    "range_problem",
    "read_text",
    "read_yaml",
    "real_number",
    "require_number",
]

MAX_FILE_BYTES = 1024 * 1024
"""The largest file :func:`read_text` reads, in bytes. The shipped configs are
at most 10 KB; a reference script of 30 000 rows fits."""

MAX_YAML_NODES = 10_000
"""The most values (scalars, lists, mappings) a YAML file may hold once every
alias is replaced by a copy of what it names. The shipped files hold at most
231 (``companion/data/mfc_default.yaml``); a pilot script of 700 segments fits.
PyYAML composes some 15 000 values a second, so this also keeps any file's
loading under a second."""

MAX_YAML_CHARS = MAX_FILE_BYTES
"""The most characters of scalar text a YAML file may hold once aliases are
expanded: no more than a file may hold (a long string used through many
aliases would otherwise print gigabytes)."""

MAX_YAML_DEPTH = 32
"""The deepest nesting of lists and mappings, aliases expanded (the shipped
files: 5). Far deeper would exhaust Python's recursion limit in PyYAML, pydantic
or ``repr``."""

MAX_MESSAGE_CHARS = 500
"""The longest problem line an error shows; longer ones are cut."""

MAX_PROBLEMS = 20
"""The most validation problems an error lists; it counts the rest."""

_MIB = 1024 * 1024

# Excerpts of values for messages: reprlib stops at these, so the cost of
# showing a value does not grow with it (the message then cuts it to 80).
_EXCERPT = reprlib.Repr()
_EXCERPT.maxlevel = 3
_EXCERPT.maxlist = _EXCERPT.maxtuple = _EXCERPT.maxset = _EXCERPT.maxfrozenset = 20
_EXCERPT.maxdeque = _EXCERPT.maxarray = 20
_EXCERPT.maxdict = 10
_EXCERPT.maxstring = _EXCERPT.maxlong = _EXCERPT.maxother = 100


def _clip(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text``, cut to ``limit`` characters with ``...`` when longer."""
    return text if len(text) <= limit else text[: limit - 3] + "..."


def require_number(v: object) -> object:
    """Refuse a boolean or a quoted number where a number belongs (pydantic would read
    ``true`` as 1 and ``"1.5"`` as 1.5); pass anything else on, other text for
    pydantic to refuse in its own words."""
    if isinstance(v, bool):
        raise ValueError(
            "expected a number, not a boolean (YAML reads true/false, yes/no, on/off as booleans)"
        )
    if isinstance(v, (str, bytes)):
        try:
            float(v)
        except ValueError:
            return v
        raise ValueError(
            'expected a number, not text (YAML reads a quoted number as text: write 1.5, not "1.5")'
        )
    return v


Real = Annotated[float, BeforeValidator(require_number)]
"""A float that refuses booleans and quoted numbers, element by element in a tuple (an
error names the index), in any model; ints pass. A :class:`StrictModel`'s plain
``float`` does the same: prefer it in a bound alias, ``Annotated[float, Field(ge=0)]``
(around Real's validator, pydantic leaves the bound out of the JSON schema)."""

Count = Annotated[int, BeforeValidator(require_number)]
"""An int that refuses booleans and quoted numbers."""


def real_number(v: object) -> float | None:
    """``v`` when it is a finite int or float (not a boolean), else None: what a check
    run before pydantic's (``mode="before"``, to say the likely mistake first) may
    judge; anything else is pydantic's to refuse."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    x = float(v)
    return x if math.isfinite(x) else None


def range_problem(
    value: float, bounds: tuple[float, float], what: str, low_hint: str, high_hint: str
) -> str | None:
    """Why ``value`` is outside the closed ``bounds``, the hint for its side first, or None.

    ``what`` says what was expected, ``%s`` where the range goes: ``"a speed in %s rad/s"``.
    """
    lo, hi = bounds
    if lo <= value <= hi:
        return None
    hint = low_hint if value < lo else high_hint
    return (f"{hint}: " if hint else "") + "expected " + what % f"[{lo:g}, {hi:g}]"


def _numbers_only(schema: Any) -> Any:
    """``schema`` (a pydantic core schema) with :func:`require_number` before each int
    and float in it: a field's, a tuple's or a list's element, an optional's."""
    if isinstance(schema, list):
        return [_numbers_only(s) for s in schema]
    if not isinstance(schema, dict):
        return schema
    kind = schema.get("type")
    if kind in ("int", "float"):
        return core_schema.no_info_before_validator_function(require_number, schema)
    if kind == "function-before" and schema["function"].get("function") is require_number:
        return schema  # a nested model's, done when it was built
    # Metadata and serialisation hold no validation.
    return {
        k: v if k in ("metadata", "serialization") else _numbers_only(v) for k, v in schema.items()
    }


class StrictModel(BaseModel):
    """Frozen, rejects unknown keys, non-finite numbers (``.nan``, ``.inf``), booleans
    and quoted numbers where a number belongs (:func:`require_number`: pydantic would
    read ``true`` as 1 and ``"1.5"`` as 1.5), wherever the number is (a field, an
    element of a tuple or a list)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)

    @classmethod
    def __get_pydantic_core_schema__(
        cls, source: type[BaseModel], handler: GetCoreSchemaHandler
    ) -> CoreSchema:
        schema: CoreSchema = _numbers_only(handler(source))
        return schema


_NOT_REGULAR: tuple[tuple[Callable[[int], bool], str], ...] = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _require_regular(p: Path, mode: int) -> None:
    """Refuse ``p`` unless ``mode`` (its ``st_mode``) is a regular file's."""
    if not stat.S_ISREG(mode):
        kind = next((name for is_kind, name in _NOT_REGULAR if is_kind(mode)), "something else")
        raise ConfigError(str(p), [f"cannot read file: expected a regular file, got {kind}"])


def _read_bytes(p: Path) -> bytes:
    """The bytes of the regular file ``p``, at most :data:`MAX_FILE_BYTES` of them."""
    too_big = f"cannot read file: larger than {MAX_FILE_BYTES / _MIB:g} MiB"
    try:
        # Look before opening: opening a FIFO blocks, opening a device may act on it.
        _require_regular(p, os.stat(p).st_mode)
        # Non-blocking, and checked again: ``p`` may have been swapped since.
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0))
        with open(fd, "rb") as f:
            st = os.fstat(fd)
            _require_regular(p, st.st_mode)
            if st.st_size > MAX_FILE_BYTES:
                raise ConfigError(str(p), [f"{too_big} ({st.st_size} bytes)"])
            data = f.read(MAX_FILE_BYTES + 1)  # a file growing meanwhile stops here
    except OSError as exc:
        raise ConfigError(str(p), [f"cannot read file: {exc.strerror or exc}"]) from exc
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(str(p), [f"{too_big} (it grew while being read)"])
    return data


def read_text(path: str | Path) -> str:
    """The UTF-8 text of ``path``.

    Raises
    ------
    ConfigError
        Naming the file when it is missing or unreadable, is not a regular file
        (a directory, a FIFO, a device), is larger than :data:`MAX_FILE_BYTES`,
        or is not UTF-8.
    """
    p = Path(path)
    data = _read_bytes(p)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(
            str(p), [f"cannot read file: not UTF-8 text (byte {exc.object[exc.start]:#04x} "
                     f"at offset {exc.start})"]
        ) from None  # fmt: skip
    # Universal newlines, as a file opened in text mode reads.
    return text.replace("\r\n", "\n").replace("\r", "\n")


class _LimitError(yaml.YAMLError):
    """A YAML document over :data:`MAX_YAML_NODES`, :data:`MAX_YAML_CHARS` or
    :data:`MAX_YAML_DEPTH`, or holding itself through an alias."""


def _where(mark: Any) -> str:
    """A PyYAML mark as people count: ``line 3, column 7``."""
    return f"line {mark.line + 1}, column {mark.column + 1}"


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, reading numbers as YAML 1.2 does, refusing a key given
    twice in one mapping and a document over the limits once aliases are expanded.

    The composer builds an alias as a second reference to the node it names;
    everything downstream (pydantic, ``repr``, JSON) walks it as a copy. So each
    node's expanded size is counted once, when it is composed, from its
    children's: (values, characters of scalar text, depth of nesting).
    """

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._expanded: dict[int, tuple[int, int, int]] = {}  # by id(node)
        self._calls = 0  # nodes and aliases composed: fails a long file early
        self._level = 0  # lists and mappings open around the node being composed

    def compose_node(self, parent: Any, index: Any) -> Any:
        event = self.peek_event()  # type: ignore[no-untyped-call]  # untyped in types-PyYAML
        mark = event.start_mark
        alias = isinstance(event, yaml.AliasEvent)
        if alias:
            named = self.anchors.get(event.anchor)
            if named is not None and id(named) not in self._expanded:
                raise _LimitError(
                    f"recursive: an alias inside the node it names (at {_where(mark)})"
                )
        self._calls += 1
        self._check(self._calls, 0, self._level, mark)
        self._level += 1
        node = super().compose_node(parent, index)
        self._level -= 1
        if not alias:
            self._expanded[id(node)] = self._measure(node)
        nodes, chars, depth = self._expanded[id(node)]
        self._check(nodes, chars, self._level + depth, mark)
        return node

    def _measure(self, node: Any) -> tuple[int, int, int]:
        """``node``'s expanded size, from its children's (already counted)."""
        if isinstance(node, yaml.ScalarNode):
            return 1, len(node.value), 0
        children = node.value
        if isinstance(node, yaml.MappingNode):
            children = [child for pair in node.value for child in pair]
        sizes = [self._expanded[id(child)] for child in children]
        return (
            1 + sum(s[0] for s in sizes),
            sum(s[1] for s in sizes),
            1 + max((s[2] for s in sizes), default=0),
        )

    @staticmethod
    def _check(nodes: int, chars: int, depth: int, mark: Any) -> None:
        for count, limit, what in (
            (nodes, MAX_YAML_NODES, "values"),
            (chars, MAX_YAML_CHARS, "characters of text"),
            (depth, MAX_YAML_DEPTH, "levels of nesting"),
        ):
            if count > limit:
                raise _LimitError(
                    f"too large: over the limit of {limit} {what} once aliases are expanded "
                    f"(at {_where(mark)})"
                )

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        # The keys as written: a merge (<<: *anchor) may be overridden, which
        # is not a duplicate; an unhashable key is PyYAML's to report.
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {_EXCERPT.repr(key)} given twice", key_node.start_mark
                    )
                seen.add(key)
            except TypeError:
                continue
        return super().construct_mapping(node, deep=deep)


# YAML 1.2 numbers PyYAML's YAML 1.1 resolver reads as text: an exponent without a
# dot or without a sign (``1e-5``, ``1.0e5``). In a file they are numbers; read as
# text they would be refused as quoted numbers.
_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def read_yaml(path: str | Path) -> Any:
    """``path`` parsed as YAML.

    Raises
    ------
    ConfigError
        Naming the file when :func:`read_text` refuses it, when it is not YAML,
        holds a key twice in one mapping (YAML forbids it; PyYAML would silently
        keep the last), or is over :data:`MAX_YAML_NODES`, :data:`MAX_YAML_CHARS`
        or :data:`MAX_YAML_DEPTH` once aliases are expanded.
    """
    text = read_text(path)
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader: no arbitrary objects
    except _LimitError as exc:
        raise ConfigError(str(path), [str(exc)]) from exc
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: an int of 5000 digits, 2024-02-30
        raise ConfigError(str(path), [_clip(f"not valid YAML: {exc}")]) from exc


M = TypeVar("M", bound=BaseModel)


def format_validation_error(exc: ValidationError) -> list[str]:
    """Turn pydantic's errors into ``key.path: what was expected`` lines.

    At most :data:`MAX_PROBLEMS` lines (and one counting the rest), each at most
    :data:`MAX_MESSAGE_CHARS` long, however large the offending values.
    """
    problems = []
    errors = exc.errors()
    for err in errors[:MAX_PROBLEMS]:
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "missing":
            msg = "missing required key"
        elif err["type"] == "value_error":  # our validators' own words
            msg = msg.removeprefix("Value error, ")
        got = err.get("input")
        # A model-level check got the whole mapping: its message says what it saw.
        whole = err["type"] == "value_error" and isinstance(got, dict)
        shown = ""
        if err["type"] not in ("missing", "extra_forbidden") and not whole:
            shown = _clip(f", got {_EXCERPT.repr(got)}", 80)
        problems.append(_clip(f"{loc}: {msg}{shown}"))
    if len(errors) > MAX_PROBLEMS:
        problems.append(f"... and {len(errors) - MAX_PROBLEMS} more")
    return problems


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    """Read ``path`` as YAML and validate it against ``model``.

    Raises
    ------
    ConfigError
        When :func:`read_yaml` refuses the file or it does not validate; the
        message names the file and each offending key path (the first
        :data:`MAX_PROBLEMS` of them).
    """
    p = Path(path)
    data = read_yaml(p)
    if not isinstance(data, dict):
        raise ConfigError(str(p), ["(top level): expected a mapping of keys"])
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(p), format_validation_error(exc)) from exc
