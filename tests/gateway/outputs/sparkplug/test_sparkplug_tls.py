"""The Sparkplug edge node over mutual TLS to a real Mosquitto; a TLS set-up that fails (missing CA
file) is a state: logged once, retried, no crash, no bdSeq used up."""
import logging

from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import SparkplugOutput
from kit.broker import Broker
from kit.certs import make_certs as _certs
from kit.northbound import LoopThread, RunningStation, make_station
from kit.sparkplug_host import PrimaryHost
from kit.tools import wait_for


def test_edge_node_over_mutual_tls_and_a_missing_ca_file(tmp_path, caplog):
    c = _certs(tmp_path)
    b = Broker(tmp_path)
    b.conf.write_text(b.conf.read_text() + f"cafile {c['ca.crt']}\ncertfile {c['server.crt']}\n"
                      f"keyfile {c['server.key']}\nrequire_certificate true\n")
    lt = LoopThread()
    with b:
        host = PrimaryHost(b.port, "h", "g", tmp_path,
                           tls={"ca": c["ca.crt"], "cert": c["client.crt"], "key": c["client.key"]})
        run = None
        try:
            st = make_station(tmp_path, [], station_id="tls-1")
            st.outputs.append(SparkplugOutput(SparkplugSettings(
                group_id="g", edge_node_id="n", device_id="tls-1", servers=[("127.0.0.1", b.port)],
                store_path=str(tmp_path / "a.sqlite"), tls_enabled=True, ca_file=c["ca.crt"],
                cert_file=c["client.crt"], key_file=c["client.key"], gather_s=0.0), st))
            run = RunningStation(lt, st)
            host.wait(lambda: host.all("DDATA"), 30, "DDATA over TLS")
            assert [m.kind for m in host.all()[:2]] == ["NBIRTH", "DBIRTH"]
            run.stop()
            run = None
            # a CA file that is not there: logged, retried, no crash, no bdSeq used
            caplog.set_level(logging.ERROR, logger="hookwatch.sparkplug")
            st2 = make_station(tmp_path, [], station_id="tls-2")
            out = SparkplugOutput(SparkplugSettings(
                group_id="g", edge_node_id="n2", device_id="tls-2", servers=[("127.0.0.1", b.port)],
                store_path=str(tmp_path / "b.sqlite"), tls_enabled=True,
                ca_file=str(tmp_path / "missing.crt"), reconnect_min_s=0.1, reconnect_max_s=0.2,
                gather_s=0.0), st2)
            st2.outputs.append(out)
            run = RunningStation(lt, st2)
            wait_for(lambda: out.rt is not None and out.rt.counters["tls_errors"] >= 3, 20,
                     what="TLS retries")
            assert out.rt.node.bdseq.fresh, "no CONNECT was sent: bdSeq 0 is still unused"
            assert out.rt._thread.is_alive()
            assert sum("TLS set-up failed" in r.getMessage() for r in caplog.records) == 1
        finally:
            if run is not None:
                run.stop()
            lt.close()
            host.close()
