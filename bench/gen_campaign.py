#!/usr/bin/env python3
"""Synthetic test campaigns for `hookwatch report`: tests, benchmark, example.

Each test is a log in the interchange format (METHOD.md §9: ``t,T1,T2``) with its sidecar:
a regulated mean tension (3 Hz ripple + noise) split by the capstan relation T2 = T1·e^{μθ}
(quantised to 0.001 N like the meter), and a friction curve μ(t) with a run-in, a steady stage at
μ0 and an accelerated rise that crosses (1 + δ0)·μ0 at the sample's target life. Readings are
dropped at random (missing rows), a few single-slot spikes and short dropouts (< 1 s) are added.

By default the campaign is the paper's: grades I and II, T_set 0.5 / 0.7 / 0.9 N, three samples
each, target lives and μ_ss from Table 3, lives compressed by ``--compress`` (t_end 10 h / factor).
``--compress 1`` gives the paper's full ten-hour tests at the default method parameters.

    python bench/gen_campaign.py DIR [--compress 100] [--layout flat|gateway] [--hours 10]
    python bench/gen_campaign.py DIR --source plant --compress 100   # the shipped example
    python bench/gen_campaign.py --forecast [--reps 6] [--compress 40] [DIR]   # §5b bench

``--forecast`` is the remaining-life bench (METHOD.md §5b, §7a): a campaign of grades I and II ×
T_set 0.5 / 0.7 / 0.9 N from the virtual bench, run in order, each test's prior taken from the
campaign's own earlier tests (§7a: at least 3 failures of its grade and T_set), analysed offline;
it prints how many failures were warned at least ``lead`` ahead, how many warnings came after an
end of life, and how often t_life fell inside [e10, e90] at half-life. See bench/README.md.
"""
from __future__ import annotations

import argparse
import gzip
import json
import math
import os
import sys
import zlib
from dataclasses import dataclass, field

import numpy as np

THETA = math.radians(105.0)
TS = 0.02

#: the paper's Table 3: sample_id -> (grade, T_set N, t_life s, μ_ss)
PAPER_TABLE3 = {
    "I-05-01": ("I", 0.5, 32663.8, 0.3891), "I-05-02": ("I", 0.5, 31228.3, 0.3076),
    "I-05-03": ("I", 0.5, 33028.6, 0.2780), "II-05-01": ("II", 0.5, 21734.2, 0.3957),
    "II-05-02": ("II", 0.5, 21506.6, 0.3961), "II-05-03": ("II", 0.5, 21689.8, 0.2591),
    "I-07-01": ("I", 0.7, 28958.2, 0.2580), "I-07-02": ("I", 0.7, 28604.2, 0.2494),
    "I-07-03": ("I", 0.7, 29569.1, 0.2517), "II-07-01": ("II", 0.7, 19488.6, 0.2412),
    "II-07-02": ("II", 0.7, 18933.5, 0.2399), "II-07-03": ("II", 0.7, 18099.5, 0.2536),
    "I-09-01": ("I", 0.9, 26674.2, 0.2546), "I-09-02": ("I", 0.9, 26611.1, 0.2504),
    "I-09-03": ("I", 0.9, 26453.1, 0.2466), "II-09-01": ("II", 0.9, 16683.9, 0.2556),
    "II-09-02": ("II", 0.9, 17004.2, 0.2553), "II-09-03": ("II", 0.9, 16043.2, 0.2580),
}

#: the paper's Table 6 wear values (µm) for the 0.5 N samples
PAPER_WEAR = {
    "I-05-01": (36.8, 86.1, 86.6, 87.2, 160.4), "I-05-02": (40.2, 87.3, 87.6, 88.1, 167.1),
    "I-05-03": (37.7, 84.2, 85.3, 85.5, 151.4), "II-05-01": (42.1, 85.2, 85.6, 85.9, 176.5),
    "II-05-02": (40.4, 84.4, 84.8, 85.5, 171.2), "II-05-03": (43.4, 87.5, 88.1, 88.4, 186.3),
}
WEAR_COLUMNS = ("dw1_um", "dw21_um", "dw22_um", "dw23_um", "dw3_um")


