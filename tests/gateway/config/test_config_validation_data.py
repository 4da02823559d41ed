"""One validation style (issue 11 item 5): station configuration, meter maps, scenarios and the
method's parameters report a bad field as data — key path, value, allowed, did-you-mean, file and
line — not as text to be parsed back. The messages themselves are the broken-config corpus'
(tests/gateway/cli/test_check.py); this file checks the data behind them."""
import os

import pytest
import yaml

from conftest import ROOT
from drivers.meter.meter_map import MapError, map_from_dict
from drivers.sim.scenario import ScenarioError, scenario_from_dict
from gateway.config import validate_station
from gateway.core.method.params import ParamError, build_params
from gateway.core.validation import MISSING, Problem, ValidationError

BROKEN = os.path.join(ROOT, "tests", "configs", "broken")


def test_param_error_names_the_field_value_and_rule():
    with pytest.raises(ParamError) as ei:
        build_params({"t_set": 0.5, "w_ss": 0})
    pr = ei.value.problem
    assert isinstance(ei.value, ValidationError)
    assert (pr.path, pr.value, pr.allowed) == (("w_ss",), 0.0, "> 0")
    assert str(ei.value) == "w_ss: 0.0 is impossible; allowed: > 0"


def test_rule_between_two_parameters_names_both():
    with pytest.raises(ParamError) as ei:
        build_params({"t_set": 0.5, "r_min": 1.01, "r_max": 0.9})
    pr = ei.value.problem
    assert pr.path == ("r_max",) and pr.related == (("r_min",),) and pr.value == 0.9
    assert pr.fields == (("r_min",), ("r_max",))


def test_unknown_parameter_suggests_and_huge_number_is_a_param_error():
    with pytest.raises(ParamError) as ei:
        build_params({"t_set": 0.5, "dleta": 0.3})
    assert ei.value.problem.path == ("dleta",) and ei.value.problem.suggestion == "delta"
    with pytest.raises(ParamError) as ei:              # was OverflowError (issue 12 item 10)
        build_params({"t_set": 10 ** 400})
    assert ei.value.problem.path == ("t_set",) and "is not a number" in str(ei.value)


def _issue(name):
    ld = validate_station(os.path.join(BROKEN, name))
    assert ld.cfg is None and len(ld.errors) == 1, ld.errors
    return ld.errors[0]


def test_station_issue_carries_the_field():
    i = _issue("typo_key.yaml")
    assert i.path == ("meter", "buad") and i.suggestion == "baud" and i.line == 5
    assert "baud" in i.allowed.split(", ")
    i = _issue("bad_type_baud.yaml")
    assert i.path == ("meter", "baud") and i.value is not MISSING and "9600" in i.allowed
    i = _issue("impossible_r_range.yaml")        # the rule lands on the key the file sets last
    assert i.path == ("method", "r_max") and i.line == 7 and i.value == 0.9
    i = _issue("impossible_w_ss.yaml")
    assert i.path == ("method", "w_ss") and i.allowed == "> 0" and i.value == 0.0


def test_meter_map_error_carries_the_field():
    with open(os.path.join(ROOT, "config", "meters", "zn-s.yaml"), encoding="utf-8") as f:
        base = yaml.safe_load(f)
    with pytest.raises(MapError) as ei:
        map_from_dict({**base, "unit_id": 0}, "m.yaml")
    pr = ei.value.problem
    assert (pr.path, pr.value, pr.file) == (("unit_id",), 0, "m.yaml") and "1..247" in pr.allowed
    with pytest.raises(MapError) as ei:
        map_from_dict({**base, "buad": 9600}, "m.yaml")
    assert ei.value.problem.path == ("buad",) and ei.value.problem.suggestion == "baud"
    assert str(ei.value).startswith("m.yaml: buad: unknown key; allowed keys: ")


def test_scenario_error_carries_the_field():
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict({"control": {"kpp": 3}}, "s.yaml")
    pr = ei.value.problem
    assert pr.path == ("control", "kpp") and pr.file == "s.yaml" and pr.suggestion == "kp"
    with pytest.raises(ScenarioError) as ei:
        scenario_from_dict({"method": {"w_ss": -3}}, "s.yaml")
    assert ei.value.problem.path == ("method", "w_ss") and ei.value.problem.value == -3.0


def test_problem_text_is_made_from_its_fields():
    p = Problem(("meter", "baud"), "12345 is not allowed", value=12345, file="a.yaml", line=3)
    assert str(p) == "a.yaml:3: meter.baud: 12345 is not allowed"
    assert str(ValidationError([p, p])) == f"{p}\n{p}"
