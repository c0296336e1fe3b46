"""pydantic models of the YAML files a user writes: the shared types and the one-line error.

A file is read with ``yaml.safe_load`` (:func:`pipeline.ingest.catalog.read_yaml`) and checked
by a frozen model that forbids unknown keys (:class:`Strict`). Its scalar types (:func:`number`,
:func:`integer`, :func:`pair`) say what a value must be in the words of the message; a
:class:`pydantic.ValidationError` becomes the caller's :class:`~mscal_core.errors.MscalError`
in one line (:func:`validate`): the file, the key path (``bands[2].wavelength_nm``), what is
wrong, and how to fix it (the allowed keys for a missing or unknown one). What ties several
keys together (bands against the layout, a marker against the reflector) stays with the code
that builds the frozen dataclasses the rest of mscal uses.
"""

from __future__ import annotations

import math
import types
import typing
from typing import Annotated, Any, Callable, ClassVar

from mscal_core.errors import MscalError
from pydantic import (
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Tag,
    TypeAdapter,
    ValidationError,
)

MAX_PIXELS = 100_000


class Strict(BaseModel):
    """A YAML mapping: frozen, unknown keys refused. ``TAGS``: the values of ``KEY`` that choose
    this model in a union of models (``layout.kind``, ``marker.type``); pydantic puts the
    chosen tag into an error's location, a key path leaves it out."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    TAGS: ClassVar[tuple[str, ...]] = ()
    KEY: ClassVar[str] = "kind"


def show_key(key: Any) -> str:
    """A mapping key as it reads in a one-line message (repr unless plain printable text)."""
    return key if isinstance(key, str) and key.isprintable() and key.strip() == key and key else repr(key)


def finite_number(value: Any) -> float | None:
    """``value`` as a finite float, None if it is not a number (bools are not) or not finite
    (NaN, inf, an integer too large for a float)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        v = float(value)
    except OverflowError:
        return None
    return v if math.isfinite(v) else None


class Problem(ValueError):
    """What a validator raises: the message says ``KEY TEXT, got VALUE`` (``value_first``:
    ``KEY VALUE TEXT``) with ``hint`` in brackets (pydantic keeps it as the error's context)."""

    def __init__(self, text: str, hint: str | None = None, value_first: bool = False):
        super().__init__(text)
        self.text, self.hint, self.value_first = text, hint, value_first



def check(test: Callable[[Any], bool], text: str, convert: Callable[[Any], Any] = lambda v: v,
          hint: str | None = None, value_first: bool = False) -> BeforeValidator:
    """A validator: ``convert(value)`` if ``test(value)``, else :class:`Problem` ``text``."""
    def run(value: Any) -> Any:
        if not test(value):
            raise Problem(text, hint, value_first)
        return convert(value)
    return BeforeValidator(run)


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def number(*, positive: bool = False, text: str | None = None) -> Any:
    """A finite number (not a bool), above 0 with ``positive``; the message says ``must be
    TEXT``, by default ``a number`` or ``positive``."""
    def run(value: Any) -> float:
        x = finite_number(value)
        if x is None or (positive and not x > 0):
            raise Problem(f"must be {text or ('a number' if x is None else 'positive')}")
        return x
    return Annotated[float, BeforeValidator(run)]


def items(test: Callable[[Any], bool], text: str, convert: Callable[[Any], Any] = lambda v: v,
          size: Callable[[int], bool] = lambda n: True) -> Any:
    """A YAML list whose items pass ``test`` and whose length passes ``size``, as a tuple of
    ``convert(item)``; else ``must be TEXT``."""
    return Annotated[tuple[Any, ...], check(
        lambda v: isinstance(v, list) and size(len(v)) and all(test(x) for x in v), f"must be {text}",
        lambda v: tuple(convert(x) for x in v))]


