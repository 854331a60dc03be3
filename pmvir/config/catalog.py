"""The catalog of options: every leaf of the configuration tree with its type, default, range and level.

``pmvir options`` prints it and the documentation's options reference is generated from it, so
both follow the models.
"""

from __future__ import annotations

import difflib
import enum
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from pmvir.config.base import Level


@dataclass(frozen=True)
class OptionInfo:
    """One option of the configuration tree.

    Attributes:
        name: dotted path, e.g. ``refine.solver.max_iterations``.
        type: the value's type as a user writes it: ``int``, ``float``, ``bool``, ``str``,
            ``list[float]``, with `` | None`` where None is allowed.
        default: the default, as JSON would hold it.
        unit: the unit (``px``, ``deg``, ...), or None.
        range: the accepted values: an interval (``[0, 1)``, ``>= 2``), the choices
            (``off, start, stages``) or a pattern; None when any value of the type is accepted.
        description: what it does, at most 200 characters.
        level: ``basic`` (an option a user sets) or ``advanced`` (it tunes a step).
    """

    name: str
    type: str
    default: Any
    unit: str | None
    range: str | None
    description: str
    level: Level


def option_catalog(*, include_advanced: bool = True) -> list[OptionInfo]:
    """Every option of :class:`pmvir.config.PipelineConfig`, in the tree's order.

    Args:
        include_advanced: also list the advanced options (False: only the basic ones).

    >>> names = [o.name for o in option_catalog(include_advanced=False)]
    >>> "refine.solver.max_iterations" in names and "refine.pol.k" not in names
    True
    """
    from pmvir.config import PipelineConfig

    options = list(_walk(PipelineConfig, ""))
    return options if include_advanced else [o for o in options if o.level == "basic"]


def nearest_option(name: str) -> str | None:
    """The valid option name closest to a dotted ``name`` that is not one, or None.

    An option under another group of the same section wins (``refine.max_iterations`` ->
    ``refine.solver.max_iterations``); otherwise the closest spelling.

    >>> nearest_option("refine.max_iterations")
    'refine.solver.max_iterations'
    >>> nearest_option("geometry.mvs.plane")
    'geometry.mvs.planes'
    """
    names = [o.name for o in option_catalog()]
    section, leaf = name.split(".")[0], name.rsplit(".", 1)[-1]
    same_leaf = [n for n in names if n.split(".")[0] == section and n.rsplit(".", 1)[-1] == leaf]
    if len(same_leaf) == 1:
        return same_leaf[0]
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.7)
    return close[0] if close else None


def _walk(model: type[BaseModel], prefix: str) -> typing.Iterator[OptionInfo]:
    for name, field in model.model_fields.items():
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            yield from _walk(annotation, f"{prefix}{name}.")
            continue
        extra = field.json_schema_extra if isinstance(field.json_schema_extra, dict) else {}
        unit = extra.get("unit")
        level = extra.get("level", "advanced")
        type_name, choices = _type_and_choices(annotation)
        yield OptionInfo(
            name=f"{prefix}{name}",
            type=type_name,
            default=_json_value(field.get_default(call_default_factory=True)),
            unit=unit if isinstance(unit, str) else None,
            range=choices or _interval(field),
            description=field.description or "",
            level="basic" if level == "basic" else "advanced",
        )


def _type_and_choices(annotation: Any) -> tuple[str, str | None]:
    """(type name, the choices of a Literal or enum or None)."""
    args = typing.get_args(annotation)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        optional = type(None) in args
        parts = [_type_and_choices(a) for a in args if a is not type(None)]
        names = sorted({p[0] for p in parts})
        choices = [p[1] for p in parts if p[1]]
        if choices and any(p[0] == "bool" for p in parts):  # e.g. bool | Literal["auto"]: every value
            choices = ["true, false", *choices]
        type_name = " | ".join(names) + (" | None" if optional else "")
        return type_name, ", ".join(choices) if choices else None
    if origin is Literal:
        kinds = sorted({type(a).__name__ for a in args})
        return " | ".join(kinds), ", ".join(str(a) for a in args)
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return "str", ", ".join(str(m.value) for m in annotation)
    if origin is list:
        return f"list[{_type_and_choices(args[0])[0]}]", None
    return getattr(annotation, "__name__", str(annotation)), None


def _interval(field: FieldInfo) -> str | None:
    lower = upper = None
    for m in field.metadata:
        if isinstance(m, annotated_types.Ge):
            lower = f"[{_number(m.ge)}"
        elif isinstance(m, annotated_types.Gt):
            lower = f"({_number(m.gt)}"
        elif isinstance(m, annotated_types.Le):
            upper = f"{_number(m.le)}]"
        elif isinstance(m, annotated_types.Lt):
            upper = f"{_number(m.lt)})"
        elif getattr(m, "pattern", None):
            return f"pattern {m.pattern}"
    if lower and upper:
        return f"{lower}, {upper}"
    if lower:
        return (">= " if lower[0] == "[" else "> ") + lower[1:]
    if upper:
        return ("<= " if upper[-1] == "]" else "< ") + upper[:-1]
    return None


def _number(x: Any) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}"


def _json_value(value: Any) -> Any:
    if isinstance(value, enum.Enum):
        return value.value
    return value
