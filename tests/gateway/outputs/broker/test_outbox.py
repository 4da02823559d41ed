"""The on-disk outbox: order, confirmation, restart, telemetry budget, superseded states."""
import sqlite3

from gateway.outputs.broker.outbox import Outbox, Row

TELEMETRY_BYTES = "SELECT SUM(LENGTH(payload)+LENGTH(topic)+64) FROM messages WHERE kind='telemetry'"


def _rows(ob, kinds, size=100):
    out = []
    for k in kinds:
        s = ob.next_seq()
        out.append(Row(s, k, f"t/{k}", (f'{{"seq":{s}}}'.ljust(size)).encode(), 1, k == "state"))
    return out


def test_order_confirm_and_restart(tmp_path):
    p = str(tmp_path / "ob.sqlite")
    ob = Outbox(p)
    rows = _rows(ob, ["event", "telemetry", "state", "alarm", "telemetry", "result"])
    ob.add(rows)
    assert [r.seq for r in ob.pending(0, 100)] == [1, 2, 3, 4, 5, 6]
    assert [r.seq for r in ob.pending(2, 2)] == [3, 4]
    assert ob.table.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    ob.confirm([1, 2])
    assert [r.seq for r in ob.pending(0, 100)] == [3, 4, 5, 6]
    ob.close()
    # a restart resends what is not confirmed, and the sequence goes on
    ob = Outbox(p)
    assert [r.seq for r in ob.pending(0, 100)] == [3, 4, 5, 6]
    assert ob.next_seq() == 7
    got = ob.pending(0, 1)[0]
    assert (got.kind, got.topic, got.retain) == ("state", "t/state", True)
    ob.confirm([3, 4, 5, 6])
    ob.close()
    # everything confirmed: the counter still survives (7 was reserved, never stored: reused)
    ob = Outbox(p)
    assert ob.count() == 0 and ob.next_seq() == 7
    ob.close()


def test_a_newer_state_supersedes_unsent_ones_but_not_sent_ones(tmp_path):
    ob = Outbox(str(tmp_path / "ob.sqlite"))
    ob.add(_rows(ob, ["state", "event"]))                   # 1 2
    ob.add(_rows(ob, ["state"]), sent_upto=2)               # 3 (1 is in flight: kept)
    # 1 and 2 handed to the client already; 3 not: a new state drops 3 only
    ob.add(_rows(ob, ["state", "telemetry"]), sent_upto=2)  # 4 5
    assert [(r.seq, r.kind) for r in ob.pending(0, 10)] == [(1, "state"), (2, "event"), (4, "state"),
                                                           (5, "telemetry")]
    assert ob.superseded_states == 1
    ob.close()


def test_over_budget_the_oldest_telemetry_goes_first_and_events_never(tmp_path):
    ob = Outbox(str(tmp_path / "ob.sqlite"), telemetry_budget_bytes=20_000)
    kinds = []
    for i in range(400):
        kinds.append("event" if i % 10 == 0 else "telemetry")
    for i in range(0, 400, 40):
        ob.add(_rows(ob, kinds[i:i + 40], size=200), sent_upto=0)
    left = ob.pending(0, 10_000)
    ev = [r.seq for r in left if r.kind == "event"]
    tel = [r.seq for r in left if r.kind == "telemetry"]
    assert len(ev) == 40                             # no event lost
    assert ob.telemetry_bytes <= 20_000
    assert len(tel) < 360 and ob.dropped_telemetry == 360 - len(tel)
    # the survivors are the newest telemetry
    all_tel = [i + 1 for i, k in enumerate(kinds) if k == "telemetry"]
    assert tel == all_tel[-len(tel):]
    # the running byte count matches the table
    real = ob.table.db.execute(TELEMETRY_BYTES).fetchone()[0]
    assert real == ob.telemetry_bytes
    ob.confirm(tel[:5])
    real = ob.table.db.execute(TELEMETRY_BYTES).fetchone()[0]
    assert real == ob.telemetry_bytes
    ob.close()


def test_in_flight_telemetry_is_not_trimmed(tmp_path):
    ob = Outbox(str(tmp_path / "ob.sqlite"), telemetry_budget_bytes=3_000)
    ob.add(_rows(ob, ["telemetry"] * 10, size=200))
    ob.add(_rows(ob, ["telemetry"] * 10, size=200), sent_upto=10)
    seqs = [r.seq for r in ob.pending(0, 100)]
    assert seqs[:10] == list(range(1, 11))             # in flight: kept until confirmed
    ob.close()