def integer(low: int, high: int | None = None, text: str | None = None) -> Any:
    """An integer (not a bool) from ``low`` to ``high``."""
    what = text or (f"an integer {low}..{high}" if high is not None else f"an integer of at least {low}")
    return Annotated[int, check(lambda v: is_int(v) and low <= v <= (math.inf if high is None else high),
                                f"must be {what}", int)]


def pair(low: int = 0, high: int = MAX_PIXELS) -> Any:
    """``[a, b]``: two integers from ``low`` to ``high``."""
    return Annotated[tuple[int, int], check(
        lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(is_int(x) and low <= x <= high for x in v),
        f"must be a pair of integers {low}..{high}", lambda v: (int(v[0]), int(v[1])))]


#: The pydantic error type of a value of none of a :func:`one_of`'s forms.
ONE_OF = "mscal_one_of"


def one_of(kind: Callable[[Any], str | None], text: str, **members: Any) -> Any:
    """A value of one of several forms, chosen by ``kind(value)`` (a name of ``members``, None:
    none of them) before it is validated: an error inside a form is named by the key path
    alone (the form's name is no key); a value of no form ``must be TEXT``."""
    union = typing.Union[tuple(Annotated[tp, Tag(name)] for name, tp in members.items())]
    return Annotated[union, Discriminator(kind, custom_error_type=ONE_OF, custom_error_message=text)]


def is_number(value: Any) -> bool:
    """A YAML number (an int or a float, not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


#: Free text: whatever YAML gives, as text (a description may read as a number).
Text = Annotated[str, BeforeValidator(str)]
PositiveNumber = number(positive=True, text="a positive number")


# --------------------------------------------------------------------------- the one-line error


def _tag(tp: Any) -> str | None:
    """The :func:`one_of` form name of a union member (``Annotated[X, Tag(name)]``), else None."""
    if typing.get_origin(tp) is Annotated:
        return next((m.tag for m in typing.get_args(tp)[1:] if isinstance(m, Tag)), None)
    return None


def _aliases(field: Any) -> list[str]:
    """The keys a model's field is given by: its validation aliases (none: by its name)."""
    alias = field.validation_alias
    if isinstance(alias, AliasChoices):
        return [a for a in alias.choices if isinstance(a, str)]
    return [alias] if isinstance(alias, str) else []


def _unwrap(tp: Any) -> Any:
    """``tp`` without Annotated, Optional and ClassVar wrappings."""
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return args
            tp = args[0]
        else:
            return tp


def _trail(model: Any, loc: tuple[Any, ...]) -> tuple[str, Any]:
    """The key path of ``loc`` as a message writes it, and the type found at its end (a
    union member's tag is no key: it is dropped, or said in brackets when it ends ``loc``)."""
    text, tp = "", model
    for i, part in enumerate(loc):
        tp = _unwrap(tp)
        form = next((m for m in tp if _tag(m) == part and not getattr(_unwrap(m), "TAGS", ())), None) \
            if isinstance(tp, list) else None
        if form is not None:  # a one_of form: no key
            tp = form
            continue
        if isinstance(tp, list):  # a union of models chosen by their TAGS
            tp = next((m for m in map(_unwrap, tp) if part in getattr(m, "TAGS", ())), None)
            text += f" ({tp.KEY} {part})" if tp is not None and i == len(loc) - 1 else ""
            continue
        if typing.get_origin(tp) is dict:
            text += f".{show_key(part)}"
            tp = typing.get_args(tp)[1]
            continue
        if isinstance(part, int):
            text += f"[{part}]"
            args = typing.get_args(tp)
            tp = args[0] if args else None
            continue
        text += f"{'.' if text else ''}{show_key(part)}"
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            field = tp.model_fields.get(part) if isinstance(part, str) else None
            field = field or next((f for f in tp.model_fields.values() if part in _aliases(f)), None)
            tp = None if field is None else field.annotation
        else:
            tp = None
    return text, _unwrap(tp)


