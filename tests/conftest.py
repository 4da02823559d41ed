"""Shared test setup. Tests mirror the package tree (tests/gateway/..., tests/drivers/...); the
shared kit is tests/kit/ (process stop, Mosquitto, the virtual station and meter, fakes), offered
here as fixtures too."""
import os
import sys

import pytest

HERE = TESTS = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
VECTORS = os.path.join(HERE, "vectors")
VENV_BIN = os.path.join(ROOT, ".venv", "bin")

# the project before tests/ (tests/gateway must never shadow the gateway package), and tests/
# for `kit` and `conftest` from any depth
for _p in (HERE, ROOT):
    if _p in sys.path:
        sys.path.remove(_p)
    sys.path.insert(0, _p)


def hookwatch_cmd() -> list[str]:
    """The console command as a user runs it (the venv's, else the one on PATH)."""
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    if os.path.exists(exe):
        return [exe]
    return [sys.executable, "-m", "gateway.cli"]


# ------------------------------------------------------------------------------------ fixtures

#: the worker's shared RabbitMQ cluster (``rabbitmq_cluster``)
pytest_plugins = ("kit.rabbitmq_pool",)


@pytest.fixture(autouse=True)
def _no_process_outlives_its_test():
    """A gateway left running by a test that ended (an assertion, a test that stops its simulator
    first) keeps reopening its ports by path, and a pseudo-terminal's number is soon reused by the
    next test's simulator: that gateway then locks the new test's STM32 port and reads its meter
    (seen twice in parallel runs). Every Proc a test started and did not stop is stopped here
    (the module-scoped fixtures' ones, started before, are left to their fixtures)."""
    from kit.proc import LIVE
    before = set(LIVE)
    yield
    for p in list(LIVE):
        if p not in before:
            p.stop(timeout=10)


@pytest.fixture
def broker(tmp_path):
    """A running Mosquitto on a free loopback port (kit.broker.Broker), stopped after the test."""
    from kit.broker import Broker

    with Broker(tmp_path) as b:
        yield b


@pytest.fixture
def virtual_station(tmp_path):
    """Starts `hookwatch sim SCENARIO` (kit.e2e.virtual_station): call it with the scenario path;
    yields (process, links). Stopped after the test."""
    import contextlib

    from kit.e2e import virtual_station as _vs

    with contextlib.ExitStack() as stack:
        yield lambda scenario, **kw: stack.enter_context(_vs(tmp_path, scenario, **kw))


@pytest.fixture
def browser():
    """Playwright driving Debian's chromium (kit.browser.launch): skipped where either is
    missing, failed in CI."""
    from kit.browser import launch

    with launch() as b:
        yield b


@pytest.fixture
def fake_meter():
    from kit.fakes import FakeMeter

    return FakeMeter()


@pytest.fixture
def fake_stm32():
    from kit.fakes import FakeStm32

    return FakeStm32()


@pytest.fixture
def loop_thread():
    """An asyncio loop in its own thread (kit.northbound.LoopThread), closed after the test."""
    from kit.northbound import LoopThread

    lt = LoopThread()
    yield lt
    lt.close()


# ------------------------------------------------------------------------ the suite's schedule
# `./run-tests` runs the suite on pytest-xdist workers (`-n 4 --dist loadgroup`): most tests wait
# on real time (50 Hz stations, simulated lives), so several run side by side on two cores. The
# tables below say, in one place, which tests are long (`slow`: left out of the quick loop
# `-m "not slow"`) and which must share a worker (`xdist_group`). No module marks itself: this is
# the one declaration (tests/test_suite_schedule.py checks that, and that every entry names a test
# that exists).