@dataclass
class TestDef:
    sample_id: str
    grade: str | None
    t_set: float
    t_end: float                 # s
    life: float | None           # target t_life (s); None: never fails before t_end
    mu0: float = 0.26
    run_in_s: float = 600.0
    mu_noise: float = 0.002
    drop: float = 0.002          # share of readings missing
    spikes: int = 4              # single-slot spikes in T2
    dropouts: int = 2            # short dropouts (< 1 s)
    abort_at: float | None = None  # a 2 s loss of data here: protection stop
    method: dict = field(default_factory=dict)   # sidecar method: overrides

    @property
    def seed(self) -> int:
        return zlib.crc32(self.sample_id.encode())


def mu_curve(tt: np.ndarray, d: TestDef, delta0: float = 0.25) -> np.ndarray:
    """Run-in (+0.03 decaying), steady μ0, then μ0·(1 + ((t − t_acc)/T_r)²) which reaches
    (1 + δ0)·μ0 at the target life."""
    mu = np.full(tt.size, d.mu0)
    mu += np.where(tt < d.run_in_s, 0.03 * (1.0 - tt / d.run_in_s), 0.0)
    if d.life is not None:
        t_r = 0.3 * d.life
        t_acc = d.life - math.sqrt(delta0) * t_r
        x = np.clip((tt - t_acc) / t_r, 0.0, None)
        mu *= 1.0 + x * x
    return np.minimum(mu, 0.75)   # R stays below r_max = 4.2


