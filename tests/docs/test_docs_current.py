"""Generated docs are current (one definition → docs)."""
import importlib
import os

import pytest

from conftest import ROOT

GENERATED = [("gateway.core.method.docs", "docs/method.md")]


@pytest.mark.parametrize("module,path", GENERATED)
def test_generated_doc_is_current(module, path):
    mod = importlib.import_module(module)
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        assert f.read() == mod.render(), f"regenerate: python -m {module} > {path}"


def test_the_metrics_page_lists_the_catalogs_gauges():
    """docs/metrics.md's table of the state's gauges is the catalog's (gateway/core/catalog.py)."""
    from gateway.outputs.prometheus import docs

    with open(os.path.join(ROOT, "docs", "metrics.md"), encoding="utf-8") as f:
        page = f.read()
    assert docs.render(page) == page, "regenerate: python -m gateway.outputs.prometheus.docs docs/metrics.md"
