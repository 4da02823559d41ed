"""A box's config report on a broker, as its supervisor publishes it: the real
:class:`gateway.supervisor.boxpublish.ReportPublisher` (its session, the retained report, the
``online: false`` Will) with the report :func:`gateway.config.site.boxreport.build_report` makes of
a real state folder. Killed with SIGKILL, the broker publishes the Will.

``python tests/kit/box_reporter.py PORT STATE_DIR``; prints ``published`` once the report is out."""
from __future__ import annotations

import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(os.path.dirname(HERE))]

from gateway.config.site.boxreport import build_report  # noqa: E402
from gateway.config.site.versions import StateDir  # noqa: E402
from gateway.outputs.broker.settings import BrokerSettings  # noqa: E402
from gateway.supervisor.boxpublish import ReportPublisher  # noqa: E402


def main() -> None:
    port, state_dir = int(sys.argv[1]), sys.argv[2]
    state = StateDir(state_dir)
    rep = build_report(state, online=True)
    pub = ReportPublisher(BrokerSettings(host="127.0.0.1", port=port, reconnect_min_s=0.2,
                                         reconnect_max_s=1.0), "hookwatch", rep["site"], rep["box"])
    pub.start()
    pub.update(rep)
    while pub.published < 1:
        time.sleep(0.05)
    print("published", flush=True)
    while True:
        time.sleep(1)


if __name__ == "__main__":
    main()
