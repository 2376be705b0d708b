"""JSON-safe values: no NaN or infinity reaches a JSON writer."""

import json
import math

import numpy as np

from dentibot.jsonsafe import finite


def test_non_finite_floats_become_null_at_any_depth_and_numpy_becomes_lists():
    obj = {"a": math.nan, "b": [1.0, math.inf, (2.5, -math.inf)], "c": np.array([1.0, np.nan]),
           "d": np.float64(3.0), "e": "text", "f": None, "g": 4}
    out = finite(obj)
    assert out == {"a": None, "b": [1.0, None, [2.5, None]], "c": [1.0, None], "d": 3.0,
                   "e": "text", "f": None, "g": 4}
    json.dumps(out, allow_nan=False)               # strict JSON accepts it
