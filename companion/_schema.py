"""Typed, validated YAML: the shared edge where files become frozen objects."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from companion.errors import ConfigError

__all__ = ["StrictModel", "format_validation_error", "load_yaml_model"]


class StrictModel(BaseModel):
    """Frozen, rejects unknown keys."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False)


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
        got = err.get("input")
        shown = "" if err["type"] in ("missing", "extra_forbidden") else f", got {got!r}"
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
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), [f"cannot read file: {exc.strerror or exc}"]) from exc
    try:
        import yaml

        data = yaml.safe_load(text)
    except Exception as exc:  # yaml.YAMLError and its subclasses
        raise ConfigError(str(p), [f"not valid YAML: {exc}"]) from exc
    if not isinstance(data, dict):
        raise ConfigError(str(p), ["(top level): expected a mapping of keys"])
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(p), format_validation_error(exc)) from exc