#: long on the wall clock (a gateway with a fleet, a browser, a campaign report, a fuzzed live
#: server, hypothesis at thousands of examples): module → test functions, "*" for all of them
SLOW: dict[str, tuple[str, ...]] = {
    # the end-to-end lives: a virtual station and a gateway over ptys, a compressed life each
    **{m: ("*",) for m in (
        "tests/gateway/supervisor/test_supervisor_e2e.py",
        "tests/gateway/supervisor/test_supervisor_shared_e2e.py",
        "tests/gateway/supervisor/test_supervisor_realtime.py",
        "tests/gateway/supervisor/test_supervisor_sparkplug_e2e.py",
        "tests/gateway/outputs/test_forecast_doors_e2e.py",
        "tests/gateway/outputs/test_outputs_disk_state.py",
        "tests/gateway/outputs/mqtt/test_mqtt_cutoff_result.py",
        "tests/gateway/outputs/test_outputs_e2e.py",
        "tests/gateway/outputs/sparkplug/test_sparkplug_doors_e2e.py",
        "tests/gateway/outputs/sparkplug/test_sparkplug_e2e.py",
        "tests/gateway/outputs/test_wear_e2e.py",
        "tests/gateway/outputs/mqtt/test_site_lives_e2e.py",
        "tests/gateway/outputs/test_site_lives_churn_e2e.py",
        "tests/gateway/outputs/test_site_lives_store_e2e.py",
        "tests/gateway/outputs/test_acl_prior_e2e.py",
        "tests/gateway/outputs/test_prior_early_e2e.py",
        "tests/gateway/outputs/test_command_replay_e2e.py",
        "tests/gateway/outputs/mqtt/test_mqtt_rabbitmq_cluster_e2e.py",
        "tests/gateway/station/test_stall_e2e.py",
        "tests/gateway/station/test_station_start_e2e.py",
        "tests/gateway/station/test_station_e2e.py",
        "tests/gateway/station/test_station_independent_slave.py",
        "tests/gateway/station/test_fleet_e2e.py",
        "tests/gateway/station/test_fleet_crash_restart.py",
        "tests/gateway/cli/test_reload_hostile_yaml.py",
        "tests/gateway/cli/test_reload_e2e.py",
        # issue 37: a box from a site repository (a supervisor, 2 virtual stations, Mosquitto)
        "tests/gateway/config/test_site_apply_e2e.py",
        "tests/deploy/test_release.py",
        "tests/deploy/test_setup.py",
        # the site rolled out by ansible-playbook to three boxes, each a supervisor and a station
        "tests/deploy/test_ansible_site.py")},
    "tests/gateway/station/test_retention_e2e.py": ("test_retention_over_many_short_tests_on_a_small_disk",),
    "tests/gateway/station/test_recorder_disk.py": (
        "test_station_on_a_disk_filled_then_freed_mid_test",
        "test_station_folder_unwritable_mid_test_completes_and_keeps_its_result"),
    "tests/gateway/station/test_lost_slots_e2e.py": ("test_disk_full_longer_than_the_reserve_offline_equals_online",),
    "tests/gateway/cli/test_check_probe.py": (
        "test_the_probe_beside_a_running_station_costs_it_no_slot_and_names_it",),
    "tests/gateway/core/method/test_method_property.py": (
        "test_streaming_equals_batch", "test_streaming_equals_batch_past_the_baseline",
        "test_streaming_equals_batch_with_lost_slots"),
    "tests/gateway/offline/report/test_report_campaign.py": (
        "test_report_has_every_table_and_figure", "test_report_tables_match_the_campaign",
        "test_one_and_two_processes_give_the_same_tables", "test_gateway_layout_and_gateway_aborted_tests",
        "test_shipped_example_campaign_gives_a_full_report"),
    "tests/gateway/offline/report/test_report_bad_input.py": ("*",),
    "tests/gateway/offline/report/test_report_wear.py": ("*",),
    "tests/gateway/outputs/plc/test_plc_server.py": (
        "test_malformed_frames_never_stop_the_server", "test_server_alive_after_fuzzing_and_no_write_got_through"),
    "tests/gateway/outputs/test_command_intake_doors.py": (
        "test_fuzzed_mqtt_commands_each_get_one_small_reply_and_the_link_stays_up",
        "test_after_fuzzing_the_station_still_answers_and_events_are_bounded"),
    "tests/gateway/outputs/plc/test_modbus_tcp.py": (
        "test_1100_idle_sockets_under_a_low_fd_limit_do_not_lock_out_the_plc",),
    "tests/gateway/outputs/prometheus/test_metrics_prometheus.py": ("*",),
    "tests/gateway/outputs/prometheus/test_metrics_fleet.py": ("*",),
    "tests/gateway/outputs/prometheus/test_metrics_outputs.py": ("*",),
    "tests/gateway/outputs/mqtt/test_mqtt.py": (
        "test_broker_outage_and_gateway_restart_deliver_every_event_in_order_once",),
    "tests/gateway/outputs/console/test_console_http.py": (
        "test_console_history_fig7_downloads_and_campaign", "test_console_slow_client_dropped_fast_client_served",
        "test_console_http_auth_csrf_commands_lockout"),
    "tests/gateway/outputs/console/test_console_browser.py": ("*",),
    # the site view: chromium and three gateways on one Mosquitto; hookwatch run (a station, a fleet)
    "tests/gateway/outputs/console/test_console_site_browser.py": ("*",),
    # issue 37: the Boxes page, chromium and three boxes' report publishers on one Mosquitto
    "tests/gateway/outputs/console/test_console_boxes_browser.py": ("*",),
    "tests/gateway/outputs/console/test_console_feed.py": (
        "test_ten_hour_series_is_bounded_and_keeps_a_one_slot_spike",),
    "tests/gateway/cli/test_console_demo.py": ("*",),
    "tests/gateway/core/test_alarms_isa182.py": ("test_every_transition_is_one_event_and_the_record_reads_back",),
    "tests/deploy/test_deploy.py": ("test_gateway_speaks_the_units_notify_protocol",),
    # the shipped permissions applied by rabbitmqctl (~6 s a call on the 2-core box) on the cluster
    "tests/deploy/test_deploy_acl.py": ("test_rabbitmq_topic_permissions_refuse_a_forging_box_and_hold_a_gateway",),
    "tests/drivers/sim/test_plant.py": ("test_closed_loop_holds_setpoint_open_loop_wanders",),
    "tests/drivers/sim/test_sim.py": ("test_sim_process_prints_paths_and_each_fault_fires_on_the_wire",),
    # the door floods, the planner's browser walk and three gateways started for one check:
    # 10–67 s each (the quick loop took 3 min 13 s with them, 2026-11-26)
    "tests/gateway/outputs/console/test_console_planner_browser.py": (
        "test_journal_actions_and_hook_replaced_reach_a_real_station",),
    "tests/gateway/supervisor/test_doors_flood_e2e.py": ("*",),
    "tests/gateway/plumbing/test_doors_station_e2e.py": ("*",),
    # 300 re-opened idle sockets against the console and the metrics door (5–8 s each)
    "tests/gateway/plumbing/test_doors_fair.py": (
        "test_300_reopened_idle_sockets_from_one_address_do_not_starve_the_operators_console",
        "test_300_reopened_idle_sockets_from_one_address_do_not_starve_prometheus"),
    "tests/gateway/outputs/test_refusal_flood.py": ("*",),
    "tests/gateway/outputs/console/test_console_command_intake.py": ("*",),
    "tests/gateway/supervisor/test_supervisor_emfile.py": ("*",),
    "tests/drivers/serial/test_adapters.py": (
        "test_the_gateway_on_an_echoing_adapter_starts_a_test_only_with_local_echo",),
}

