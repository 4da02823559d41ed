"use strict";
// hookwatch operator console: fleet, station (live), history. No build step, no external assets.
(function () {
  const $ = (s, el) => (el || document).querySelector(s);
  const main = $("#main");
  const session = { user: null, csrf: null };
  const hw = window.hw = { points: 0, snapshots: 0, updates: 0 };
  let cleanup = [];

  function esc(s) { return String(s == null ? "" : s).replace(/[&<>"']/g, c => ({"&":"&amp;","<":"&lt;",">":"&gt;","\"":"&quot;","'":"&#39;"}[c])); }
  function fmt(x, nd) { return (x == null || !isFinite(x)) ? "–" : Number(x).toFixed(nd == null ? 4 : nd); }
  function say(text, ok) { const m = $("#msg"); m.textContent = text || ""; m.className = ok ? "ok" : ""; }

  async function api(path, opts) {
    opts = opts || {};
    const headers = { "Accept": "application/json" };
    if (opts.body !== undefined) headers["Content-Type"] = "application/json";
    if (opts.method === "POST" && session.csrf) headers["X-CSRF-Token"] = session.csrf;
    const r = await fetch(path, { method: opts.method || "GET", headers, credentials: "same-origin",
                                  body: opts.body === undefined ? undefined : JSON.stringify(opts.body) });
    let data = {};
    try { data = await r.json(); } catch (e) { data = { reason: r.statusText }; }
    data.status = r.status;
    return data;
  }

  async function refreshSession() {
    const s = await api("/api/session");
    session.user = s.user; session.csrf = s.csrf || null;
    $("#who").textContent = s.user ? "logged in: " + s.user : "not logged in (reading only)";
    $("#login").classList.toggle("hidden", !!s.user);
    $("#logout").classList.toggle("hidden", !s.user);
  }
  $("#login").addEventListener("submit", async ev => {
    ev.preventDefault();
    const r = await api("/api/login", { method: "POST", body: { user: $("#login-user").value, password: $("#login-pw").value } });
    $("#login-pw").value = "";
    if (r.status === 200) { say("logged in as " + r.user, true); } else { say("login refused: " + r.reason); }
    await refreshSession();
  });
  $("#logout").addEventListener("click", async () => { await api("/api/logout", { method: "POST", body: {} }); await refreshSession(); say("logged out", true); });

  async function command(sid, body) {
    const r = await api("/api/station/" + encodeURIComponent(sid) + "/command", { method: "POST", body });
    if (r.ok) say(body.command + ": accepted", true); else say(body.command + " refused: " + r.reason);
    return r;
  }
  hw.command = command;

  // ------------------------------------------------------------------ fleet
  // a hook past its threshold (t_life found, or headroom ≤ 0) is drawn as past it: a full red bar
  function headroomBar(h, past) {
    if (past || (h != null && h <= 0))
      return `<div class="bar out past" title="past its threshold${h != null ? " (headroom " + fmt(h, 2) + ")" : ""}"><div style="width:100%"></div><span>past threshold</span></div>`;
    if (h == null) return '<div class="bar" title="no headroom yet"></div>';
    const w = Math.max(0, Math.min(1, h)) * 100;
    const cls = h < 0.5 ? "low" : "";
    return `<div class="bar ${cls}" title="headroom ${fmt(h, 2)}"><div style="width:${w}%"></div></div>`;
  }
  // wall-clock time of an ISO 8601 UTC string, local to the browser: "Thu 14:05"
  function wall(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    return isNaN(d) ? "–" : d.toLocaleString(undefined, { weekday: "short", hour: "2-digit", minute: "2-digit", hour12: false });
  }
  function wallAt(start, s) { return (start && s != null && isFinite(s)) ? new Date(new Date(start).getTime() + s * 1000).toISOString() : null; }
  function projection(s) {
    if (s.end_p50 == null) return "";
    const st = s.test_started_utc;
    return `projected end ${wall(wallAt(st, s.end_p10))} – ${wall(wallAt(st, s.end_p90))} (median ${wall(wallAt(st, s.end_p50))}), P_end ${fmt(s.p_end, 2)}`;
  }
  // how many lives a prior came from (METHOD.md §7a v3): "4 wear-out failures, 3 censored,
  // 1 early failure" ("" without counts)
  function priorLives(s) {
    if (s.prior_n == null) return "";
    const w = (n, one, many) => `${n} ${n === 1 ? one : many}`;
    return [w(s.prior_n, "wear-out failure", "wear-out failures"),
            s.prior_n_censored != null ? `${s.prior_n_censored} censored` : null,
            s.prior_n_early != null ? w(s.prior_n_early, "early failure", "early failures") : null].filter(Boolean).join(", ");
  }
  // where the test's life prior came from (METHOD.md §7a): method / config / history:N, with
  // "the site: T tests from K stations" when other stations' lives are in it, and its lives
  function priorText(s) {
    if (s.prior_mean == null || !s.prior_source) return "none";
    const lives = priorLives(s);
    return `${fmt(s.prior_mean, 0)} ± ${fmt(s.prior_sd, 0)} s from ${esc(s.prior_source)}` +
      (lives ? ` <span class="prior-lives">(${esc(lives)})</span>` : "");
  }
  // the due list's life prior: "3156 ± 182 s · history: 4 wear-out failures, 3 censored, 1 early failure"
  function priorCell(s) {
    if (s.prior_mean == null || !s.prior_source) return "–";
    const lives = priorLives(s);
    return `${fmt(s.prior_mean, 0)} ± ${fmt(s.prior_sd, 0)} s · ${String(s.prior_source).split(/[: ]/)[0]}` + (lives ? ": " + lives : "");
  }
  function wearWarning(s) {
    if (!s.wear_warning && (!s.warning_alarm || s.warning_alarm === "normal")) return "none";
    const r = (s.warn_reasons || []).map(esc).join(", ");
    return `<span class="wear">wear warning${r ? ": " + r : ""}</span> ${alarmBadge(s.warning_alarm)}`;
  }
  function slotsText(s) {
    const n = s.slots || 0;
    return n ? `${fmt(100 * (s.filled || 0) / n, 2)} % filled, ${fmt(100 * (s.valid || 0) / n, 2)} % valid of ${n}` : "–";
  }
  function link(ok) { return ok == null ? "–" : ok ? '<span class="ok">ok</span>' : '<span class="bad">lost</span>'; }
  // ISA-18.2 states (gateway/core/records.py AlarmState); `alarm-active`: waits for an acknowledgement
  function needsAck(a) { return a === "unacknowledged" || a === "rtn_unacknowledged"; }
  function alarmBadge(a) {
    return a && a !== "normal" && a !== "none"
      ? `<span class="alarm-${esc(a)}${needsAck(a) ? " alarm-active" : ""}">${esc(a)}</span>` : "normal";
  }

  // ------------------------------------------------------------------ the site's other boxes
  // Text from other boxes (the site view, gateway/outputs/console/site.py) is never parsed as HTML: it is
  // set as text nodes by el(); the server has clipped it to short printable ASCII as well.
  function el(tag, attrs, ...kids) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) if (v != null) { if (k === "class") e.className = v; else e.setAttribute(k, String(v)); }
    for (const k of kids) if (k != null) e.append(k instanceof Node ? k : String(k));
    return e;
  }
  function liveness(s) {
    if (!s.remote) return "this box";
    return s.online ? "other box · online" : "other box · silent since " + wall(s.silent_since);
  }
  function barNode(h, past) {
    if (past || (h != null && h <= 0)) return el("div", { class: "bar out past", title: "past its threshold" }, el("div", { style: "width:100%" }), el("span", null, "past threshold"));
    if (h == null || !isFinite(h)) return el("div", { class: "bar", title: "no headroom yet" });
    return el("div", { class: "bar" + (h < 0.5 ? " low" : ""), title: "headroom " + fmt(h, 2) }, el("div", { style: "width:" + (Math.max(0, Math.min(1, Number(h))) * 100) + "%" }));
  }
  // a station of another box: read-only (no command buttons), its box's liveness first
  function remoteCard(s) {
    const alarm = s.alarm && s.alarm !== "normal" ? s.alarm : "normal";
    const wear = s.wear_warning ? "wear warning" + ((s.warn_reasons || []).length ? ": " + s.warn_reasons.join(", ") : "") : "none";
    return el("div", { class: "card remote" + (s.online ? "" : " silent"), "data-station": s.station, "data-remote": "1" },
      el("h3", null, s.station, " ", el("small", null, "(read-only)")),
      el("div", { class: "kv" },
        el("span", null, "box"), el("span", { class: "liveness " + (s.online ? "ok" : "bad") }, liveness(s)),
        el("span", null, "state"), el("span", { class: "state", "data-state": s.state || "" }, (stateWords(s) || "–") + (s.sample_id ? " · " + s.sample_id : "")),
        el("span", null, "μ"), el("span", null, `μ_ss ${fmt(s.mu_ss)}, μ_th ${fmt(s.mu_th)}`),
        el("span", null, "headroom"), el("span", null, barNode(s.headroom, s.past_threshold)),
        el("span", null, "forecast"), el("span", null, projection(s) || "–"),
        el("span", null, "wear"), el("span", { class: "wear-cell" }, wear),
        el("span", null, "alarm"), el("span", { class: "alarm" }, alarm),
        el("span", null, "links"), el("span", null, `meter ${s.meter_ok == null ? "–" : s.meter_ok ? "ok" : "lost"} · STM32 ${s.stm32_ok == null ? "–" : s.stm32_ok ? "ok" : "lost"}`),
        el("span", null, "place"), el("span", null, [s.line, s.area].filter(Boolean).join(" · ") || "–")));
  }
  function matches(s, f) {
    if (!f) return true;
    f = f.toLowerCase();
    return [s.station, s.line, s.area, s.sample_id, s.grade, s.state].some(v => v != null && String(v).toLowerCase().includes(f));
  }
  function siteToggle(id) {
    const cb = $(id);
    cb.checked = localStorage.getItem("hw-site") === "1";
    return cb;
  }
  // ------------------------------------------------------------------ operator words
  // a duration in words: "2 h 13 min", "4 min 05 s", "12.3 s"
  function dur(s) {
    if (s == null || !isFinite(s)) return "–";
    s = Number(s);
    if (s < 60) return s.toFixed(1) + " s";
    const t = Math.round(s);
    if (t < 3600) return `${Math.floor(t / 60)} min ${String(t % 60).padStart(2, "0")} s`;
    return `${Math.floor(t / 3600)} h ${String(Math.floor((t % 3600) / 60)).padStart(2, "0")} min`;
  }
  function alarmName(a) { return a === "end_of_life" ? "end of life" : a === "wear_warning" ? "wear warning" : String(a || "the alarms"); }
  function by(who) { return who ? " by " + who : ""; }
  function cap(s) { s = String(s); return s.charAt(0).toUpperCase() + s.slice(1); }
  const REASON_WORDS = { headroom: "the headroom is below its bound", prior: "the life prior puts the end near",
                         trend: "the μ trend reaches the threshold soon" };
  // a hook's life in the §7a history (gateway/station/hook_log.py LIFE_KINDS)
  const LIFE_KIND_WORDS = { wear_out: "wear-out failure", early: "early failure", censored: "censored: replaced before its end of life" };
  function lifeKind(k) { return LIFE_KIND_WORDS[k] || ""; }
  const END_WORDS = { stop: "stopped", "protection stop": "stopped by a protection stop", hook_replaced: "ended: the hook was replaced",
                      shutdown: "ended: the gateway shut down", completed: "completed" };
  // a test's end in words; `t_life` known: "end of life found at …, then stopped"
  function endWords(testStatus, endReason, tLife, status) {
    const how = END_WORDS[endReason] || (endReason ? "ended (" + endReason + ")" : testStatus === "completed" ? "completed" : "stopped");
    if (tLife != null && isFinite(tLife)) {
      return testStatus === "completed" ? `completed; end of life found at ${dur(tLife)}` : `end of life found at ${dur(tLife)}, then ${how}`;
    }
    if (testStatus === "completed") return status === "no_baseline" ? "completed without a baseline" : "completed without an end of life";
    return how;
  }
  // a station's state in words (the end of a test says what was found before it)
  function stateWords(s) {
    const st = s.state || "";
    if ((st === "aborted" || st === "completed") && s.t_life != null) return endWords(st, s.end_reason, s.t_life, s.status);
    if (st === "end_of_life" && s.t_life != null) return `end of life found at ${dur(s.t_life)}`;
    return st.replace(/_/g, " ");
  }
  hw.dur = dur;
  // one sentence per event type (gateway/core/records.py EventType; the keys: gateway/outputs/mqtt/schema.py EVENT_DATA)
  function eventText(e) {
    const n = x => fmt(x, 2), r = e.result || {};
    switch (e.type) {
      case "test_starting": return `Start accepted for sample ${e.sample_id} at ${n(e.t_set)} N: ${e.zero_check ? "zero check, then spin-up" : "spin-up"}.`;
      case "start_failed": return `The start of sample ${e.sample_id} failed: ${e.reason}.`;
      case "test_started": return `Test started${by(e.source)}: sample ${e.sample_id}${e.grade ? " (" + e.grade + ")" : ""} at ${n(e.t_set)} N` +
        (e.t_end != null ? `, planned for ${dur(e.t_end)}` : "") +
        (e.prior_mean != null ? `; life prior ${dur(e.prior_mean)} ± ${dur(e.prior_sd)} (${e.prior_source}` +
          (priorLives(e) ? `; ${priorLives(e)})` : ")") : "") + ".";
      case "baseline_established": return `Baseline found: μ_ss ${fmt(e.mu_ss, 3)}, so the threshold μ_th is ${fmt(e.mu_th, 3)}.`;
      case "end_of_life": return `End of life detected at ${dur(e.t_life)} (μ above the threshold ${fmt(e.mu_th, 3)}; baseline μ_ss ${fmt(e.mu_ss, 3)}).`;
      case "wear_warning": {
        const why = (e.reasons || []).map(x => REASON_WORDS[x] || x).join(", ");
        return `Wear warning at ${dur(e.t_warn)}: headroom ${n(e.headroom)}` + (why ? `; ${why}` : "") +
          (e.t_cross != null ? `; projected crossing at ${dur(e.t_cross)}` : "") +
          (e.end_p50 != null ? `; end expected between ${dur(e.end_p10)} and ${dur(e.end_p90)} (median ${dur(e.end_p50)})` : "") + ".";
      }
      case "protection_stop": return `Protection stop: ${(e.stop_reasons || []).join(", ") || "unsafe run"}; the drive was stopped.`;
      // the STM32 stopped the drive by itself (its watchdog, a trip): the station's own sentence
      case "drive_stopped": return cap(e.why || "the drive stopped on its own (" + e.reason + ")") + ".";
      case "test_ended": {
        const w = endWords(e.test_status, e.reason, r.t_life, r.status);
        return `Test ${w}${by(e.source)}${e.why ? ": " + e.why : ""}.`.replace(/^Test end of life/, "Test: end of life");
      }
      case "port_lost": return `The ${e.port === "stm32" ? "STM32" : e.port} port was lost${e.times > 1 ? " (" + e.times + " times)" : ""}.`;
      case "port_back": return `The ${e.port === "stm32" ? "STM32" : e.port} port is back.`;
      case "alarm_acknowledged": return `Alarm acknowledged${by(e.source)}.`;
      case "alarm_cleared": return `Alarms closed${e.reason === "hook_replaced" ? ": the hook was replaced" : e.reason ? ": " + e.reason : ""}${by(e.source)}.`;
      case "alarm_shelved": return `The ${alarmName(e.alarm)} alarm was shelved${by(e.source)}${e.until ? " until " + wall(new Date(e.until * 1000).toISOString()) : ""}.`;
      case "alarm_unshelved": return e.expired ? `The shelving of the ${alarmName(e.alarm)} alarm ran out.` : `The ${alarmName(e.alarm)} alarm was unshelved${by(e.source)}.`;
      case "alarm_out_of_service": return `Alarms taken out of service${by(e.source)}.`;
      case "alarm_in_service": return `Alarms returned to service${by(e.source)}.`;
      case "hook_replaced": return `Hook ${e.old_sample_id || "?"} replaced by ${e.new_sample_id}${e.grade ? " (" + e.grade + ")" : ""}${by(e.by)}` +
        (e.life_s != null ? `; its life ${dur(e.life_s)}` + (lifeKind(e.life_kind) ? ` (${lifeKind(e.life_kind)})` : "") : "") + (e.logged === false ? "; NOT written to hooks.jsonl (disk)" : "") + ".";
      case "command_rejected": return `${e.count > 1 ? e.count + " " + e.command + " commands" : "A " + e.command + " command"} from ${e.source} refused: ${e.reason}${e.code != null ? " (code " + e.code + ")" : ""}.`;
      case "config_reloaded": return "Configuration reloaded.";
      case "disk_full": return `The ${e.store} cannot be written: ${e.reason}.`;
      case "disk_ok": return `The ${e.store} can be written again.`;
      case "records_pruned": return `Record retention removed ${(e.tests || []).length} old test(s), ${fmt((e.bytes || 0) / 1e6, 1)} MB.`;
      default: return String(e.type).replace(/_/g, " ") + ".";
    }
  }
  hw.eventText = eventText;

  function fleetPage() {
    main.innerHTML = `<div class="row"><h2 style="margin:0">Fleet</h2>
      <label><input type="checkbox" id="site"> whole site</label>
      <label>filter <input id="filter" maxlength="64" placeholder="station, line, area, sample …"></label>
      <label>sort by <select id="sort"><option value="headroom">headroom (least first)</option><option value="name">name</option><option value="silent">silent boxes first</option></select></label>
      <small id="fleet-note"></small></div>
      <div class="cards" id="cards"></div>`;
    const sortSel = $("#sort"), siteCb = siteToggle("#site"), filt = $("#filter");
    sortSel.value = localStorage.getItem("hw-sort") || "headroom";
    sortSel.addEventListener("change", () => { localStorage.setItem("hw-sort", sortSel.value); load(); });
    siteCb.addEventListener("change", () => { localStorage.setItem("hw-site", siteCb.checked ? "1" : "0"); load(); });
    filt.addEventListener("input", () => load());
    async function load() {
      const r = await api("/api/fleet" + (siteCb.checked ? "?site=1" : ""));
      if (r.status !== 200) { say(r.reason); return; }
      const st = r.stations.filter(s => matches(s, filt.value));
      const byName = (a, b) => String(a.station).localeCompare(String(b.station));
      if (sortSel.value === "headroom") st.sort((a, b) => (a.headroom == null ? 1e9 : a.headroom) - (b.headroom == null ? 1e9 : b.headroom) || byName(a, b));
      else if (sortSel.value === "silent") st.sort((a, b) => (a.remote && !a.online ? 0 : 1) - (b.remote && !b.online ? 0 : 1) || byName(a, b));
      else st.sort(byName);
      hw.fleet = st.map(s => s.station);
      const cards = $("#cards");
      cards.replaceChildren(...st.map(s => s.remote ? remoteCard(s) : localCard(s)));
      const n = r.stations.filter(s => s.remote).length;
      $("#fleet-note").textContent = siteCb.checked ? `${r.stations.length - n} of this box, ${n} of the site's other boxes${r.site && !r.site.fed ? " (no MQTT session carries the site view)" : ""}` : "";
      main.querySelectorAll("button.ack").forEach(b => b.addEventListener("click", () => command(b.dataset.sid, { command: "ack" }).then(load)));
    }
    // a station of this box: its own text escaped (esc), with its command buttons
    function localCard(s) {
      const t = document.createElement("template");
      t.innerHTML = `<div class="card" data-station="${esc(s.station)}">
        <h3><a href="#/station/${encodeURIComponent(s.station)}">${esc(s.station)}</a></h3>
        <div class="kv">
          <span>state</span><span class="state" data-state="${esc(s.state)}">${esc(stateWords(s) || (s.online ? "" : "offline"))}${s.sample_id ? " · " + esc(s.sample_id) : ""}</span>
          <span>μ now</span><span>${fmt(s.mu_now)} <small>(μ_ss ${fmt(s.mu_ss)}, μ_th ${fmt(s.mu_th)})</small></span>
          <span>headroom</span><span>${headroomBar(s.headroom, s.past_threshold)}</span>
          <span>wear</span><span class="wear-cell">${wearWarning(s)}</span>
          <span>alarm</span><span class="alarm">${alarmBadge(s.alarm)} ${needsAck(s.alarm) ? `<button class="ack" data-sid="${esc(s.station)}">acknowledge</button>` : ""}</span>
          <span>links</span><span>meter ${link(s.meter_ok)} · STM32 ${link(s.stm32_ok)} · MQTT ${link(s.mqtt_ok)}</span>
          <span>slots</span><span>${slotsText(s)}</span>
        </div>
        <a href="#/history/${encodeURIComponent(s.station)}">history</a></div>`;
      return t.content.firstElementChild;
    }
    load();
    const t = setInterval(load, 1000);
    cleanup.push(() => clearInterval(t));
  }

  // ------------------------------------------------------------------ station
  function markerPlugin(get) {
    return { hooks: { draw: [u => {
      const m = get(); const ctx = u.ctx; ctx.save();
      const lines = [["t_stable", "#2e7d32", "stable"], ["t_b", "#2e7d32", "baseline"], ["t_warn", "#f9a825", "warning"], ["t_life", "#c62828", "t_life"]];
      for (const [k, color, label] of lines) {
        const v = m[k]; if (v == null) continue;
        const x = u.valToPos(v, "x", true); if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) continue;
        ctx.strokeStyle = color; ctx.lineWidth = 2 * devicePixelRatio; ctx.setLineDash([6, 4]);
        ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
        ctx.fillStyle = color; ctx.font = (11 * devicePixelRatio) + "px sans-serif"; ctx.fillText(label, x + 4, u.bbox.top + 12 * devicePixelRatio);
      }
      ctx.restore();
    }] } };
  }

  // every value of the station the catalog labels (gateway/core/catalog.py, GET /api/values): the
  // labels come from the server, never a list of their own here
  let catalogRows = null;
  async function valueRows() {
    if (catalogRows === null) {
      const r = await api("/api/values");
      if (r.status === 200) catalogRows = r.values;
    }
    return catalogRows || [];
  }
  function valueText(row, x) {
    if (x == null) return "–";
    if (row.type === "bool") return x ? "yes" : "no";
    if (row.type === "list") return x.length ? x.map(esc).join(", ") : "–";
    if (row.type === "float") return fmt(x, Math.abs(x) >= 100 ? 1 : 4) + (row.unit ? " " + esc(row.unit) : "");
    return esc(x) + (row.unit ? " " + esc(row.unit) : "");
  }
  async function allValues(s) {
    const rows = await valueRows(), vals = s.values || {}, box = $("#values-kv");
    if (!box) return;
    box.innerHTML = rows.map(row => `<span>${esc(row.label)}</span><span data-value="${esc(row.name)}">${valueText(row, vals[row.name])}</span>`).join("");
    hw.values = rows.length;
  }

  function stationPage(sid) {
    main.innerHTML = `<h2 style="margin:0 0 .5em">Station ${esc(sid)} <small><a href="#/history/${encodeURIComponent(sid)}">history</a></small></h2>
      <div class="panel kv" id="st-info"></div>
      <details class="panel" id="all-values"><summary>all values</summary><div class="kv" id="values-kv"></div></details>
      <div class="panel controls" id="ctl">
        <label>sample <input id="c-sample" maxlength="32"></label>
        <label>grade <input id="c-grade" maxlength="16"></label>
        <label>T_set (N) <input id="c-tset" type="number" step="0.01"></label>
        <label>duration (s) <input id="c-tend" type="number" step="1"></label>
        <button id="b-start">start</button> <button id="b-stop">stop</button>
        <button id="b-ack">acknowledge</button> <button id="b-hook">hook replaced …</button>
      </div>
      <dialog id="hook-dlg"><form method="dialog" id="hook-form">
        <p><b>Hook replaced on ${esc(sid)}</b><br><small>ends the running test, closes the old hook's alarms and logs its life</small></p>
        <label>new hook's sample id <input id="h-sample" required maxlength="32" pattern="[ -~]+"></label><br>
        <label>grade (optional) <input id="h-grade" maxlength="16"></label><br>
        <button id="h-send" value="send">hook replaced</button> <button id="h-cancel" type="button">cancel</button>
      </form></dialog>
      <div class="panel"><b>μ(t)</b> <small id="mu-note"></small><div id="mu-chart"></div></div>
      <div class="row"><div class="panel"><b>tension (N)</b><div id="t-chart"></div></div>
      <div class="panel"><b>speed (rpm)</b><div id="s-chart"></div></div></div>
      <div class="panel"><b>events</b><div class="events" id="events"></div></div>
      <div class="panel" id="journal-panel"><b>alarm journal</b> <small>(ISA-18.2: every transition, who, when)</small>
        <div class="controls" id="alarm-ctl">
          <label>alarm <select id="j-alarm"><option value="end_of_life">end of life</option><option value="wear_warning">wear warning</option></select></label>
          <label>for (min) <input id="j-minutes" type="number" min="1" max="720" step="1" value="60"></label>
          <button id="b-shelve">shelve</button> <button id="b-unshelve">unshelve</button>
          <button id="b-oos">out of service</button> <button id="b-ins">in service</button>
        </div>
        <table id="journal"><thead><tr><th>time (UTC)</th><th>alarm</th><th>from</th><th>to</th><th>action</th><th>by</th><th>hook</th></tr></thead><tbody></tbody></table>
      </div>`;
    let rows = [], markers = {}, summary = {}, width = 0.02;
    const W = Math.min(1200, main.clientWidth - 40);
    const muPlot = new uPlot({ width: W, height: 320, scales: { x: { time: false } }, plugins: [markerPlugin(() => markers)],
      series: [{ label: "t (s)" }, { label: "μ (min/max)", stroke: "#1d3557", width: 1 },
               { label: "μ_ss", stroke: "#2e7d32", dash: [4, 4] }, { label: "μ_th", stroke: "#c62828", dash: [8, 4] }],
      axes: [{ label: "t (s)" }, { label: "μ" }] }, [[], [], [], []], $("#mu-chart"));
    const half = Math.max(300, (W - 40) / 2);
    const tPlot = new uPlot({ width: half, height: 220, scales: { x: { time: false } },
      series: [{ label: "t (s)" }, { label: "T1", stroke: "#1f77b4" }, { label: "T2", stroke: "#d62728" },
               { label: "mean", stroke: "#333" }, { label: "T_set", stroke: "#2e7d32", dash: [4, 4] }] },
      [[], [], [], [], []], $("#t-chart"));
    const sPlot = new uPlot({ width: half, height: 220, scales: { x: { time: false } },
      series: [{ label: "t (s)" }, { label: "command", stroke: "#9467bd" }, { label: "actual", stroke: "#8c564b" }] },
      [[], [], []], $("#s-chart"));

    function redraw() {
      const x = [], mu = [], ss = [], th = [];
      const tx = [], t1 = [], t2 = [], tm = [], tset = [], sc = [], sa = [];
      const mss = markers.mu_ss == null ? summary.mu_ss : markers.mu_ss, mth = markers.mu_th == null ? summary.mu_th : markers.mu_th;
      const ts = markers.t_set == null ? summary.t_set : markers.t_set;
      for (const r of rows) {
        x.push(r[0], r[0] + width / 2); mu.push(r[1], r[2]);
        ss.push(mss, mss); th.push(mth, mth);
        tx.push(r[0]); t1.push(r[3]); t2.push(r[4]); tm.push(r[5]); tset.push(ts); sc.push(r[6]); sa.push(r[7]);
      }
      hw.points = x.length; hw.lastT = rows.length ? rows[rows.length - 1][0] : null; hw.firstT = rows.length ? rows[0][0] : null;
      muPlot.setData([x, mu, ss, th]); tPlot.setData([tx, t1, t2, tm, tset]); sPlot.setData([tx, sc, sa]);
      $("#mu-note").textContent = rows.length ? `${rows.length} buckets of ${fmt(width, 2)} s, t = ${fmt(hw.firstT, 1)} … ${fmt(hw.lastT, 1)} s` : "no test data yet";
    }
    function info(events) {
      const s = summary;
      $("#st-info").innerHTML = `<span>state</span><span id="state" data-state="${esc(s.state)}">${esc(stateWords(s))}</span>
        <span>test</span><span>${esc(s.test_id)} · sample ${esc(s.sample_id)} · grade ${esc(s.grade)} · T_set ${fmt(s.t_set, 2)} N</span>
        <span>μ now</span><span>${fmt(s.mu_now)} (μ_ss ${fmt(s.mu_ss)}, μ_th ${fmt(s.mu_th)})</span>
        <span>headroom</span><span id="headroom">${headroomBar(s.headroom, s.past_threshold)} ${s.t_cross != null ? "projected crossing at " + fmt(s.t_cross, 0) + " s" : ""}</span>
        <span>forecast</span><span id="projection">${projection(s) || "–"}</span>
        <span>life prior</span><span id="prior">${priorText(s)}</span>
        <span>wear</span><span>${wearWarning(s)}</span>
        <span>t_life</span><span id="t-life">${s.t_life != null ? fmt(s.t_life, 2) + " s" : "–"}</span>
        <span>alarm</span><span id="alarm">${alarmBadge(s.alarm)}</span>
        <span>links</span><span>meter ${link(s.meter_ok)} · STM32 ${link(s.stm32_ok)} · MQTT ${link(s.mqtt_ok)}</span>
        <span>slots</span><span>${slotsText(s)}</span>`;
      allValues(s);
      if (events) renderEvents(events);
    }
    // the events in plain words, newest first; each one's raw JSON one click away (kept open
    // across updates: the list is drawn again only when it changed)
    const openRaw = new Set();
    let eventsSig = null;
    function renderEvents(events) {
      const last = events[events.length - 1];
      const sig = events.length + "|" + (last ? last.time + last.type + (last.count || "") : "");
      if (sig === eventsSig) return;
      eventsSig = sig;
      hw.events = events.length;
      $("#events").innerHTML = events.map((e, i) => [e, i]).reverse().map(([e, i]) => {
        const key = e.time + "|" + e.type + "|" + i;
        let text;
        try { text = eventText(e); } catch (err) { text = String(e.type); }
        return `<div class="event" data-type="${esc(e.type)}" data-key="${esc(key)}">
          <span class="ev-time">${new Date(e.time * 1000).toISOString().slice(11, 19)}</span> <span class="ev-text">${esc(text)}</span>
          <button type="button" class="raw-toggle" title="the event as recorded (JSON)" aria-expanded="${openRaw.has(key)}">{…}</button>
          <pre class="raw${openRaw.has(key) ? "" : " hidden"}">${esc(JSON.stringify(e, null, 1))}</pre></div>`;
      }).join("");
    }
    $("#events").addEventListener("click", ev => {
      const b = ev.target.closest("button.raw-toggle");
      if (!b) return;
      const row = b.closest(".event"), pre = row.querySelector("pre.raw");
      const open = pre.classList.toggle("hidden") === false;
      b.setAttribute("aria-expanded", String(open));
      if (open) openRaw.add(row.dataset.key); else openRaw.delete(row.dataset.key);
    });
    const es = new EventSource("/api/station/" + encodeURIComponent(sid) + "/stream");
    let gen = null;
    es.onmessage = ev => {
      const m = JSON.parse(ev.data);
      if (m.type === "snapshot") { rows = m.rows; width = m.width_s; gen = m.gen; hw.snapshots++; }
      else if (m.gen !== gen) { fetch("/api/station/" + encodeURIComponent(sid)).then(r => r.json()).then(s => { rows = s.rows; width = s.width_s; gen = s.gen; markers = s.markers; summary = s.summary; redraw(); }); return; }
      else if (m.from != null) { rows = rows.slice(0, m.from).concat(m.rows); hw.updates++; }
      markers = m.markers || {}; summary = m.summary || {};
      info(m.events); redraw();
    };
    es.onerror = () => say("live data interrupted; reconnecting …");
    cleanup.push(() => es.close());
    $("#b-start").addEventListener("click", () => {
      const b = { command: "start", sample_id: $("#c-sample").value };
      if ($("#c-grade").value) b.grade = $("#c-grade").value;
      if ($("#c-tset").value) b.t_set = Number($("#c-tset").value);
      if ($("#c-tend").value) b.t_end = Number($("#c-tend").value);
      command(sid, b);
    });
    // the stop names the test this page shows (its test_id): if that test ended meanwhile, the
    // station refuses the stop (15 WRONG_TEST) instead of ending a newer one
    $("#b-stop").addEventListener("click", () => {
      const b = { command: "stop" };
      if (["baseline_search", "monitoring", "end_of_life"].includes(summary.state) && summary.test_id) b.test_id = summary.test_id;
      command(sid, b);
    });
    $("#b-ack").addEventListener("click", () => command(sid, { command: "ack" }));
    // hook replaced: the same command as MQTT, the PLC and Sparkplug, with the NEW hook's sample id
    const dlg = $("#hook-dlg");
    $("#b-hook").addEventListener("click", () => { $("#h-sample").value = ""; $("#h-grade").value = ""; dlg.showModal(); });
    $("#h-cancel").addEventListener("click", () => dlg.close("cancel"));
    $("#hook-form").addEventListener("submit", ev => {
      ev.preventDefault();
      const sample = $("#h-sample").value.trim();
      if (!sample) { $("#h-sample").reportValidity(); return; }
      const b = { command: "hook_replaced", sample_id: sample };
      if ($("#h-grade").value.trim()) b.grade = $("#h-grade").value.trim();
      dlg.close("send");
      command(sid, b).then(loadJournal);
    });
    // the alarm journal and its actions (shelve / unshelve one alarm; out of / in service: both)
    async function loadJournal() {
      const r = await api("/api/station/" + encodeURIComponent(sid) + "/journal");
      if (r.status !== 200) return;
      hw.journal = r.journal.length;
      $("#journal tbody").innerHTML = r.journal.slice().reverse().map(j => `<tr class="j-${esc(j.to)}">
        <td>${esc(new Date(j.time * 1000).toISOString().replace("T", " ").slice(0, 19))}</td><td>${esc(j.alarm)}</td>
        <td>${esc(j.from)}</td><td>${esc(j.to)}</td><td>${esc(j.action)}</td><td class="by">${esc(j.by)}</td><td>${esc(j.hook)}</td></tr>`).join("");
    }
    const alarmCmd = body => command(sid, body).then(loadJournal);
    $("#b-shelve").addEventListener("click", () => alarmCmd({ command: "shelve", alarm: $("#j-alarm").value, duration_s: 60 * Number($("#j-minutes").value || 60) }));
    $("#b-unshelve").addEventListener("click", () => alarmCmd({ command: "unshelve", alarm: $("#j-alarm").value }));
    $("#b-oos").addEventListener("click", () => alarmCmd({ command: "out_of_service" }));
    $("#b-ins").addEventListener("click", () => alarmCmd({ command: "in_service" }));
    loadJournal();
    const jt = setInterval(loadJournal, 2000);
    cleanup.push(() => clearInterval(jt));
  }

  // ------------------------------------------------------------------ the planner's due list
  // the due list: the server's order (the soonest due first), or sorted by a column (click its
  // header, again to reverse); filtered by line / area (server) and by text (here)
  const DUE_SORT = {
    station: x => String(x.station), box: x => (x.remote ? (x.online ? 1 : 2) : 0), p_end: x => (x.p_end == null ? -1 : x.p_end),
    state: x => String(x.state || ""), grade: x => String(x.grade || ""), sample: x => String(x.sample_id || ""),
    line: x => String(x.line || ""), area: x => String(x.area || ""),
  };
  function duePage() {
    const q = new URLSearchParams(location.hash.split("?")[1] || "");
    main.innerHTML = `<div class="row"><h2 style="margin:0">Due list</h2>
      <label><input type="checkbox" id="f-site"> whole site</label>
      <label>line <select id="f-line"><option value="">all</option></select></label>
      <label>area <select id="f-area"><option value="">all</option></select></label>
      <label>filter <input id="f-text" maxlength="64" placeholder="station, sample, grade …"></label>
      <a id="csv" href="/api/due.csv" download>CSV</a> <small id="due-note"></small></div>
      <table id="due"><thead><tr><th data-sort="station">station</th><th data-sort="box">box</th><th data-sort="when">projected end p10 – p90 (median)</th><th data-sort="p_end">P_end</th><th>reasons</th><th>life prior</th><th data-sort="state">state</th><th data-sort="grade">grade</th><th data-sort="sample">sample</th><th data-sort="line">line</th><th data-sort="area">area</th></tr></thead><tbody></tbody></table>`;
    const fl = $("#f-line"), fa = $("#f-area"), siteCb = siteToggle("#f-site"), ft = $("#f-text");
    const want = { line: q.get("line") || "", area: q.get("area") || "" };
    const sort = { key: "when", dir: 1 };
    function query() {
      const p = new URLSearchParams();
      if (fl.value) p.set("line", fl.value);
      if (fa.value) p.set("area", fa.value);
      if (siteCb.checked) p.set("site", "1");
      const s = p.toString();
      return s ? "?" + s : "";
    }
    function fill(sel, values, cur) {
      const have = [...sel.options].map(o => o.value).slice(1).join("\n");
      if (have !== values.join("\n")) sel.replaceChildren(el("option", { value: "" }, "all"), ...values.map(v => el("option", { value: v }, v)));
      if ([...sel.options].some(o => o.value === cur)) sel.value = cur;
    }
    function row(x) {
      const when = x.t_life != null ? `past its end of life since ${wall(x.t_life_utc)}`
        : x.end_utc_p50 ? `${wall(x.end_utc_p10)} – ${wall(x.end_utc_p90)} (${wall(x.end_utc_p50)})` : "–";
      const name = x.remote ? el("span", { class: "remote-name", title: "a station of another box (read-only)" }, x.station)
        : el("a", { href: "#/station/" + encodeURIComponent(x.station) }, x.station);
      return el("tr", { "data-station": x.station, "data-remote": x.remote ? "1" : null, class: (x.due ? "due" : "") + (x.remote && !x.online ? " silent" : "") },
        el("td", null, name), el("td", { class: "box" }, liveness(x)), el("td", { class: "when" }, when),
        el("td", null, fmt(x.p_end, 2)), el("td", null, (x.reasons || []).join(", ")),
        el("td", { class: "prior" }, priorCell(x)), el("td", null, x.state || ""),
        el("td", null, x.grade || ""), el("td", null, x.sample_id || ""), el("td", null, x.line || ""), el("td", null, x.area || ""));
    }
    let last = null;
    function render() {
      if (!last) return;
      let rows = last.stations.map((x, i) => ({ ...x, _i: i })).filter(x => matches(x, ft.value));
      const f = DUE_SORT[sort.key];
      if (f) rows.sort((a, b) => { const va = f(a), vb = f(b); return (va < vb ? -1 : va > vb ? 1 : a._i - b._i) * sort.dir; });
      else if (sort.dir < 0) rows.reverse();
      hw.due = rows.map(x => x.station);
      $("#due tbody").replaceChildren(...rows.map(row));
      main.querySelectorAll("#due th[data-sort]").forEach(th => th.classList.toggle("sorted", th.dataset.sort === sort.key));
      $("#due-note").textContent = `${rows.length} stations, ${rows.filter(x => x.due).length} due` +
        (siteCb.checked ? `, ${rows.filter(x => x.remote).length} of other boxes` : "");
    }
    // a refresh that answers after the planner left the page draws nothing (its table is gone)
    let gone = false;
    cleanup.push(() => { gone = true; });
    async function load() {
      const r = await api("/api/due" + query());
      if (gone) return;
      if (r.status !== 200) { say(r.reason); return; }
      fill(fl, r.lines, fl.value || want.line); fill(fa, r.areas, fa.value || want.area);
      $("#csv").href = "/api/due.csv" + query();
      last = r; render();
    }
    main.querySelectorAll("#due th[data-sort]").forEach(th => th.addEventListener("click", () => {
      sort.dir = sort.key === th.dataset.sort ? -sort.dir : 1; sort.key = th.dataset.sort; render();
    }));
    fl.addEventListener("change", () => { want.line = fl.value; load(); });
    fa.addEventListener("change", () => { want.area = fa.value; load(); });
    siteCb.addEventListener("change", () => { localStorage.setItem("hw-site", siteCb.checked ? "1" : "0"); load(); });
    ft.addEventListener("input", render);
    load();
    const t = setInterval(load, 2000);
    cleanup.push(() => clearInterval(t));
  }

  // ------------------------------------------------------------------ the site's boxes (issue 37)
  // Each box's retained config report (gateway/outputs/console/boxes.py): which version of the site's
  // configuration it runs, what waits for a test to end, drift, its last rollback. Text as text.
  function shortV(v) { return v ? String(v).slice(0, 12) : "–"; }
  function boxesPage() {
    main.innerHTML = `<h2 style="margin:0 0 .5em">Boxes of the site</h2>
      <table id="boxes"><thead><tr><th>box</th><th>online</th><th>version</th><th>verified</th><th>applied (UTC)</th><th>deferred (test running)</th><th>pending</th><th>drift</th><th>last rollback</th><th>last interrupt</th></tr></thead><tbody></tbody></table>
      <p><small id="boxes-note"></small></p>`;
    function row(b) {
      const rb = b.last_rollback, it = b.last_interrupt;
      const drift = b.drift ? el("span", { class: "bad" }, "yes: " + (b.drift_files || []).join(", ")) : el("span", { class: "ok" }, "no");
      return el("tr", { "data-box": b.box, class: (b.online === false ? "silent" : "") + (b.drift ? " drift" : "") },
        el("td", { class: "box" }, b.box),
        el("td", { class: "online" }, b.online === false ? el("span", { class: "bad" }, "offline") : el("span", { class: "ok" }, "online")),
        el("td", { class: "version", title: b.version || "" }, shortV(b.version) + (b.applying ? " (applying " + shortV(b.applying) + ")" : "")),
        el("td", { class: "verified", title: b.verified || "" }, shortV(b.verified)),
        el("td", null, b.applied_at ? String(b.applied_at).replace("T", " ").slice(0, 19) : "–"),
        el("td", { class: "deferred" }, (b.deferred || []).join(", ") || "none"),
        el("td", { class: "pending" }, (b.pending || []).join(", ") || "none"),
        el("td", { class: "drift" }, drift),
        el("td", { class: "rollback" }, rb ? `${shortV(rb.from)} → ${shortV(rb.to)}: ${rb.why || ""}` + (rb.time ? " (" + String(rb.time).replace("T", " ").slice(0, 19) + ")" : "") : "none"),
        el("td", { class: "interrupt" }, it ? `by ${it.by}: ${(it.stations || []).join(", ")}` : "none"));
    }
    async function load() {
      const r = await api("/api/boxes");
      if (r.status && r.status !== 200) { $("#boxes-note").textContent = r.reason || "no answer"; return; }
      const boxes = r.boxes || [];
      $("#boxes tbody").replaceChildren(...boxes.map(row));
      hw.boxes = boxes.map(b => b.box);
      $("#boxes-note").textContent = `${boxes.length} boxes` + (r.site && !r.site.fed ? " (the site view is not fed: no station of this box has MQTT)" : "");
    }
    load();
    const t = setInterval(load, 2000);
    cleanup.push(() => clearInterval(t));
  }

  // ------------------------------------------------------------------ history
  async function historyPage(sid) {
    main.innerHTML = `<h2 style="margin:0 0 .5em">History of ${esc(sid)} <small><a href="#/station/${encodeURIComponent(sid)}">live</a></small></h2>
      <div class="row"><div class="panel"><b>hooks</b><div id="hooks">loading …</div></div>
      <div class="panel"><b>tests</b><div id="tests">loading …</div></div></div><div id="fig"></div>`;
    api("/api/station/" + encodeURIComponent(sid) + "/hooks").then(h => {
      if (h.status !== 200) { $("#hooks").textContent = h.reason; return; }
      $("#hooks").innerHTML = h.hooks.length ? `<table id="hooks-table"><tr><th>replaced (UTC)</th><th>old hook</th><th>its life (s)</th><th>its last test</th><th>new hook</th><th>grade</th><th>by</th></tr>` +
        h.hooks.map(x => `<tr><td>${esc((x.utc || "").replace("T", " ").slice(0, 19))}</td><td>${esc(x.old_sample_id)}</td><td>${fmt(x.life_s, 1)}${lifeKind(x.life_kind) ? ` <span class="life-kind" data-kind="${esc(x.life_kind)}">${esc(lifeKind(x.life_kind))}</span>` : ""}</td><td>${esc(x.test_id)}</td><td>${esc(x.new_sample_id)}</td><td>${esc(x.grade)}</td><td>${esc(x.by)}</td></tr>`).join("") + "</table>"
        : "no hook replaced yet";
    });
    const r = await api("/api/station/" + encodeURIComponent(sid) + "/tests");
    if (r.status !== 200) { $("#tests").textContent = r.reason; return; }
    const base = "/api/station/" + encodeURIComponent(sid) + "/tests/";
    $("#tests").innerHTML = r.tests.length ? `<table><tr><th>test</th><th>sample</th><th>grade</th><th>status</th><th>t_life (s)</th><th>μ_ss</th><th>headroom at end</th><th>files</th><th></th></tr>` +
      r.tests.map(t => `<tr><td>${esc(t.test_id)}</td><td>${esc(t.sample_id)}</td><td>${esc(t.grade)}</td><td class="status" title="${esc(t.test_status)} / ${esc(t.status)}${t.end_reason ? " (" + esc(t.end_reason) + ")" : ""}${t.why ? ": " + esc(t.why) : ""}">${esc(t.test_status === "running" || t.test_status === "unreadable" ? t.test_status : endWords(t.test_status, t.end_reason, t.t_life, t.status))}</td><td>${fmt(t.t_life, 2)}</td><td>${fmt(t.mu_ss)}</td><td>${fmt(t.headroom, 2)}</td>
        <td>${t.files.map(f => `<a href="${base}${encodeURIComponent(t.test_id)}/files/${f}">${f}</a>`).join(" ")}</td>
        <td>${t.files.includes("result.json") ? `<button class="fig7" data-tid="${esc(t.test_id)}">Fig. 7</button>` : ""}</td></tr>`).join("") + "</table>" : "no recorded tests";
    main.querySelectorAll("button.fig7").forEach(b => b.addEventListener("click", () => {
      $("#fig").innerHTML = `<p id="fig-note">rendering Fig. 7 of ${esc(b.dataset.tid)} …</p><img class="fig" alt="Fig. 7 of ${esc(b.dataset.tid)}" src="${base}${encodeURIComponent(b.dataset.tid)}/fig7.png">`;
      const img = $("#fig img");
      img.addEventListener("load", () => { $("#fig-note").textContent = "Fig. 7 of " + b.dataset.tid; });
      img.addEventListener("error", () => { $("#fig-note").textContent = "no figure (see the gateway log)"; });
    }));
  }

  // ------------------------------------------------------------------ campaign
  async function campaignPage() {
    main.innerHTML = `<h2 style="margin:0 0 .5em">Campaign report</h2>
      <p>The report (paper Tables 3–6, Figs. 7–9) over the ended tests of the chosen stations. It needs a login (it takes a while and a core).</p>
      <div id="choose" class="panel"></div><button id="b-campaign">make the report</button> <span id="camp-out"></span>`;
    const r = await api("/api/fleet");
    $("#choose").innerHTML = (r.stations || []).map(s => `<label><input type="checkbox" value="${esc(s.station)}" checked> ${esc(s.station)}</label> `).join("");
    $("#b-campaign").addEventListener("click", async () => {
      const stations = [...main.querySelectorAll("#choose input:checked")].map(i => i.value);
      $("#camp-out").textContent = "making the report …";
      const c = await api("/api/campaign", { method: "POST", body: { stations } });
      if (c.ok) $("#camp-out").innerHTML = `${c.tests} tests: <a id="camp-link" target="_blank" href="${esc(c.url)}">open the report</a>`;
      else $("#camp-out").textContent = "refused: " + c.reason;
    });
  }

  function route() {
    cleanup.forEach(f => f()); cleanup = [];
    const h = location.hash.replace(/^#/, "");
    let m;
    if ((m = h.match(/^\/station\/(.+)$/))) stationPage(decodeURIComponent(m[1]));
    else if ((m = h.match(/^\/history\/(.+)$/))) historyPage(decodeURIComponent(m[1]));
    else if (h === "/campaign") campaignPage();
    else if (h === "/boxes") boxesPage();
    else if (h === "/due" || h.startsWith("/due?")) duePage();
    else fleetPage();
  }
  window.addEventListener("hashchange", route);
  refreshSession().then(route);
})();
