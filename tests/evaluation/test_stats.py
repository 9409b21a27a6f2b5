import pytest

from keygen.errors import InvalidParameterError
from keygen.evaluation.stats import summarize, wilson_interval


def test_wilson_known_values():
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(1.959964**2 / (10 + 1.959964**2))  # z^2 / (n + z^2)
    lo, hi = wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(10 / (10 + 1.959964**2))
    lo, hi = wilson_interval(8, 10)
    assert lo < 0.8 < hi and lo == pytest.approx(0.4902, abs=1e-3) and hi == pytest.approx(0.9433, abs=1e-3)
    assert wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(InvalidParameterError):
        wilson_interval(3, 2)


def test_summarize_groups_and_failures():
    results = [
        {"object_id": 0, "success": True, "failure": None},
        {"object_id": 0, "success": False, "failure": "dropped"},
        {"object_id": 1, "success": False, "failure": "timeout"},
        {"object_id": 1, "success": True, "failure": None},
    ]
    s = summarize(results)
    assert s["episodes"] == 4 and s["success_rate"] == 0.5
    assert s["by_object"]["0"]["failures"] == {"dropped": 1}
    assert s["failures"] == {"dropped": 1, "timeout": 1}
    assert s["ci95"][0] < 0.5 < s["ci95"][1]
