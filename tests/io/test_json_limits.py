"""JSON from untrusted sources (pmvir.io.json_limits): every hostile document is one JsonError."""

from __future__ import annotations

import pytest

from pmvir.errors import ManifestError
from pmvir.io.json_limits import MAX_NUMBER_CHARS, JsonError, loads
from pmvir.io.manifest import parse_manifest


@pytest.mark.parametrize(
    ("doc", "problem"),
    [
        ('{"a": ' + "1" * 5000 + "}", "a number of 5000 characters"),
        ('{"a": 1.' + "5" * 100 + "}", "a number of 102 characters"),
        ("[" * 50_000 + "]" * 50_000, "nested deeper than 64 levels"),
        ("[" * 65 + "]" * 65, "nested deeper than 64 levels"),
        (b"\xff{}", "not UTF-8"),
        ("{'a': 1}", "not valid JSON"),
    ],
)
def test_hostile_documents_raise_one_error_naming_the_source(doc: str | bytes, problem: str) -> None:
    with pytest.raises(JsonError, match=problem) as err:
        loads(doc, source="options")
    assert err.value.source == "options" and str(err.value).startswith("options: ")


def test_ordinary_documents_parse_as_json_does() -> None:
    doc = '{"a": [1, -2.5e-3, "x", true, null], "b": {"c": ' + "9" * MAX_NUMBER_CHARS + "}}"
    assert loads(doc, source="x") == {
        "a": [1, -2.5e-3, "x", True, None],
        "b": {"c": int("9" * MAX_NUMBER_CHARS)},
    }
    assert loads("[" * 64 + "]" * 64, source="x") is not None


def test_capture_json_with_a_huge_number_is_a_manifest_error() -> None:
    with pytest.raises(ManifestError, match=r"capture\.json: a number of 5000 characters"):
        parse_manifest('{"format": "pmvir-capture/1", "x": ' + "1" * 5000 + "}")
