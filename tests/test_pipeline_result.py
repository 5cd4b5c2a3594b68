"""A registration's result (:mod:`dit_jax.pipeline.result`): its full record, read back exactly."""

import dataclasses
import json

import numpy as np
import pytest
from conftest import exact_result

from dit_jax.pipeline.result import Result, Stage


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    if isinstance(a, float) and np.isnan(a):
        return isinstance(b, float) and np.isnan(b)
    return type(a) is type(b) and a == b


def test_a_results_record_gives_it_back_field_for_field():
    motion = np.eye(4)
    motion[:3, 3] = [0.1, -2.0, 1.0 / 3.0]
    stage = Stage("network", motion[:3, :3], motion[:3, 3], 0.25, 0.8, float("nan"), "forward", None, False)
    result = dataclasses.replace(
        exact_result(motion, "unconfirmed", 0.7),
        confidence=np.array([0.1, np.nan, 1.0], np.float32),
        source_indices=np.array([4, 0, 7], np.int32),
        agreement=float("nan"),
        rival=0.125,
        agreement_band=(2.0, None, 40, 31),
        stages=(stage, dataclasses.replace(stage, name="refined", refinement="icp", verdict=True)),
    )
    back = Result.from_record(json.loads(json.dumps(result.to_record(), allow_nan=False)))
    for field in dataclasses.fields(Result):
        if field.name != "stages":
            assert _same(getattr(result, field.name), getattr(back, field.name)), field.name
    for was, now in zip(result.stages, back.stages, strict=True):
        for field in dataclasses.fields(Stage):
            assert _same(getattr(was, field.name), getattr(now, field.name)), field.name


def test_a_record_that_is_not_a_results_says_so():
    with pytest.raises(ValueError, match="not a result's record"):
        Result.from_record({"level": "trusted"})