def synth(d: TestDef) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, T1, T2) of the readings that arrived."""
    rng = np.random.default_rng(d.seed)
    n = int(round(d.t_end / TS))
    k = np.arange(n)
    tt = k * TS
    mu = mu_curve(tt, d) + d.mu_noise * rng.standard_normal(n)
    mean = d.t_set * (1.0 + 0.008 * np.sin(2 * np.pi * 3.0 * tt)) + 0.003 * rng.standard_normal(n)
    e = np.exp(mu * THETA)
    t1 = np.round(2.0 * mean / (1.0 + e), 3)
    t2 = np.round(t1 * e, 3)
    for _ in range(d.spikes):
        i = int(rng.integers(n // 10, n))
        t2[i] += 0.6 * d.t_set                       # gated out as a JUMP
    keep = rng.random(n) > d.drop
    for _ in range(d.dropouts):
        i = int(rng.integers(0, max(1, n - 40)))
        keep[i:i + int(rng.integers(5, 40))] = False  # 0.1–0.8 s
    if d.abort_at is not None:
        i = int(d.abort_at / TS)
        keep[i:i + int(2.0 / TS)] = False             # 2 s without data: protection stop
    t = tt + rng.uniform(-0.004, 0.004, n)
    return t[keep], t1[keep], t2[keep]


def write_log(path: str, t: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> None:
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    opener = gzip.open if path.endswith(".gz") else open
    kw = {"compresslevel": 6} if path.endswith(".gz") else {}
    with opener(path, "wt", **kw) as f:
        f.write("t,T1,T2\n")
        chunk = 200_000
        for i in range(0, t.size, chunk):
            rows = np.column_stack([t[i:i + chunk], t1[i:i + chunk], t2[i:i + chunk]])
            np.savetxt(f, rows, fmt=("%.4f", "%.3f", "%.3f"), delimiter=",")


def sidecar(d: TestDef, extra: dict | None = None) -> str:
    import yaml

    meta = {"sample_id": d.sample_id, "grade": d.grade, "t_set": d.t_set,
            "method": {"t_set": d.t_set, "t_end": d.t_end, **d.method}}
    meta.update(extra or {})
    return yaml.safe_dump(meta, sort_keys=False)


def write_test(root: str, d: TestDef, layout: str = "flat", station: str = "loom-01") -> str:
    """Write one test; returns the log path. ``flat``: ROOT/SAMPLE.csv.gz + SAMPLE.meta.yaml;
    ``gateway``: ROOT/STATION/TEST_ID/log.csv.gz + log.meta.yaml + result.json + events.jsonl."""
    t, t1, t2 = synth(d)
    if layout == "gateway":
        test_dir = os.path.join(root, station, f"20260101T{d.seed % 240000:06d}Z-{d.sample_id}")
        log = os.path.join(test_dir, "log.csv.gz")
    else:
        log = os.path.join(root, d.sample_id + ".csv.gz")
    write_log(log, t, t1, t2)
    meta_path = log[: -len(".csv.gz")] + ".meta.yaml"
    with open(meta_path, "w", encoding="utf-8") as f:
        f.write(sidecar(d, {"station": station} if layout == "gateway" else None))
    if layout == "gateway":
        aborted = d.abort_at is not None
        with open(os.path.join(os.path.dirname(log), "result.json"), "w", encoding="utf-8") as f:
            json.dump({"test_status": "aborted" if aborted else "completed",
                       "end_reason": "protection stop" if aborted else "completed"}, f, indent=1)
        with open(os.path.join(os.path.dirname(log), "events.jsonl"), "w", encoding="utf-8") as f:
            f.write(json.dumps({"type": "test_started", "sample_id": d.sample_id}) + "\n")
    return log


def paper_tests(compress: float = 100.0, hours: float = 10.0, grades=("I", "II"),
                setpoints=(0.5, 0.7, 0.9), reps: int = 3) -> list[TestDef]:
    """The paper's campaign; lives, t_end and the method windows divided by ``compress``
    (w_ss 60 → 10 s, w_hold 3600 → 60 s, tau 60 → 10 s at 100×)."""
    out = []
    method = {} if compress == 1 else {"w_ss": 10, "w_hold": 60, "tau": 10}
    for sp in setpoints:
        for g in grades:
            for r in range(1, reps + 1):
                sid = f"{g}-{int(round(sp * 10)):02d}-{r:02d}"
                if sid in PAPER_TABLE3:
                    _, _, life, mu0 = PAPER_TABLE3[sid]
                else:   # outside the paper's grid: a plausible life
                    rng = np.random.default_rng(zlib.crc32(sid.encode()))
                    base = {"I": 32300.0, "II": 21600.0}.get(g, 25000.0)
                    life = base * (0.5 / sp) ** 0.4 * (1 + 0.02 * rng.standard_normal())
                    mu0 = 0.26
                out.append(TestDef(sid, g, sp, hours * 3600.0 / compress, life / compress, mu0,
                                   run_in_s=max(20.0, 600.0 / compress),
                                   spikes=4 if compress > 1 else 40,
                                   dropouts=2 if compress > 1 else 20, method=dict(method)))
    return out


def wear_rows(tests: list[TestDef], seed: int = 1) -> list[dict]:
    """Offline wear per sample: the paper's Table 6 where it has the sample, else values that
    grow as the target life shrinks (shorter life ↔ more wear), with scatter."""
    rng = np.random.default_rng(seed)
    lives = [d.life for d in tests if d.life is not None]
    lo, hi = (min(lives), max(lives)) if lives else (1.0, 2.0)
    rows = []
    for d in tests:
        if d.sample_id in PAPER_WEAR:
            vals = PAPER_WEAR[d.sample_id]
        else:
            w = 0.5 if d.life is None or hi == lo else (hi - d.life) / (hi - lo)   # 0 longest … 1 shortest
            vals = (36.0 + 7.0 * w + rng.normal(0, 0.8), 84.0 + 3.0 * w + rng.normal(0, 0.8),
                    84.5 + 3.0 * w + rng.normal(0, 0.8), 85.0 + 3.0 * w + rng.normal(0, 0.8),
                    150.0 + 35.0 * w + rng.normal(0, 4.0))
        rows.append({"sample_id": d.sample_id, "grade": d.grade, "t_set_N": d.t_set,
                     **{c: round(float(v), 1) for c, v in zip(WEAR_COLUMNS, vals)}})
    return rows


def write_wear(path: str, rows: list[dict]) -> None:
    import csv

    with open(path, "w", encoding="utf-8", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)


def synth_loop(closed: bool, t_set: float = 0.5, duration: float = 300.0, seed: int = 3
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A stand-in for the open/closed-loop comparison (Fig. 8): open loop drifts and ripples
    with the yarn package, closed loop holds T_set with a small residual."""
    rng = np.random.default_rng(seed + int(closed))
    n = int(round(duration / TS))
    tt = np.arange(n) * TS
    if closed:
        mean = t_set * (1.0 + 0.006 * np.sin(2 * np.pi * 3.0 * tt)) + 0.004 * rng.standard_normal(n)
    else:
        drift = 0.12 * t_set * (tt / duration) + 0.05 * t_set * np.sin(2 * np.pi * tt / (duration / 2.3))
        mean = t_set * (1.0 + 0.03 * np.sin(2 * np.pi * 3.0 * tt)) + drift + 0.01 * rng.standard_normal(n)
    e = math.exp(0.26 * THETA)
    t1 = np.round(2.0 * mean / (1.0 + e), 3)
    t2 = np.round(t1 * e, 3)
    return tt + rng.uniform(-0.004, 0.004, n), t1, t2


