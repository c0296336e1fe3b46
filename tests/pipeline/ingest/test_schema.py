"""The one-line message of a pydantic model's ValidationError: file, key path, what is wrong, how to fix."""

from typing import Any

import pytest

from mscal_core.errors import CatalogError, SessionError
from pipeline.ingest.schema import PositiveNumber, Strict, Text, integer, items, validate


class Leaf(Strict):
    size: PositiveNumber
    count: integer(1, 9) = 1  # type: ignore[valid-type]


class Root(Strict):
    name: Text
    leaves: tuple[Leaf, ...] = ()
    table: dict[str, PositiveNumber] = {}
    pair: items(lambda v: isinstance(v, str), "two names", str, lambda n: n == 2) = ("a", "b")  # type: ignore[valid-type]


def _message(data: Any, **kw: str) -> str:
    with pytest.raises(CatalogError) as err:
        validate(Root, data, "x.yaml", CatalogError, **kw)
    text = str(err.value)
    assert "\n" not in text and text.startswith("x.yaml: ")
    return text[len("x.yaml: "):]


def test_missing_keys_come_first_then_unknown_ones_each_at_one_place() -> None:
    assert _message({"colour": 1, "leaves": [{"size": 1, "x": 2, "y": 3}]}, label="thing") == (
        "thing: missing key(s) name (allowed keys: name, leaves, pair, table)")
    assert _message({"name": "n", "leaves": [{"size": 1}, {"size": 1, "x": 2, "y": 3}]}) == (
        "leaves[1]: unknown key(s) x, y (allowed keys: size, count)")
    assert _message({"name": "n", None: 1}) == "unknown key(s) None (allowed keys: name, leaves, pair, table)"


def test_a_value_is_named_by_its_key_path_and_says_what_it_must_be() -> None:
    assert _message({"name": "n", "leaves": [{"size": 1}, {"size": -2}]}) == (
        "leaves[1].size must be a positive number, got -2")
    assert _message({"name": "n", "leaves": [{"size": 1, "count": True}]}) == (
        "leaves[0].count must be an integer 1..9, got True")
    assert _message({"name": "n", "table": {"red": "x"}}, prefix="top") == "top.table.red must be a positive number, got 'x'"
    assert _message({"name": "n", "pair": ["a"]}) == "pair must be two names, got ['a']"
    assert _message({"name": "n", "leaves": "many"}) == "leaves must be a list, got 'many'"
    long = _message({"name": "n", "leaves": [{"size": "y" * 200}]})
    assert long.startswith("leaves[0].size must be a positive number, got 'yyy") and long.endswith("...")
    assert len(long) < 140


def test_the_error_class_is_the_callers_and_a_good_mapping_is_the_model() -> None:
    with pytest.raises(SessionError, match=r"^s\.yaml: must be a YAML mapping of keys to values, got 3 \(keys: name"):
        validate(Root, 3, "s.yaml", SessionError)
    root = validate(Root, {"name": 5, "leaves": [{"size": 2}]}, "x.yaml", CatalogError)
    assert (root.name, root.leaves[0].size, root.leaves[0].count, root.pair) == ("5", 2.0, 1, ("a", "b"))
