"""Work done per log, in a worker process: read the log once, gate and find the baseline once
(method core), finish the method for every δ of the sensitivity study, draw the sample's Fig. 7.
Functions here never raise: errors come back in the result as ``{"error": message}``."""
from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np

from ...core.method.core import gate_and_baseline, life_result
from ..analysis import AnalysisError, log_slots
from ..logio import LogError, read_log
from .plots import fig7_data, loop_series, render_fig7, render_fig8, time_unit


def analyze_test(task: dict[str, Any]) -> dict[str, Any]:
    """task: log, params (MethodParams), factors (δ multipliers), fig (PNG path or None), title."""
    t0 = time.perf_counter()
    c0 = time.process_time()
    path, p = task["log"], task["params"]
    try:
        lg = read_log(path)     # with its sidecar: the recorded lost_spans are LOST slots
    except LogError as e:
        return {"error": str(e)}
    except MemoryError:
        return {"error": f"{path}: not enough memory to read the log"}
    try:
        s = log_slots(lg, p)    # as `hookwatch analyze` and the live station saw them
        g = gate_and_baseline(s, p)
        results = {f: life_result(g, None if f == 1.0 else p.delta * f).as_dict()
                   for f in task["factors"]}
    except AnalysisError as e:
        return {"error": str(e)}
    except Exception as e:  # noqa: BLE001 - a bad log must not take the campaign down
        return {"error": f"{path}: analysis failed: {type(e).__name__}: {e}"}
    t_last = float(np.nanmax(lg.t)) if lg.t.size and np.isfinite(lg.t).any() else None
    out: dict[str, Any] = {
        "results": results, "n_rows": int(lg.t.size), "duplicates": s.duplicates,
        "out_of_grid": s.out_of_grid, "t_last": t_last, "fig": None, "fig_error": None,
    }
    if task.get("fig"):
        try:

            d = fig7_data(title=task["title"], ts=p.ts, mask=g.mask, mu=g.mu, ratio=g.ratio,
                          t1=s.t1, t2=s.t2, p=p, result=results[1.0], windows=g.windows)
            render_fig7(d, task["fig"])
            out["fig"] = task["fig"]
        except Exception as e:  # noqa: BLE001
            out["fig_error"] = f"Fig. 7 not drawn: {type(e).__name__}: {e}"
    out["seconds"] = time.perf_counter() - t0
    out["cpu_s"] = time.process_time() - c0
    return out


def control_figure(task: dict[str, Any]) -> dict[str, Any]:
    """task: open, closed (log paths), t_set, fig, title, labels. Fig. 8 and its figures."""
    try:

        logs = {}
        for key in ("open", "closed"):
            try:
                logs[key] = read_log(task[key], with_meta=False)
            except LogError as e:
                return {"error": str(e)}
        t_set = task["t_set"]
        span = max(float(np.nanmax(lg.t)) if lg.t.size else 0.0 for lg in logs.values()) or 1.0
        unit, scale = time_unit(span)
        x_end = span / scale
        settled = {k: settle_time(lg.t, lg.t1, lg.t2, t_set) for k, lg in logs.items()}
        dev = np.concatenate([((lg.t1 + lg.t2) / 2.0 - t_set)[lg.t >= settled[k]] for k, lg in logs.items()])
        dev = dev[np.isfinite(dev)]
        lim = float(np.percentile(np.abs(dev), 99.5)) if dev.size else 0.1
        lim = max(lim, 0.02 * t_set)
        # bins a whole number of 0.0005 N wide (the mean of two 0.001 N readings), edges between
        # those values: quantisation makes no comb
        q = 0.0005
        w = max(q, math.ceil(2 * lim / 80 / q) * q)
        nb = int(math.ceil(lim / w))
        edges = np.arange(-nb, nb + 1) * w + q / 2
        series = {k: loop_series(task["labels"][k], lg.t, lg.t1, lg.t2, t_set, scale, x_end, edges,
                                 settled[k]) for k, lg in logs.items()}
        render_fig8(series["open"], series["closed"], t_set, unit, x_end, task["fig"], task["title"])
        return {"fig": task["fig"], "stats": {
            k: {"mean_N": s.mean, "sd_N": s.sd, "drift_N_per_h": s.drift_per_h,
                "within_5pct": s.within_pct, "n_rows": int(logs[k].t.size), "settled_s": settled[k]}
            for k, s in series.items()}}
    except Exception as e:  # noqa: BLE001
        return {"error": f"Fig. 8 not drawn: {type(e).__name__}: {e}"}


def settle_time(t: np.ndarray, t1: np.ndarray, t2: np.ndarray, t_set: float) -> float:
    """When the mean tension first comes within ±5 % of T_set (the start-up is left out of the
    statistics of Fig. 8); the log's start if it never does."""
    with np.errstate(invalid="ignore"):
        ok = np.abs((t1 + t2) / 2.0 - t_set) <= 0.05 * t_set
    i = np.flatnonzero(ok & np.isfinite(t))
    return float(t[i].min()) if i.size else (float(np.nanmin(t)) if t.size else 0.0)


def run_task(task: dict[str, Any]) -> dict[str, Any]:
    os.environ.setdefault("MPLBACKEND", "Agg")
    if task.get("kind") == "control":
        return control_figure(task)
    return analyze_test(task)