def write_loop_logs(root: str, t_set: float = 0.5, duration: float = 300.0) -> tuple[str, str]:
    import yaml

    out = []
    for closed in (False, True):
        name = "closed_loop" if closed else "open_loop"
        log = os.path.join(root, "control", name + ".csv.gz")
        write_log(log, *synth_loop(closed, t_set, duration))
        with open(log[:-7] + ".meta.yaml", "w", encoding="utf-8") as f:
            yaml.safe_dump({"role": name, "t_set": t_set, "method": {"t_set": t_set},
                            "control": {"mode": "closed" if closed else "open"}}, f, sort_keys=False)
        out.append(log)
    return out[0], out[1]


def make_campaign(root: str, *, compress: float = 100.0, hours: float = 10.0, layout: str = "flat",
                  wear: bool = True, control: bool = True, tests: list[TestDef] | None = None) -> list[str]:
    os.makedirs(root, exist_ok=True)
    tests = tests if tests is not None else paper_tests(compress, hours)
    logs = [write_test(root, d, layout) for d in tests]
    if wear:
        write_wear(os.path.join(root, "wear.csv"), wear_rows(tests))
    if control:
        logs += write_loop_logs(root, duration=max(60.0, min(600.0, hours * 3600.0 / compress)))
    return logs


# ---------------------------------------------------------------------------------------------
# From the virtual bench: drivers/sim/plant.py under gateway.core.control.Controller, offline
# ---------------------------------------------------------------------------------------------

PLANT_STATION = "virtual-bench"


def plant_run(grade: str, t_set: float, seed: int, duration: float, time_scale: float = 100.0,
              mode: str = "closed", drop: float = 0.002):
    """Sample the plant at 50 Hz for ``duration`` s with the gateway's controller closing the
    loop (or holding the open-loop speed): a pure loop, no I/O. A share ``drop`` of the slots,
    and a few short bursts, lose their reading (meter timeouts). Returns (t, T1, T2, truth)."""
    from drivers.sim.plant import Plant, PlantParams
    from gateway.core.control import Controller, ControlParams

    plant = Plant(PlantParams(grade=grade, t_set=t_set, time_scale=time_scale), seed)
    tp = plant.p.tension
    cp = ControlParams(mode=mode, open_loop_rpm=tp.offset_rpm + (t_set - tp.pretension_n) / tp.gain_n_per_rpm)
    ctl = Controller(cp, t_set)
    plant.enable(True)
    n = int(round(duration / TS))
    t1 = np.empty(n)
    t2 = np.empty(n)
    for k in range(n):
        plant.advance_to(k * TS)
        c1, c2 = plant.tensions()
        t1[k], t2[k] = c1, c2
        plant.set_command(ctl.step((c1 + c2) / 2.0, plant.speed_rpm).u)
    rng = np.random.default_rng(seed + 1)
    keep = rng.random(n) > drop
    for _ in range(3):
        i = int(rng.integers(0, max(1, n - 40)))
        keep[i:i + int(rng.integers(5, 30))] = False      # < 0.6 s: no protection stop
    t = np.arange(n) * TS
    return t[keep], t1[keep], t2[keep], plant.truth()


