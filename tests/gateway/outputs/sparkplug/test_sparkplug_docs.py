"""docs/sparkplug.md is generated from the metric definition; the metric tables keep the rules."""
import os

from conftest import ROOT
from gateway.outputs.sparkplug import docs
from gateway.outputs.sparkplug import metrics as M


def test_sparkplug_doc_is_current():
    with open(os.path.join(ROOT, "docs", "sparkplug.md"), encoding="utf-8") as f:
        assert f.read() == docs.render(), \
            "regenerate: python -m gateway.outputs.sparkplug.docs > docs/sparkplug.md"


def test_metric_names_differ_in_lower_case_and_commands_are_writable():
    names = [m.name for m in M.NODE_METRICS + M.DEVICE_METRICS]
    assert len({n.lower() for n in names}) == len(names)
    for name in list(M.COMMANDS) + list(M.COMMAND_ARGS):
        assert M.DEVICE_BY_NAME[name].writable, name
    assert M.BDSEQ not in M.node_aliases() and M.REBIRTH not in M.node_aliases()
