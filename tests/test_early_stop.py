import math

import pytest

from mi_grg.training.early_stop import EarlyStopper


def test_stops_on_drop_of_more_than_half_a_percent_from_the_best():
    s = EarlyStopper(drop=0.005)
    assert s.update(500, 30.0) == "improved"
    assert s.update(1000, 31.0) == "improved"
    assert s.update(1500, 30.9) == "within"            # -0.32 %
    assert s.update(2000, 30.86) == "within"           # -0.45 % from the best
    assert s.update(2500, 30.80) == "stop"             # -0.65 % from the best
    assert s.best == 31.0 and s.best_iteration == 1000
    assert s.kept_iteration == 2000                    # the latest state within the margin
    assert "1000" in s.reason and "2500" in s.reason


def test_patience_needs_drops_at_consecutive_evaluations():
    s = EarlyStopper(drop=0.005, patience=2)
    assert s.update(500, 30.0) == "improved"
    assert s.update(625, 29.8) == "below"              # -0.67 %, first below the margin
    assert s.update(750, 29.9) == "within"             # -0.33 %: the run of drops is broken
    assert s.update(875, 29.8) == "below"              # first again
    assert s.update(1000, 29.7) == "stop"              # second in a row
    assert s.best_iteration == 500 and "2 evaluations in a row" in s.reason
    assert s.kept_iteration == 750                     # states below the margin never qualify
    t = EarlyStopper(drop=0.005, patience=2)
    for it, v in [(1, 30.0), (2, 29.0), (3, 30.5), (4, 29.0)]:   # an improvement resets it
        assert t.update(it, v) != "stop"
    u = EarlyStopper(drop=0.005, patience=2)            # the count survives a checkpoint
    u.update(1, 30.0), u.update(2, 29.0)
    v = EarlyStopper(drop=0.005, patience=2)
    v.load_state_dict(u.state_dict())
    assert v.kept_iteration == 1
    assert v.update(3, 29.0) == "stop"
    for bad in (0, 1.5):
        with pytest.raises(ValueError, match="patience"):
            EarlyStopper(patience=bad)


def test_slow_slide_is_caught_although_each_step_is_small():
    s = EarlyStopper(drop=0.005)
    values = [40.0, 39.9, 39.8, 39.7]                  # each step -0.25 %
    out = [s.update(500 * (i + 1), v) for i, v in enumerate(values)]
    assert out == ["improved", "within", "within", "stop"]


def test_state_round_trip_and_nan():
    s = EarlyStopper()
    s.update(1, 10.0)
    t = EarlyStopper()
    t.load_state_dict(s.state_dict())
    assert t.update(2, 9.0) == "stop"
    with pytest.raises(FloatingPointError):
        t.update(3, math.nan)
    with pytest.raises(ValueError):
        EarlyStopper(drop=1.5)