def make_plant_campaign(root: str, *, time_scale: float = 100.0, t_end: float = 360.0,
                        grades=("I", "II"), setpoints=(0.5, 0.7, 0.9), reps: int = 3,
                        control_s: float = 7200.0, control_every: int = 10, seed0: int = 100) -> list[str]:
    """The example campaign: 2 grades × 3 setpoints × 3 samples from the virtual bench, lives
    compressed ``time_scale``× (method windows w_ss 10 s, w_hold 60 s, tau 10 s; the lead
    3600 s and the life prior of the paper's Table 4 divided by time_scale), in the
    gateway's folder layout; a wear table; an open-loop and a closed-loop log for Fig. 8 (two
    hours each, long enough for the drift to leave the controller's dead band; every 10th slot
    written)."""
    import yaml

    from drivers.sim.plant import TABLE4_LIFE
    from gateway.core.method.core import analyze_readings
    from gateway.core.method.params import build_params

    logs, tests = [], []
    i = 0
    for sp in setpoints:
        for g in grades:
            for r in range(1, reps + 1):
                i += 1
                sid = f"{g}-{int(round(sp * 10)):02d}-{r:02d}"
                seed = seed0 + i
                t, a, b, truth = plant_run(g, sp, seed, t_end, time_scale)
                # the life prior a plant would configure (forecast.priors): the paper's Table 4
                # for the grade and setpoint, compressed like the lives (METHOD.md §5b, §7a)
                pm, psd = TABLE4_LIFE[(g, sp)]
                method = {"t_set": sp, "t_end": t_end, "w_ss": 10, "w_hold": 60, "tau": 10,
                          "lead": 3600.0 / time_scale, "prior_mean": round(pm / time_scale, 3),
                          "prior_sd": round(psd / time_scale, 3)}
                test_id = f"20260105T{8 + (i * 7) // 60:02d}{(i * 7) % 60:02d}00Z-{sid}"
                d = os.path.join(root, PLANT_STATION, test_id)
                log = os.path.join(d, "log.csv.gz")
                write_log_plain(log, t, a, b)
                meta = {"station": PLANT_STATION, "test_id": test_id, "sample_id": sid, "grade": g,
                        "t_set": sp, "software": "bench/gen_campaign.py (virtual bench, offline)",
                        "prior_source": "config", "prior_n": 3, "method": method, "control": {"mode": "closed"},
                        "sim": {"seed": seed, "time_scale": time_scale,
                                "table_life_s": round(truth["table_life_s"], 1),
                                "true_crossing_s": round(truth["cross_run_s"], 2),
                                "true_mu_ss": round(truth["mu_ss"], 4)}}
                with open(os.path.join(d, "log.meta.yaml"), "w", encoding="utf-8") as f:
                    yaml.safe_dump(meta, f, sort_keys=False)
                res = analyze_readings(t, a, b, build_params(method)).as_dict()
                with open(os.path.join(d, "result.json"), "w", encoding="utf-8") as f:
                    json.dump({"test_id": test_id, "station": PLANT_STATION, "test_status": "completed",
                               "end_reason": "completed", "method": res}, f, indent=1)
                with open(os.path.join(d, "events.jsonl"), "w", encoding="utf-8") as f:
                    f.write(json.dumps({"type": "test_started", "k": 0, "sample_id": sid, "grade": g}) + "\n")
                    if res["k_b"] is not None:
                        f.write(json.dumps({"type": "baseline", "k": res["k_b"], "mu_ss": res["mu_ss"]}) + "\n")
                    if res["k_life"] is not None:
                        f.write(json.dumps({"type": "end_of_life", "k": res["k_life"], "t_life": res["t_life"]}) + "\n")
                    f.write(json.dumps({"type": "test_ended", "reason": "completed", "status": res["status"]}) + "\n")
                logs.append(log)
                tests.append(TestDef(sid, g, sp, t_end, truth["cross_run_s"]))
    write_wear(os.path.join(root, "wear.csv"), wear_rows(tests))
    for _k, mode in enumerate(("open", "closed")):
        t, a, b, _ = plant_run("I", 0.5, seed0 + 50, control_s, time_scale, mode=mode, drop=0.0)
        log = os.path.join(root, "control", f"{mode}_loop.csv.gz")
        sl = slice(None, None, control_every)     # the drift is slow: every 10th slot is enough
        write_log_plain(log, t[sl], a[sl], b[sl])
        with open(log[:-7] + ".meta.yaml", "w", encoding="utf-8") as f:
            yaml.safe_dump({"role": f"{mode}_loop", "station": PLANT_STATION, "sample_id": None,
                            "grade": "I", "t_set": 0.5, "method": {"t_set": 0.5},
                            "control": {"mode": mode}, "sim": {"seed": seed0 + 50}}, f, sort_keys=False)
        logs.append(log)
    return logs