def test_meta_and_a_second_reader(tmp_path):
    p = str(tmp_path / "ob.sqlite")
    ob = Outbox(p)
    ob.add(_rows(ob, ["alarm"]), meta={"alarm": {"state": "active"}})
    assert ob.meta_get("alarm") == {"state": "active"}
    # WAL: another connection reads while the outbox is open
    con = sqlite3.connect(p)
    assert con.execute("SELECT COUNT(*) FROM messages").fetchone()[0] == 1
    con.close()
    ob.close()


def test_meta_int_reads_back_the_counters_kept_there_and_nothing_else(tmp_path):
    """The engines' counters in the meta table (the status session, Sparkplug's bdSeq) read back
    typed, across a reopen; a value that is not an integer (or none) reads as None."""
    p = str(tmp_path / "ob.sqlite")
    ob = Outbox(p)
    ob.add([], meta={"status_session": 7, "bdseq": 0, "probe": 1.5, "flag": True, "name": "7"})
    ob.close()
    ob = Outbox(p)
    assert (ob.meta_int("status_session"), ob.meta_int("bdseq")) == (7, 0)
    assert [ob.meta_int(k) for k in ("probe", "flag", "name", "missing")] == [None] * 4
    assert (ob.meta_get("probe"), ob.meta_get("name")) == (1.5, "7")
    ob.close()


def test_the_reserve_holds_what_is_not_telemetry_within_its_bound():
    """The disk-full state's reserve (gateway/outputs/broker/outbox_reserve.py) without a disk: new
    telemetry is refused and counted, a newer state supersedes the unsent older ones, beyond
    RESERVE_MAX_ROWS the oldest rows go (counted), confirmed rows leave it, the others are
    handed back for the disk."""
    from gateway.outputs.broker.outbox_reserve import RESERVE_MAX_ROWS, DiskFullReserve

    r = DiskFullReserve("ob.sqlite")
    rows = [Row(s, k, f"t/{k}", b"{}") for s, k in enumerate(["state", "telemetry", "event", "state"], 1)]
    r.hold(rows, {"status_session": 3}, sent_upto=0)
    assert [x.seq for x in r.after(0)] == [3, 4] and r.refused_telemetry == 1 and r.superseded_states == 1
    assert r.meta == {"status_session": 3} and (r.count(), r.count("state"), r.count("event")) == (2, 1, 1)
    assert r.take_confirmed([3, 99]) == [99] and [x.seq for x in r.after(0)] == [4]
    r.hold([Row(s, "event", "t/event", b"{}") for s in range(5, 5 + RESERVE_MAX_ROWS)], None, sent_upto=0)
    assert r.count() == RESERVE_MAX_ROWS and r.lost_rows == 1
    assert r.after(0)[0].seq == 5 and r.after(0)[-1].seq == 4 + RESERVE_MAX_ROWS


def test_the_disk_state_reports_each_change_once_and_survives_its_callback(caplog):
    """A failed write turns the state FAILED (reported once, one log line), further failures are
    counted only; a recovery reports what was held and refused. A callback that raises is logged,
    never passed on."""
    import logging

    from gateway.outputs.broker.outbox_reserve import DiskFullReserve

    caplog.set_level(logging.ERROR, "hookwatch.outbox")
    r = DiskFullReserve("ob.sqlite")
    seen: list[tuple[bool, dict]] = []
    r.on_disk_state = lambda ok, info: seen.append((ok, info))
    full = sqlite3.OperationalError("database or disk is full")
    r.failed(full)
    r.failed(full)
    r.hold([Row(1, "telemetry", "t/telemetry", b"{}"), Row(2, "event", "t/event", b"{}")], None, 0)
    assert not r.disk_ok and r.write_errors == 2
    assert seen == [(False, {"reason": "database or disk is full"})]
    assert len([x for x in caplog.records if "cannot write" in x.getMessage()]) == 1
    r.recovered(rows_written=1)
    assert r.disk_ok and r.count() == 0 and seen[-1][0] is True
    assert {k: seen[-1][1][k] for k in ("rows_written", "refused_telemetry", "lost_rows")} == {
        "rows_written": 1, "refused_telemetry": 1, "lost_rows": 0}

    def boom(ok, info):
        raise RuntimeError("callback fault")
    r.on_disk_state = boom
    r.failed(full)                       # logged, not raised
    assert not r.disk_ok and any("disk state callback failed" in x.getMessage() for x in caplog.records)
