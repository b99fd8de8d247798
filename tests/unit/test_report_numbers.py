"""Numbers in the report: digits from the uncertainty, targets judged on their interval."""
import pytest

from ema_uq.report.html import _at, _gap_finding, _judged, _pm


@pytest.mark.parametrize("x,sigma,text", [
    (0.049662, 0.00085, "0.04966 ± 0.00085"),     # two significant digits of sigma, x to the same place
    (2190.27, 45.6, "2190 ± 46"),
    (0.8909, 0.1191, "0.89 ± 0.12"),
    (5.0e-23, 1.2e-24, "(5.00 ± 0.12)·10<sup>-23</sup>"),   # far from 1: one shared power of ten
])
def test_value_carries_the_digits_its_uncertainty_supports(x, sigma, text):
    assert _pm(x, sigma) == text
    assert _at(x, sigma) == text.split(" ± ")[0].lstrip("(") + (text.split(")")[1] if ")" in text else "")


def test_without_an_uncertainty_the_value_keeps_a_few_digits():
    assert _pm(0.123456, None).startswith("0.1235 ± ") and _pm(0.123456, 0.0).startswith("0.1235 ± ")
    assert "–" in _pm(float("nan"), 0.1)


def test_a_target_is_judged_only_when_the_interval_is_on_one_side():
    assert "not shown" in _judged(0.025, 1.0, 0.9, "≥")          # 1 of 1 right: cannot show >= 0.9
    assert ">met<" in _judged(0.92, 1.0, 0.9, "≥") and "NOT met" in _judged(0.1, 0.6, 0.9, "≥")
    assert ">met<" in _judged(0.0, 0.049, 0.05, "≤") and "not shown" in _judged(0.0, 0.3, 0.05, "≤")


def test_the_gap_finding_writes_units_but_not_a_dimensionless_one():
    gap = {"verdict": "effect", "effect": "stribeck", "family": "stribeck", "confidence": "high",
           "effect_parameters": {"stribeck_ratio": {"estimate": 0.4994, "std": 0.0037, "unit": "1"},
                                 "stribeck_speed": {"estimate": 1.0006, "std": 0.008, "unit": "rad/s"}}}
    text = _gap_finding(gap)
    assert "stribeck_ratio = 0.4994 ± 0.0037;" in text
    assert "stribeck_speed = 1.0006 ± 0.0080 rad/s" in text and "high confidence" in text


def test_the_gap_section_says_where_along_the_stroke_when_the_gap_lies_there(tmp_path):
    from ema_uq import io
    from ema_uq.report.html_gap import _gap_section

    gap = {"verdict": "unexplained", "effect": None, "family": None, "confidence": "low",
           "where": {"channels": ["current"], "regimes": ["reversal"],
                     "stroke": ["stroke:2/4 (position 0.05957-0.09811 m, holds 143% of the gap, z 156.8)"]},
           "gap": {"before": 0.3, "after": 0.3}, "ranking": []}
    io.write_json(tmp_path / "gap.json", gap)
    study = {"concept": "cranfield", "name": "s"}
    text = _gap_section(study, tmp_path)
    assert "along the stroke in stroke:2/4 (position 0.05957-0.09811 m" in text
    gap["where"]["stroke"] = []
    io.write_json(tmp_path / "gap.json", gap)
    assert "along the stroke" not in _gap_section(study, tmp_path)