# ---------------------------------------------------------------------------------------------
# The remaining-life bench (METHOD.md §5b, §7a)
# ---------------------------------------------------------------------------------------------

#: the method's times at full scale; divided by the compression (tau_g and stop_after are about
#: data gaps, not wear: they stay)
FULL_SCALE_TIMES = {"w_ss": 60.0, "w_hold": 3600.0, "tau": 60.0, "lead": 3600.0}


@dataclass
class ForecastRow:
    sample_id: str
    grade: str
    t_set: float
    prior: tuple[float, float, str | None, int | None]   # mean, sd, source, n
    truth_life: float         # the plant's drawn life, running s
    status: str
    t_life: float | None
    k_life: int | None
    warn_s: float | None
    warn_slot: int | None
    reasons: list[str] | None
    lead: float
    band: tuple[float, float] | None     # [e10, e90] at half-life (with a prior)

    @property
    def lead_s(self) -> float | None:
        return None if self.warn_s is None or self.t_life is None else self.t_life - self.warn_s

    @property
    def late(self) -> bool:
        """A warning at or after the end of life (slot ≥ k_life)."""
        return self.warn_slot is not None and self.k_life is not None and self.warn_slot >= self.k_life


def forecast_campaign(*, compress: float = 40.0, reps: int = 6, grades=("I", "II"),
                      setpoints=(0.5, 0.7, 0.9), seed0: int = 500, out: str | None = None,
                      log=print) -> list[ForecastRow]:
    """Run the campaign in rounds (every group's r-th test before any (r+1)-th), each test with
    the §7a prior from the earlier ones; returns one row per test."""
    from drivers.sim.plant import table_life
    from gateway.core.method.core import analyze_readings
    from gateway.core.method.forecast import band_at_half_life
    from gateway.core.method.params import build_params
    from gateway.core.method.prior import PastTest, resolve_prior

    times = {k: v / compress for k, v in FULL_SCALE_TIMES.items()}
    history: list[PastTest] = []
    rows: list[ForecastRow] = []
    i = 0
    for r in range(1, reps + 1):
        for sp in setpoints:
            for g in grades:
                i += 1
                sid = f"{g}-{int(round(sp * 10)):02d}-{r:02d}"
                m, sd = table_life(g, sp)
                # long enough for every life the plant can draw (mean + 5 SD, +10 %), no longer
                duration = round((m + 5 * sd) * 1.1 / compress, 1)
                t, a, b, truth = plant_run(g, sp, seed0 + i, duration, compress)
                prior = resolve_prior([], history, g, sp)
                method = {"t_set": sp, "t_end": duration, **times}
                if prior.mean is not None:
                    method.update(prior_mean=prior.mean, prior_sd=prior.sd)
                p = build_params(method)
                res = analyze_readings(t, a, b, p)
                # §7a: a failure, or a right-censored life (a baseline, then t_end: no_failure)
                history.append(PastTest(g, sp, res.status, res.t_life, k_b=res.k_b,
                                        stop_reasons=None if res.stop_reasons is None
                                        else tuple(res.stop_reasons), n_slots=res.n_slots, ts=p.ts))
                band = None
                if res.t_life is not None and prior.mean is not None and prior.sd is not None:
                    f = band_at_half_life(res.t_life, prior.mean, prior.sd, p.lead, p.n_ss * p.ts)
                    band = None if f is None else (f.e10, f.e90)
                row = ForecastRow(sid, g, sp, (prior.mean or 0.0, prior.sd or 0.0, prior.source, prior.n),
                                  truth["cross_run_s"], res.status, res.t_life, res.k_life,
                                  None if res.warn_slot is None else (res.warn_slot + 1) * p.ts,
                                  res.warn_slot, res.warn_reasons, p.lead, band)
                rows.append(row)
                if out is not None:
                    _write_forecast_test(out, i, row, t, a, b, method, res.as_dict(), prior.source, prior.n)
                log(_row_line(row))
    return rows