#: CPU-bound (no real-time wait): one after another on one worker, so that they never take both
#: cores from the real-time tests at once; and the modules whose tests share a module-scoped
#: fixture (a campaign, a running plant) or build on each other in order stay on one worker
CPU_GROUP = "cpu"
CPU: dict[str, tuple[str, ...]] = {
    "tests/gateway/core/method/test_method_property.py": ("*",),
    "tests/gateway/core/method/test_method_vectors.py": ("*",),
    "tests/gateway/core/method/test_prior_mle.py": ("*",),
    "tests/gateway/core/method/test_prior_early.py": ("*",),
    "tests/gateway/offline/report/test_report_priors_campaign.py": ("*",),
    "tests/gateway/offline/report/test_report_campaign.py": ("*",),
    "tests/gateway/offline/report/test_report_bad_input.py": ("*",),
    "tests/gateway/offline/report/test_report_wear.py": ("*",),
    "tests/gateway/offline/report/test_report_figures.py": ("*",),
    "tests/gateway/outputs/plc/test_plc_server.py": ("*",),
    "tests/gateway/outputs/test_command_intake_doors.py": ("*",),
    "tests/gateway/outputs/console/test_console_feed.py": (
        "test_ten_hour_series_is_bounded_and_keeps_a_one_slot_spike",),
    "tests/gateway/supervisor/test_supervisor_ipc.py": (
        "test_stalled_consumer_never_blocks_the_station_and_is_bounded",),
}
#: the site rolled out by ansible-playbook to three boxes (a supervisor and a virtual station
#: each): its own unit, among the first, beside the fleets — in the fleet group it made that
#: serial group (and so the run) as long as the fleets plus itself (ci: 765 s against 720). Its
#: three stations run at 50 Hz with STALL_TOLERANT methods; the fleets beside it keep to one worker
ANSIBLE_LAB = "tests/deploy/test_ansible_site.py"
#: module-scoped fixtures outside the CPU group, and the Ansible lab: the module's own worker
MODULE_GROUPS = ("tests/gateway/outputs/plc/test_modbus_tcp.py", ANSIBLE_LAB)
#: tests of several modules that share one worker's costly fixture: group → module → test functions
SHARED_GROUPS: dict[str, dict[str, tuple[str, ...]]] = {
    # one 3-node RabbitMQ cluster per worker (~1 min to start: tests/kit/rabbitmq_pool.py)
    "rabbitmq": {
        "tests/gateway/outputs/mqtt/test_mqtt_rabbitmq_cluster_e2e.py": ("*",),
        "tests/gateway/outputs/mqtt/test_site_lives_e2e.py": (
            "test_box_b_joining_through_another_rabbitmq_node_gets_the_site_prior_of_box_a",),
        "tests/deploy/test_deploy_acl.py": (
            "test_rabbitmq_topic_permissions_refuse_a_forging_box_and_hold_a_gateway",),
    },

}
#: fleets of virtual stations (several `hookwatch sim` + a gateway carrying 3–4 stations at 50 Hz):
#: one after another on one worker — two at once are 8 stations and 8 simulators on two cores,
#: where the stations' slots go MISSING by the second (their protection stops end the lives)
FLEET_GROUP = "fleet"
FLEETS = (
    "tests/gateway/station/test_fleet_e2e.py",
    "tests/gateway/station/test_fleet_crash_restart.py",
    "tests/gateway/supervisor/test_supervisor_e2e.py",
    "tests/gateway/supervisor/test_supervisor_shared_e2e.py",
    "tests/gateway/supervisor/test_supervisor_sparkplug_e2e.py",
    # one station with every door at once (MQTT, Sparkplug, PLC, metrics + Prometheus, console):
    # as heavy as a fleet; beside one, its compressed life ended in protection stops (ci runs 4, 5)
    "tests/gateway/outputs/test_forecast_doors_e2e.py",
    "tests/gateway/cli/test_console_demo.py",
    # two stations at 50 Hz under a flood of 600 lives snapshots of 115 KB through the broker, and
    # a site-managed box (a supervisor with two workers and their twins, issue 37). Beside the
    # fleets in a unit of their own the run was no shorter (ci 716 s against 684 s) and more of
    # its stations met load: one after another here
    "tests/gateway/outputs/test_site_lives_churn_e2e.py",
    "tests/gateway/config/test_site_apply_e2e.py",
)


