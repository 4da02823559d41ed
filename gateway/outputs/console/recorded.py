"""A station's recorded tests on disk, as the console serves them: the list, the files one may
download, and ``hookwatch report`` run as a low-priority child (a test's Fig. 7, a campaign)."""
from __future__ import annotations

import asyncio
import json
import os
import re
import sys
from typing import Any

TEST_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:+-]{0,127}$")
DOWNLOADS = {"log.csv.gz": "application/gzip", "log.meta.yaml": "text/yaml; charset=utf-8",
             "events.jsonl": "application/x-ndjson", "result.json": "application/json"}


async def report_process(args: list[str], timeout_s: float) -> tuple[int | None, str]:
    """Run ``hookwatch report`` as a child at low priority: (exit code or None on timeout, the
    end of its stderr). The child is killed when it runs too long or the caller is cancelled."""
    p = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "gateway.cli", "report", *args, "-q", "--jobs", "1",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        preexec_fn=lambda: os.nice(10))
    try:
        _, err = await asyncio.wait_for(p.communicate(), timeout_s)
    except (TimeoutError, asyncio.CancelledError) as e:
        p.kill()
        await asyncio.shield(p.wait())
        if isinstance(e, asyncio.CancelledError):
            raise
        return None, ""
    return p.returncode, err.decode(errors="replace")[-300:]


def find_png(out: str) -> str | None:
    d = os.path.join(out, "figures")
    try:
        names = sorted(n for n in os.listdir(d) if n.startswith("fig7") and n.endswith(".png"))
    except OSError:
        return None
    return os.path.join(d, names[0]) if names else None


def list_tests(station_dir: str, limit: int = 500) -> list[dict[str, Any]]:
    """The recorded tests of a station folder, newest first."""
    try:
        names = sorted((n for n in os.listdir(station_dir)
                        if TEST_ID_RE.match(n) and os.path.isdir(os.path.join(station_dir, n))),
                       reverse=True)[:limit]
    except OSError:
        return []
    out = []
    for n in names:
        td = os.path.join(station_dir, n)
        item: dict[str, Any] = {"test_id": n, "files": [f for f in DOWNLOADS if os.path.isfile(os.path.join(td, f))]}
        try:
            with open(os.path.join(td, "result.json"), encoding="utf-8") as fh:
                r = json.load(fh)
            m = r.get("method", r) if isinstance(r, dict) else {}
            item.update(status=m.get("status"), t_life=m.get("t_life"), mu_ss=m.get("mu_ss"),
                        mu_th=m.get("mu_th"), headroom=m.get("headroom"),
                        test_status=r.get("test_status"), end_reason=r.get("end_reason"),
                        why=r.get("why"),
                        sample_id=r.get("sample_id"), grade=r.get("grade"))
        except (OSError, ValueError, AttributeError):
            item.update(status=None, test_status="running" if "result.json" not in item["files"] else "unreadable")
        out.append(item)
    return out