def _write_forecast_test(root: str, i: int, row: ForecastRow, t, a, b, method: dict, res: dict,
                         source: str | None, n: int | None) -> None:
    import yaml

    test_id = f"20260201T{(i // 60) % 24:02d}{i % 60:02d}00Z-{row.sample_id}"
    d = os.path.join(root, PLANT_STATION, test_id)
    write_log_plain(os.path.join(d, "log.csv.gz"), t, a, b)
    meta = {"station": PLANT_STATION, "test_id": test_id, "sample_id": row.sample_id,
            "grade": row.grade, "t_set": row.t_set, "software": "bench/gen_campaign.py --forecast",
            "prior_source": source, "prior_n": n, "method": method}
    with open(os.path.join(d, "log.meta.yaml"), "w", encoding="utf-8") as f:
        yaml.safe_dump(meta, f, sort_keys=False)
    with open(os.path.join(d, "result.json"), "w", encoding="utf-8") as f:
        json.dump({"test_id": test_id, "station": PLANT_STATION, "test_status": "completed",
                   "end_reason": "completed", "sample_id": row.sample_id, "grade": row.grade,
                   "t_set": row.t_set, "ts": method.get("ts", 0.02), "t_end": method.get("t_end"),
                   "method": res}, f, indent=1)


def _row_line(r: ForecastRow) -> str:
    pm, ps, src, n = r.prior
    prior = f"prior {pm:7.1f} ± {ps:5.1f} s ({src}, n {n})" if src else "no prior" + " " * 30
    tl = "-" if r.t_life is None else f"{r.t_life:7.1f}"
    w = "no warning" if r.warn_s is None else (
        f"warned {r.warn_s:7.1f} s by {'+'.join(r.reasons or [])}, {r.lead_s:+7.1f} s ahead")
    band = "" if r.band is None else f"; half-life band [{r.band[0]:.1f}, {r.band[1]:.1f}]"
    return f"  {r.sample_id:9s} {prior}  t_life {tl} (plant {r.truth_life:7.1f})  {w}{band}"


def _pct(k: int, n: int) -> str:
    return "-" if n == 0 else f"{100.0 * k / n:.1f} % ({k}/{n})"