#: the longest units of work (an xdist group, or a module of no group) with their seconds on a
#: quiet 2-core box (`./run-tests --durations=0`, 2026-11-27): ORDER ONLY, never asserted. The
#: workers take whole units from the front of the queue (`--dist loadgroup` with
#: `--no-loadscope-reorder`, run-tests), so the longest go first and the short ones fill the
#: gaps at the end (longest processing time first); without it xdist ordered the units by their
#: number of tests, and the 3-minute broker outage life began 6 minutes in, on the critical path
LONGEST_FIRST: dict[str, int] = {
    ANSIBLE_LAB: 430,           # alone at load 3, 2026-11-29 (its release build included)
    FLEET_GROUP: 580,
    "rabbitmq": 230,
    "tests/gateway/outputs/test_outputs_e2e.py": 215,
    "tests/gateway/station/test_station_e2e.py": 185,
    "tests/deploy/test_release.py": 165,
    CPU_GROUP: 150,
    "tests/gateway/station/test_station_start_e2e.py": 95,
    "tests/gateway/outputs/test_site_lives_store_e2e.py": 100,
    "tests/gateway/station/test_stall_e2e.py": 85,
    "tests/gateway/outputs/console/test_console_http.py": 65,
    "tests/gateway/outputs/test_command_replay_e2e.py": 65,
    "tests/gateway/station/test_retention_e2e.py": 60,
    "tests/gateway/plumbing/test_doors_station_e2e.py": 47,
    "tests/gateway/outputs/console/test_console_browser.py": 45,
    "tests/gateway/outputs/test_wear_e2e.py": 42,
    "tests/gateway/station/test_lost_slots_e2e.py": 42,
    "tests/gateway/station/test_recorder_disk.py": 41,
    "tests/gateway/outputs/sparkplug/test_sparkplug_e2e.py": 40,
    "tests/gateway/outputs/test_prior_early_e2e.py": 50,
    "tests/gateway/outputs/console/test_console_planner_browser.py": 36,
    "tests/deploy/test_setup.py": 32,
    "tests/gateway/outputs/test_refusal_flood.py": 30,
}