def _keys(tp: Any) -> str:
    """The keys a model allows, required ones first (as the message's hint)."""
    if not (isinstance(tp, type) and issubclass(tp, BaseModel)):
        return ""
    fields = tp.model_fields
    if any(_aliases(f) for f in fields.values()):  # keys given by their aliases, in the model's order
        return ", ".join(" or ".join(map(show_key, _aliases(f) or [k])) for k, f in fields.items())
    return ", ".join(sorted(fields, key=lambda k: (not fields[k].is_required(), k)))


def message(exc: ValidationError, model: Any, prefix: str = "", label: str = ""
            ) -> tuple[str, str | None]:
    """One line for ``exc`` (reason, hint): missing keys first, then unknown keys (each group
    at one place), then the first other error. ``prefix`` goes before key paths (``marker``
    for a model of session.yaml's ``marker``), ``label`` names the file's top level."""
    errors = exc.errors(include_url=False)
    for kind, types_ in (("missing", ("missing",)), ("unknown", ("extra_forbidden", "invalid_key"))):
        found = [e for e in errors if e["type"] in types_]
        if found:
            parent = found[0]["loc"][:-1]
            path, tp = _trail(model, parent)
            at = f"{_join(prefix, path) or label}: " if _join(prefix, path) or label else ""
            keys = [show_key(e["input"] if e["type"] == "invalid_key" else e["loc"][-1])
                    for e in found if e["loc"][:-1] == parent]
            return f"{at}{kind} key(s) {', '.join(keys)}", (f"allowed keys: {_keys(tp)}" if _keys(tp) else None)
    e = errors[0]
    path, tp = _trail(model, e["loc"])
    at = _join(prefix, path)
    got = repr(e["input"])
    got = got if len(got) <= 80 else got[:77] + "..."
    ctx = e.get("ctx") or {}
    own = ctx.get("error")
    if isinstance(own, Problem):
        return (f"{at} {got} {own.text}" if own.value_first else f"{at} {own.text}, got {got}"), own.hint
    if e["type"] in ("model_type", "model_attributes_type", "dict_type"):
        allowed = _keys(tp)
        text = f"{at.split(' (')[0]} must be a mapping" if at else "must be a YAML mapping of keys to values"
        return f"{text}, got {got}", (f"keys: {allowed}" if allowed else None)
    if e["type"] in ("union_tag_invalid", "union_tag_not_found"):
        members = [_unwrap(m) for m in tp] if isinstance(tp, list) else []
        tags = [t for m in members for t in getattr(m, "TAGS", ())]
        key = getattr(members[0], "KEY", "kind") if members else "kind"
        value = e["input"].get(key) if isinstance(e["input"], dict) else e["input"]
        return f"{at}.{key} must be one of {', '.join(tags)}, got {value!r}", None
    if e["type"] == ONE_OF:
        return f"{at} must be {e['msg']}, got {got}", None
    if e["type"] in ("list_type", "tuple_type"):
        return f"{at} must be a list, got {got}", None
    if e["type"] == "too_short":
        return f"{at} must have at least {ctx.get('min_length')} item(s), got {got}", None
    text = e["msg"]
    text = "must" + text[len("Input should"):] if text.startswith("Input should") else f"is wrong: {text}"
    return f"{at} {text}, got {got}", None


def _join(prefix: str, path: str) -> str:
    return f"{prefix}{path}" if path[:1] in ("[", " ") else ".".join(p for p in (prefix, path) if p)


def validate(model: Any, data: Any, path: Any, error: type[MscalError], prefix: str = "", label: str = "") -> Any:
    """``model`` (a model, or any type pydantic validates) of ``data``, or ``error`` naming
    ``path`` in one line (:func:`message`)."""
    try:
        if isinstance(model, type) and issubclass(model, BaseModel):
            return model.model_validate(data)
        return TypeAdapter(model).validate_python(data)
    except ValidationError as exc:
        reason, hint = message(exc, model, prefix, label)
        raise error(reason, path=path, hint=hint) from None
