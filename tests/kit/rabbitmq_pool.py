"""One RabbitMQ cluster per worker, shared by the tests that need one (``rabbitmq_cluster``): a
pytest plugin (tests/conftest.py loads it).

Three nodes take about a minute to start and join; each test that used to start its own cluster
now gets the worker's, whole (a node a test killed and left down is started again first) and on a
virtual host of its own (kit.rabbitmq.Cluster.fresh_vhost: no retained message, persistent session
nor queue of one test reaches another). The tests that use it are one xdist group
(tests/conftest.py, SHARED_GROUPS), so they run one after another on one worker; the cluster is
stopped after the last of them (or at the end of the session)."""
from __future__ import annotations

import itertools
import re

import pytest

from kit.rabbitmq import Cluster

FIXTURE = "rabbitmq_cluster"
_vhosts = itertools.count(1)
#: the worker's cluster while it runs
_running: list[Cluster] = []


def _stop() -> None:
    while _running:
        _running.pop().stop()


@pytest.fixture(scope="session")
def _rabbitmq_session():
    """Whatever happens, the cluster is stopped at the end of the session."""
    yield
    _stop()


@pytest.fixture
def rabbitmq_cluster(_rabbitmq_session, tmp_path_factory, request) -> Cluster:
    """The worker's 3-node RabbitMQ cluster (kit.rabbitmq.Cluster), every node up, on a fresh vhost."""
    if _running:
        cluster = _running[0]
        cluster.whole()
    else:
        cluster = Cluster(tmp_path_factory.mktemp("rabbitmq-cluster"))
        cluster.__enter__()                 # stops what it started if the start fails
        _running.append(cluster)
    cluster.fresh_vhost(f"t{next(_vhosts)}-" + re.sub(r"[^A-Za-z0-9_.-]", "_", request.node.name)[:60])
    return cluster


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    """The cluster goes as soon as the next test does not use it (three idle nodes hold ~400 MB)."""
    if FIXTURE not in getattr(item, "fixturenames", ()):
        return
    if nextitem is None or FIXTURE not in getattr(nextitem, "fixturenames", ()):
        _stop()