def _listed(table: dict[str, tuple[str, ...]], path: str, name: str) -> bool:
    names = table.get(path, ())
    return "*" in names or name in names


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """Marks each test by the tables above. First of all plugins: pytest-xdist's worker names a
    test's group in its node ID (``…@group``, what `--dist loadgroup` schedules by) in its own
    pytest_collection_modifyitems, from the marks as they are then — a group marked after it is
    no group (tests/test_suite_schedule.py)."""
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        name = getattr(item, "originalname", None) or item.name.split("[", 1)[0]
        if _listed(SLOW, path, name):
            item.add_marker(pytest.mark.slow)
        if _listed(CPU, path, name):
            item.add_marker(pytest.mark.xdist_group(CPU_GROUP))
        elif path in MODULE_GROUPS:
            item.add_marker(pytest.mark.xdist_group(path))
        elif shared := [g for g, table in SHARED_GROUPS.items() if _listed(table, path, name)]:
            item.add_marker(pytest.mark.xdist_group(shared[0]))
        elif path in FLEETS:
            item.add_marker(pytest.mark.xdist_group(FLEET_GROUP))
    # the longest units first (LONGEST_FIRST), then the other modules with long tests, so that
    # the workers end together on short ones rather than one worker on a long life at the end;
    # each unit stays whole and in its own order (module-scoped fixtures, tests that build on
    # the one before): the sort is stable
    has_slow = {it.nodeid.split("::", 1)[0] for it in items if it.get_closest_marker("slow")}

    def order(it: pytest.Item) -> tuple[int, bool]:
        path = it.nodeid.split("::", 1)[0]
        g = it.get_closest_marker("xdist_group")
        unit = str(g.args[0]) if g is not None and g.args else path
        return -LONGEST_FIRST.get(unit, 0), path not in has_slow
    items.sort(key=order)
