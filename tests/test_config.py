"""TrainConfig refuses absurd values with a ValidationError naming the field."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from voxnerf.config import MAX_LR, TrainConfig


@pytest.mark.parametrize("lr", [0.0, -1e-3, math.nan, math.inf, -math.inf, 1.0000001, 10.0, 1e300])
def test_absurd_learning_rates_are_refused(lr: float) -> None:
    with pytest.raises(ValidationError) as caught:
        TrainConfig(lr=lr)
    (error,) = caught.value.errors()
    assert error["loc"] == ("lr",)
    assert "learning rate must be in (0, 1]" in str(caught.value) or "finite number" in str(caught.value)


@pytest.mark.parametrize("lr", [1e-6, 1e-2, MAX_LR])
def test_sane_learning_rates_are_kept(lr: float) -> None:
    assert TrainConfig(lr=lr).lr == lr


@pytest.mark.parametrize("field", ["max_seconds", "eval_every_s", "checkpoint_every_s", "lambda_depth"])
def test_nan_and_infinity_are_refused_in_every_number(field: str) -> None:
    for value in (math.nan, math.inf):
        with pytest.raises(ValidationError, match="finite number"):
            TrainConfig(**{field: value})
    with pytest.raises(ValidationError, match="finite number"):
        TrainConfig(eval_at=[10.0, math.inf])
