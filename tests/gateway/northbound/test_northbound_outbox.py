"""The on-disk outbox: order, confirmation, restart, telemetry budget, superseded states."""
import sqlite3

from gateway.northbound.outbox import Outbox, Row

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
