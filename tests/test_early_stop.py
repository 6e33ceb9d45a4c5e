import math

import pytest

from mi_grg.early_stop import EarlyStopper


def test_stops_on_drop_of_more_than_half_a_percent_from_the_best():
    s = EarlyStopper(drop=0.005)
    assert s.update(500, 30.0) == "improved"
    assert s.update(1000, 31.0) == "improved"
    assert s.update(1500, 30.9) == "continue"          # -0.32 %
    assert s.update(2000, 30.86) == "continue"         # -0.45 % from the best
    assert s.update(2500, 30.80) == "stop"             # -0.65 % from the best
    assert s.best == 31.0 and s.best_iteration == 1000
    assert "1000" in s.reason and "2500" in s.reason


def test_slow_slide_is_caught_although_each_step_is_small():
    s = EarlyStopper(drop=0.005)
    values = [40.0, 39.9, 39.8, 39.7]                  # each step -0.25 %
    out = [s.update(500 * (i + 1), v) for i, v in enumerate(values)]
    assert out == ["improved", "continue", "continue", "stop"]


def test_state_round_trip_and_nan():
    s = EarlyStopper()
    s.update(1, 10.0)
    t = EarlyStopper()
    t.load_state(s.state())
    assert t.update(2, 9.0) == "stop"
    with pytest.raises(FloatingPointError):
        t.update(3, math.nan)
    with pytest.raises(ValueError):
        EarlyStopper(drop=1.5)
