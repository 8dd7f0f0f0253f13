"""bench._common: the generic loader every bench's `load` is, so the report can render any section from its
recorded result."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from bench._common import from_json, load_json, to_json


@dataclass(frozen=True)
class Row:
    name: str
    value: float
    count: int


@dataclass(frozen=True)
class Result:
    rows: tuple[Row, ...]
    pair: tuple[int, str]
    by_name: dict[str, Row]
    best: Row | None
    missing: Row | None
    listed: list[float]
    array: np.ndarray
    path: Path
    extra: dict = field(default_factory=dict)


def test_a_nested_result_survives_its_json():
    result = Result((Row("a", 1.5, 2), Row("b", float("nan"), 0)), (3, "x"), {"k": Row("c", 2.0, 1)},
                    Row("d", 0.25, 4), None, [1.0, 2.0], np.arange(6.0).reshape(2, 3), Path("/tmp/x"), {"n": [1, 2]})
    again = from_json(Result, json.loads(to_json(result)))
    assert isinstance(again.rows, tuple) and all(isinstance(r, Row) for r in again.rows)
    assert again.rows[0] == Row("a", 1.5, 2) and np.isnan(again.rows[1].value)
    assert again.pair == (3, "x") and again.by_name == {"k": Row("c", 2.0, 1)}
    assert again.best == Row("d", 0.25, 4) and again.missing is None and again.listed == [1.0, 2.0]
    np.testing.assert_array_equal(again.array, result.array)
    assert again.path == Path("/tmp/x") and again.extra == {"n": [1, 2]}


def test_a_result_of_the_wrong_shape_is_refused(tmp_path):
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"name": "a", "value": 1.0, "count": "many"}))
    with pytest.raises(TypeError):
        load_json(Row, path)
    path.write_text(json.dumps({"name": "a", "value": 1.0}))
    with pytest.raises(TypeError):
        load_json(Row, path)     # a field missing: the dataclass refuses it
