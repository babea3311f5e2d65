"""Typed, validated YAML: the shared edge where files become frozen objects."""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from companion.errors import ConfigError

__all__ = ["StrictModel", "format_validation_error", "load_yaml_model", "read_text", "read_yaml"]


class StrictModel(BaseModel):
    """Frozen, rejects unknown keys and non-finite numbers (``.nan``, ``.inf``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)


def read_text(path: str | Path) -> str:
    """The UTF-8 text of ``path``; :class:`ConfigError` naming it if unreadable."""
    p = Path(path)
    try:
        return p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), [f"cannot read file: {exc.strerror or exc}"]) from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(
            str(p), [f"cannot read file: not UTF-8 text (byte {exc.object[exc.start]:#04x} "
                     f"at offset {exc.start})"]
        ) from None  # fmt: skip


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping."""

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
                        None, None, f"key {key!r} given twice", key_node.start_mark
                    )
                seen.add(key)
            except TypeError:
                continue
        return super().construct_mapping(node, deep=deep)


def read_yaml(path: str | Path) -> Any:
    """``path`` parsed as YAML; :class:`ConfigError` naming it if unreadable, not
    YAML, or holding a key twice in one mapping (YAML forbids it; PyYAML would
    silently keep the last)."""
    text = read_text(path)
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader: no arbitrary objects
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), [f"not valid YAML: {exc}"]) from exc


M = TypeVar("M", bound=BaseModel)


def format_validation_error(exc: ValidationError) -> list[str]:
    """Turn pydantic's errors into ``key.path: what was expected`` lines."""
    problems = []
    for err in exc.errors():
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
        shown = "" if err["type"] in ("missing", "extra_forbidden") or whole else f", got {got!r}"
        if len(shown) > 80:
            shown = shown[:77] + "..."
        problems.append(f"{loc}: {msg}{shown}")
    return problems


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    """Read ``path`` as YAML and validate it against ``model``.

    Raises
    ------
    ConfigError
        When the file is missing, is not YAML, or does not validate; the message
        names the file and every offending key path.
    """
    p = Path(path)
    data = read_yaml(p)
    if not isinstance(data, dict):
        raise ConfigError(str(p), ["(top level): expected a mapping of keys"])
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(p), format_validation_error(exc)) from exc