def forecast_summary(rows: list[ForecastRow]) -> dict[str, str]:
    fails = [r for r in rows if r.t_life is not None]
    with_prior = [r for r in fails if r.prior[2] is not None]
    ahead = [r for r in with_prior if r.lead_s is not None and r.lead_s >= r.lead]
    ahead_all = [r for r in fails if r.lead_s is not None and r.lead_s >= r.lead]
    banded = [r for r in with_prior if r.band is not None]
    inside = [r for r in banded if r.band is not None and r.t_life is not None
              and r.band[0] <= r.t_life <= r.band[1]]
    return {
        "tests": f"{len(rows)} ({len(fails)} failures, {len(with_prior)} with a prior from earlier tests)",
        "warned >= lead ahead (with a prior)": _pct(len(ahead), len(with_prior)) + "  [goal >= 90 %]",
        "warned >= lead ahead (all failures)": _pct(len(ahead_all), len(fails)),
        "warnings after an end of life": f"{sum(r.late for r in rows)}  [goal 0]",
        "t_life in [e10, e90] at half-life": _pct(len(inside), len(banded)) + "  [goal 70-90 %]",
        "lead": f"{rows[0].lead:g} s" if rows else "-",
    }


def write_log_plain(path: str, t: np.ndarray, t1: np.ndarray, t2: np.ndarray) -> None:
    """Like :func:`write_log` with times on the slot grid (2 decimals) — smaller files."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with gzip.open(path, "wt", compresslevel=9) as f:
        f.write("t,T1,T2\n")
        np.savetxt(f, np.column_stack([t, t1, t2]), fmt=("%.2f", "%.3f", "%.3f"), delimiter=",")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", nargs="?", help="campaign folder to write (optional with --forecast)")
    ap.add_argument("--compress", type=float, default=100.0,
                    help="divide lives and windows by this (1: real 10 h tests)")
    ap.add_argument("--hours", type=float, default=10.0, help="t_end before compression")
    ap.add_argument("--layout", choices=("flat", "gateway"), default="flat")
    ap.add_argument("--no-wear", action="store_true")
    ap.add_argument("--no-control", action="store_true")
    ap.add_argument("--source", choices=("synth", "plant"), default="synth",
                    help="synth: this file's curves (fast, any size); plant: the virtual bench "
                         "(drivers/sim/plant.py) under the gateway's controller, lives compressed "
                         "--compress× (the shipped example: --source plant --compress 100)")
    ap.add_argument("--forecast", action="store_true",
                    help="the remaining-life bench (METHOD.md §5b, §7a): plant tests in rounds, "
                         "priors from the earlier ones, figures printed (default --compress 40)")
    ap.add_argument("--reps", type=int, default=6, help="--forecast: tests per grade and T_set")
    a = ap.parse_args()
    if a.forecast:
        import time

        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        compress = a.compress if "--compress" in sys.argv else 40.0
        t0 = time.perf_counter()
        print(f"remaining-life bench: {a.reps} tests per grade and T_set, lives and method times "
              f"compressed {compress:g}x (w_ss {60 / compress:g} s, w_hold {3600 / compress:g} s, "
              f"tau {60 / compress:g} s, lead {3600 / compress:g} s)")
        rows = forecast_campaign(compress=compress, reps=a.reps, out=a.out)
        for k, v in forecast_summary(rows).items():
            print(f"{k:38s} {v}")
        print(f"{time.perf_counter() - t0:.0f} s")
        return
    if a.out is None:
        ap.error("the campaign folder is required (except with --forecast)")
    if a.source == "plant":
        sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        logs = make_plant_campaign(a.out, time_scale=a.compress, t_end=a.hours * 3600.0 / a.compress)
    else:
        logs = make_campaign(a.out, compress=a.compress, hours=a.hours, layout=a.layout,
                             wear=not a.no_wear, control=not a.no_control)
    print(f"{len(logs)} logs in {a.out}")


if __name__ == "__main__":
    main()
