/* comp-daemon operator screen. Plain JavaScript, no build step, no external assets.
 *
 * Data: GET /api/status (every 5 s and on demand; its "rsi" part lists each RSI stop with its cause
 * and what happens next), lists from /api/targets, /api/models, /api/jobs,
 * /api/datasets, /api/diagnoses, /api/gratings; live updates from /api/events (server-sent events,
 * read with fetch so that the bearer token travels in the Authorization header, never in a URL).
 * One source per fact: the banner's grating lines and the joint table are drawn from the same joint
 * rows (the daemon's staleness rule decides both); the RSI panel's header and its stop box from the
 * same "running" (the daemon's RSI sessions when it tracks them).
 * Actions (role-aware; a viewer sees none): drop a campaign (POST /api/datasets) or a target file
 * (POST /api/batches/file), queue a target (POST /api/batches), reset a fault
 * (POST /api/loop/reset-fault), calibrate the gratings (POST /api/gratings/calibrate).
 * Token: from the URL fragment (#token=...) or the sign-in dialog; kept in sessionStorage only.
 * Units: angles in degrees, lengths in mm, latencies in ms.
 */
"use strict";

(() => {
  const TOKEN_KEY = "comp-daemon-token";
  const ROLES = { anonymous: 0, viewer: 1, operator: 2, engineer: 3 };
  const ACTIVE = ["compensating", "moving", "settling"];
  const OPEN_STATES = ["queued", "compensating", "moving", "settling", "interrupted"];
  const COLORS = ["#8796a5", "#4fa3e0", "#3fb950", "#d2a8ff", "#e3a008"];

  const S = {
    token: null,
    role: "anonymous",
    status: null,
    snapshot: null,
    latency: [],
    targets: [],
    models: [],
    compareIds: [],
    compare: null,
    jobs: [],
    datasets: [],
    diagnoses: [],
    diagId: null,
    diagReport: null,
    live: false,
    loop: null,
    gratings: null,
    statusAt: 0,
  };

  const $ = (id) => document.getElementById(id);
  const el = (tag, attrs = {}, ...children) => {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs)) {
      if (k === "class") node.className = v;
      else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
      else if (v !== undefined && v !== null && v !== false) node.setAttribute(k, v === true ? "" : v);
    }
    for (const c of children) {
      if (c === null || c === undefined) continue;
      node.append(c instanceof Node ? c : document.createTextNode(String(c)));
    }
    return node;
  };
  const fmt = (x, digits = 3) => (x === null || x === undefined || Number.isNaN(x) ? "—" : Number(x).toFixed(digits));
  const pill = (text, cls) => el("span", { class: `pill ${cls || text}` }, text);
  const can = (role) => ROLES[S.role] >= ROLES[role];

  // ------------------------------------------------------------------ token and requests

  function initToken() {
    const hash = new URLSearchParams(location.hash.replace(/^#/, ""));
    const fromHash = hash.get("token");
    if (fromHash) {
      sessionStorage.setItem(TOKEN_KEY, fromHash);
      history.replaceState(null, "", location.pathname + location.search);
    }
    S.token = sessionStorage.getItem(TOKEN_KEY);
  }

  function askToken() {
    const dlg = $("signin");
    if (dlg.open) return;
    $("token-input").value = "";
    dlg.showModal();
  }

  $("signin-form").addEventListener("submit", (ev) => {
    if (ev.submitter && ev.submitter.value === "ok") {
      const value = $("token-input").value.trim();
      if (value) {
        sessionStorage.setItem(TOKEN_KEY, value);
        S.token = value;
        restartStream();
        refreshAll();
      }
    }
  });
  $("signin-btn").addEventListener("click", askToken);

  class ApiError extends Error {
    constructor(status, body) {
      super((body && body.message) || `HTTP ${status}`);
      this.status = status;
      this.body = body;
    }
  }

  async function api(path, options = {}) {
    const headers = Object.assign({ Accept: "application/json" }, options.headers || {});
    if (S.token) headers.Authorization = `Bearer ${S.token}`;
    const response = await fetch(path, Object.assign({}, options, { headers }));
    const type = response.headers.get("content-type") || "";
    const body = type.includes("json") ? await response.json().catch(() => null) : await response.text();
    if (response.status === 401) askToken();
    if (!response.ok) throw new ApiError(response.status, typeof body === "object" ? body : { message: body });
    return body;
  }

  function toast(message) {
    const box = $("toast");
    box.textContent = message;
    box.classList.remove("hidden");
    clearTimeout(toast.timer);
    toast.timer = setTimeout(() => box.classList.add("hidden"), 6000);
  }

  async function act(path, body, headers) {
    try {
      const options = { method: "POST", headers: Object.assign({}, headers || {}) };
      if (body !== undefined) {
        options.headers["Content-Type"] = "application/json";
        options.body = JSON.stringify(body);
      }
      return await api(path, options);
    } catch (err) {
      toast(err.message);
      return null;
    }
  }

  // ------------------------------------------------------------------ live stream (SSE over fetch)

  let streamAbort = null;
  let streamDelay = 1000;

  function setLive(on) {
    S.live = on;
    $("live-dot").className = `dot ${on ? "ok" : "bad"}`;
    $("live-text").textContent = on ? "live" : "reconnecting";
  }

  function restartStream() {
    if (streamAbort) streamAbort.abort();
    streamDelay = 1000;
    stream();
  }

  async function stream() {
    const controller = new AbortController();
    streamAbort = controller;
    const headers = { Accept: "text/event-stream" };
    if (S.token) headers.Authorization = `Bearer ${S.token}`;
    try {
      const response = await fetch("/api/events", { headers, signal: controller.signal, cache: "no-store" });
      if (response.status === 401) {
        setLive(false);
        askToken();
        return;
      }
      if (!response.ok || !response.body) throw new Error(`HTTP ${response.status}`);
      setLive(true);
      streamDelay = 1000;
      const reader = response.body.getReader();
      const decoder = new TextDecoder();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer += decoder.decode(value, { stream: true });
        let cut;
        while ((cut = buffer.indexOf("\n\n")) >= 0) {
          const block = buffer.slice(0, cut);
          buffer = buffer.slice(cut + 2);
          parseBlock(block);
        }
      }
    } catch (err) {
      if (controller.signal.aborted) return;
    }
    if (streamAbort !== controller) return;
    setLive(false);
    setTimeout(stream, streamDelay);
    streamDelay = Math.min(streamDelay * 2, 15000);
  }

  function parseBlock(block) {
    let kind = "message";
    const data = [];
    for (const line of block.split("\n")) {
      if (line.startsWith(":")) continue;
      if (line.startsWith("event:")) kind = line.slice(6).trim();
      else if (line.startsWith("data:")) data.push(line.slice(5).trimStart());
    }
    if (!data.length) return;
    let payload;
    try {
      payload = JSON.parse(data.join("\n"));
    } catch (err) {
      return;
    }
    dispatch(kind, payload);
  }

  const pending = new Map();
  function schedule(name, fn, delay = 250) {
    if (pending.has(name)) return;
    pending.set(name, setTimeout(() => { pending.delete(name); fn(); }, delay));
  }

  function dispatch(kind, payload) {
    if (kind === "hello") {
      if (payload.daemon) applySnapshot(payload.daemon);
      refreshAll();
      return;
    }
    const data = payload.data || {};
    if (kind === "daemon.snapshot") { applySnapshot(data); return; }
    if (kind === "loop") {
      applyLoop(data);
      if (data.state) setStateBadge(data.state);
      return;
    }
    if (kind === "joints") { mergeJoints(data.joints || []); return; }
    logEvent(kind, payload);
    if (kind === "server.closing") return;
    if (kind.startsWith("target.") || kind.startsWith("batch.")) {
      schedule("targets", refreshTargets);
      schedule("status", refreshStatus, 500);
    } else if (kind === "job.progress") {
      const job = S.jobs.find((j) => j.id === data.job_id);
      if (job) { job.progress = data.progress; job.message = data.message; renderJobs(); }
    } else if (kind.startsWith("job.")) {
      schedule("jobs", refreshJobs);
      schedule("diagnoses", refreshDiagnoses);
    } else if (kind.startsWith("model.")) {
      schedule("models", refreshModels);
      schedule("status", refreshStatus, 500);
    } else if (kind.startsWith("dataset.")) {
      schedule("datasets", refreshDatasets);
    } else if (kind.startsWith("gratings.")) {
      schedule("gratings", refreshGratings, 100);
      schedule("status", refreshStatus, 300);
    } else if (kind.startsWith("daemon.") || kind.startsWith("rsi.") || kind.startsWith("loop.")) {
      schedule("status", refreshStatus, 200);
    }
  }

  // ------------------------------------------------------------------ status, loop, joints

  async function refreshStatus() {
    try {
      const status = await api("/api/status");
      S.status = status;
      S.statusAt = Date.now();
      S.role = status.you ? status.you.role : "anonymous";
      $("who").textContent = status.you ? `${status.you.name} · ${status.you.role}` : "—";
      $("robot").textContent = status.robot;
      applySnapshot(status.daemon);
      renderRsi(status.rsi);
      renderReady();
      renderQueueChips();
      renderActions();
      if (!S.gratings || S.gratings.calibrating) refreshGratings();
    } catch (err) {
      if (err.status !== 401) toast(`status: ${err.message}`);
    }
  }

  // the daemon words a grating's fault "grating A<j>: <kind> (<detail>)"; those lines are drawn from
  // the joint rows the table shows, so that the banner and the table cannot disagree
  const GRATING_REASON = /^grating A\d+: /;

  function gratingReasons(joints) {
    return joints.filter((j) => j.encoder && j.encoder !== "ok" && j.encoder !== "absent")
      .sort((a, b) => a.joint - b.joint)
      .map((j) => `grating A${j.joint}: ${j.encoder}${j.encoder_detail ? ` (${j.encoder_detail})` : ""}`);
  }

  function currentReasons() {
    if (!S.status) return [];
    const joints = (S.snapshot && S.snapshot.joints) || [];
    return [...S.status.reasons.filter((r) => !GRATING_REASON.test(r)), ...gratingReasons(joints)];
  }

  function renderReady() {
    if (!S.status) return;
    const reasons = currentReasons();
    const ready = reasons.length === 0;
    $("ready-dot").className = `dot ${ready ? "ok" : "warn"}`;
    $("ready-text").textContent = ready ? "ready" : "not ready";
    const box = $("reasons");
    box.replaceChildren();
    if (!ready) {
      box.append(el("ul", {}, ...reasons.map((r) => el("li", {}, r))));
      box.classList.remove("hidden");
    } else {
      box.classList.add("hidden");
    }
  }

  function stateClass(state) {
    if (state === "idle") return "ok";
    if (["compensating", "moving", "settling", "running", "calibrating gratings"].includes(state)) return "info";
    if (["holding", "starting", "waiting for RSI"].includes(state)) return "warn";
    if (["stopped", "fault", "not running"].includes(state)) return "bad";
    return "";
  }

  function encoderClass(health) {
    if (!health || health === "absent") return "absent";
    if (health === "ok") return "ok";
    if (["stale", "silent", "no_data"].includes(health)) return "stale";
    return "fault";
  }

  function setStateBadge(state) {
    const badge = $("state-badge");
    const changed = badge.textContent !== state;
    badge.textContent = state;
    badge.className = `badge ${stateClass(state)}`;
    // the fault box and the buttons follow the state word (fault latched, calibrating…)
    if (changed && S.status && S.snapshot && S.snapshot.state !== state) schedule("status", refreshStatus, 100);
  }

  function mergeJoints(rows) {
    // live rows cover the joints with gratings; the others keep the last snapshot's values
    const byJoint = new Map(((S.snapshot && S.snapshot.joints) || []).map((j) => [j.joint, j]));
    for (const row of rows) byJoint.set(row.joint, Object.assign({}, byJoint.get(row.joint) || {}, row));
    const joints = [...byJoint.values()];
    if (S.snapshot) S.snapshot.joints = joints;
    renderJoints(joints);
    renderReady();
  }

  function applySnapshot(snap) {
    if (!snap) return;
    S.snapshot = snap;
    setStateBadge(snap.state);
    $("hold").textContent = snap.hold_reason ? `corrections held: ${snap.hold_reason}` : "";
    $("current-target").textContent = snap.current_target_id
      ? `target ${snap.current_target_id}${snap.phase ? " · " + snap.phase : ""}` : "no target";
    applyLoop(snap.loop || {});
    renderJoints(snap.joints || []);
    renderFault();
  }

  // RSI running or stopped, one answer for the panel's header and its stop box: the daemon's RSI
  // sessions when it tracks them (a stop is recorded once telegrams have ceased, a re-arm once the
  // controller runs again), else the loop's own "telegrams arrive"
  function rsiRunning() {
    const rsi = S.status && S.status.rsi;
    if (rsi) return rsi.running;
    return Boolean(S.loop && S.loop.running);
  }

  function renderLoopHeader() {
    const loop = S.loop || {};
    const cycle = loop.cycle_ms || (S.status && S.status.cycle_ms);
    $("cycle").textContent = cycle ? `${cycle} ms cycle · ${rsiRunning() ? "running" : "stopped"}` : "—";
  }

  function applyLoop(loop) {
    S.loop = loop;
    renderLoopHeader();
    const rsi = S.status && S.status.rsi;
    // telegrams came or ceased since the sessions were read: read them again (at most once a second)
    if (rsi && loop.running !== undefined && loop.running !== rsi.running && Date.now() - S.statusAt > 1000) {
      schedule("status", refreshStatus, 100);
    }
    $("lat-p50").textContent = fmt(loop.latency_p50_ms, 3);
    $("lat-p99").textContent = fmt(loop.latency_p99_ms, 3);
    $("lat-max").textContent = fmt(loop.latency_max_ms, 3);
    $("cycles").textContent = loop.cycles ?? "—";
    $("late").textContent = loop.late_replies ?? "—";
    $("late-kpi").className = `kpi ${loop.late_replies > 0 ? "bad" : ""}`;
    $("rejected").textContent = loop.rejected ?? "—";
    if (loop.running && loop.latency_p99_ms !== null && loop.latency_p99_ms !== undefined) {
      S.latency.push({ t: Date.now(), p99: loop.latency_p99_ms, max: loop.latency_max_ms });
      if (S.latency.length > 600) S.latency.splice(0, S.latency.length - 600);
    }
    drawLatency();
  }

  const CAUSE_WORDS = {
    late_replies: "late replies",
    timeout: "telegrams ceased",
    fault: "fault",
    operator: "operator",
  };

  function renderRsi(rsi) {
    const box = $("rsi-stop");
    const body = document.querySelector("#rsi-stops tbody");
    if (!rsi) {
      box.classList.add("hidden");
      $("rsi-summary").textContent = "—";
      body.replaceChildren();
      return;
    }
    const causes = Object.entries(rsi.stops_by_cause || {}).filter(([, n]) => n > 0)
      .map(([c, n]) => `${n} ${CAUSE_WORDS[c] || c}`).join(", ");
    $("rsi-summary").textContent = `· ${rsi.sessions} started · ${rsi.stops_total} stopped${causes ? ` (${causes})` : ""}` +
      ` · ${rsi.rearms} re-armed`;
    const last = (rsi.stops || [])[0];
    renderLoopHeader();
    if (last && !rsiRunning() && last.rearmed_at === null) {
      const when = new Date(last.time * 1000).toLocaleTimeString();
      box.replaceChildren(
        el("div", {}, el("b", {}, `RSI stopped at ${when}: ${CAUSE_WORDS[last.cause] || last.cause}`),
          ` after ${last.cycles} cycles (${last.late_replies} late replies). ${last.detail}.`),
        el("div", {}, el("b", {}, "Next: "), last.next || "—"),
      );
      box.className = `rsi-stop ${last.cause === "late_replies" || last.cause === "fault" ? "bad" : "warn"}`;
      $("rsi-sessions").open = true;
    } else {
      box.className = "rsi-stop hidden";
    }
    body.replaceChildren(...(rsi.stops || []).slice(0, 20).flatMap((s) => [
      el("tr", { class: "stop" },
        el("td", { class: "mono" }, new Date(s.time * 1000).toLocaleTimeString()),
        el("td", {}, pill(CAUSE_WORDS[s.cause] || s.cause, s.cause === "operator" ? "queued" : "failed")),
        el("td", { class: "num" }, s.cycles),
        el("td", { class: "num" }, s.late_replies)),
      el("tr", { class: "stop-detail" },
        el("td", { colspan: 4 }, el("span", { class: "detail" }, s.detail), " · ", el("b", {}, "then: "),
          el("span", { class: "then" }, s.next || "—"))),
    ]));
  }

  function renderJoints(joints) {
    const body = $("joints").tBodies[0];
    const rows = [];
    for (let j = 1; j <= 6; j++) {
      const s = joints.find((x) => x.joint === j) || { joint: j, encoder: "absent" };
      const err = s.error_deg;
      const tol = settleTol();
      const errCls = err === null || err === undefined ? "" : Math.abs(err) <= tol ? "ok" : Math.abs(err) <= roughTol() ? "warn" : "bad";
      rows.push(el("tr", {},
        el("td", {}, `J${j}`),
        el("td", { class: "num" }, fmt(s.axis_deg, 4)),
        el("td", { class: "num" }, fmt(s.target_deg, 4)),
        el("td", { class: "num" }, fmt(s.grating_deg, 4)),
        el("td", { class: "num", "data-testid": `error-j${j}` }, errCls ? el("span", { class: `pill ${errCls}` }, fmt(err, 4)) : "—"),
        el("td", { class: "num" }, fmt(s.correction_deg, 4)),
        el("td", { title: s.encoder_detail || "" }, pill(s.encoder || "absent", encoderClass(s.encoder))),
        el("td", { class: "num" }, fmt(s.reading_age_ms, 1)),
      ));
    }
    body.replaceChildren(...rows);
    drawErrors(joints);
  }

  const settleTol = () => (S.status && S.status.controller ? S.status.controller.settle_tolerance_deg : 0.001);
  const roughTol = () => (S.status && S.status.controller ? S.status.controller.rough_threshold_deg : 0.007);

  // ------------------------------------------------------------------ canvas helpers

  function canvasCtx(canvas) {
    const ratio = window.devicePixelRatio || 1;
    if (!canvas.dataset.h) {
      // fix the CSS height once: with height auto a canvas keeps its aspect ratio and would grow
      canvas.dataset.h = canvas.getAttribute("height") || "120";
      canvas.style.height = `${canvas.dataset.h}px`;
    }
    const w = canvas.clientWidth || 300;
    const h = Number(canvas.dataset.h);
    if (canvas.width !== Math.round(w * ratio) || canvas.height !== Math.round(h * ratio)) {
      canvas.width = Math.round(w * ratio);
      canvas.height = Math.round(h * ratio);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.font = "11px ui-monospace, monospace";
    return { ctx, w, h };
  }

  function drawLatency() {
    const { ctx, w, h } = canvasCtx($("latency-chart"));
    const pad = { l: 42, r: 8, t: 8, b: 16 };
    const data = S.latency;
    const top = Math.max(1.2, ...data.map((d) => d.max || 0)) * 1.1;
    const y = (v) => pad.t + (h - pad.t - pad.b) * (1 - Math.min(v, top) / top);
    ctx.strokeStyle = "#2a3642";
    ctx.fillStyle = "#8796a5";
    for (const v of [0, top / 2, top]) {
      ctx.beginPath(); ctx.moveTo(pad.l, y(v)); ctx.lineTo(w - pad.r, y(v)); ctx.stroke();
      ctx.fillText(`${v.toFixed(2)} ms`, 2, y(v) + 4);
    }
    ctx.setLineDash([4, 3]); ctx.strokeStyle = "#f85149";
    ctx.beginPath(); ctx.moveTo(pad.l, y(1)); ctx.lineTo(w - pad.r, y(1)); ctx.stroke();
    ctx.setLineDash([]);
    if (data.length < 2) {
      ctx.fillText(data.length ? "collecting…" : "no loop data", pad.l + 8, h / 2);
      return;
    }
    const x = (i) => pad.l + ((w - pad.l - pad.r) * i) / (data.length - 1);
    for (const [key, color] of [["max", "#e3a008"], ["p99", "#4fa3e0"]]) {
      ctx.strokeStyle = color; ctx.lineWidth = 1.5; ctx.beginPath();
      data.forEach((d, i) => (i ? ctx.lineTo(x(i), y(d[key] || 0)) : ctx.moveTo(x(i), y(d[key] || 0))));
      ctx.stroke();
    }
    ctx.lineWidth = 1;
  }

  function drawErrors(joints) {
    const { ctx, w, h } = canvasCtx($("error-chart"));
    const rough = roughTol();
    const tol = settleTol();
    const values = [1, 2, 3, 4, 5, 6].map((j) => {
      const s = joints.find((x) => x.joint === j);
      return s && s.error_deg !== null && s.error_deg !== undefined ? s.error_deg : null;
    });
    const span = Math.max(rough * 1.5, ...values.filter((v) => v !== null).map((v) => Math.abs(v) * 1.2));
    const mid = h / 2;
    const scale = (h / 2 - 12) / span;
    const slot = (w - 50) / 6;
    ctx.fillStyle = "rgba(63,185,80,.12)";
    ctx.fillRect(50, mid - tol * scale, w - 50, 2 * tol * scale);
    ctx.strokeStyle = "#e3a008"; ctx.setLineDash([4, 3]);
    for (const v of [rough, -rough]) { ctx.beginPath(); ctx.moveTo(50, mid - v * scale); ctx.lineTo(w, mid - v * scale); ctx.stroke(); }
    ctx.setLineDash([]); ctx.strokeStyle = "#2a3642";
    ctx.beginPath(); ctx.moveTo(50, mid); ctx.lineTo(w, mid); ctx.stroke();
    ctx.fillStyle = "#8796a5";
    ctx.fillText(`+${span.toFixed(4)}°`, 2, 12); ctx.fillText(`-${span.toFixed(4)}°`, 2, h - 4); ctx.fillText("0", 2, mid + 4);
    values.forEach((v, i) => {
      const cx = 50 + slot * i + slot / 2;
      ctx.fillStyle = "#8796a5";
      ctx.fillText(`J${i + 1}`, cx - 8, h - 2);
      if (v === null) return;
      const a = Math.abs(v);
      ctx.fillStyle = a <= tol ? "#3fb950" : a <= rough ? "#e3a008" : "#f85149";
      const bh = v * scale;
      ctx.fillRect(cx - slot * 0.25, bh >= 0 ? mid - bh : mid, slot * 0.5, Math.max(1, Math.abs(bh)));
    });
  }

  // ------------------------------------------------------------------ targets

  async function refreshTargets() {
    const all = $("show-finished").checked;
    const query = all ? "newest_first=true&limit=100" : OPEN_STATES.map((s) => `state=${s}`).join("&") + "&limit=100";
    try {
      S.targets = await api(`/api/targets?${query}`);
      renderTargets();
    } catch (err) { /* shown by status */ }
  }
  $("show-finished").addEventListener("change", refreshTargets);

  function renderQueueChips() {
    const counts = (S.status && S.status.targets) || {};
    const chips = ["queued", "compensating", "moving", "settling", "interrupted", "done", "failed", "cancelled"]
      .map((s) => el("span", { class: "chip" }, pill(s), el("b", {}, counts[s] ?? 0)));
    $("queue-chips").replaceChildren(...chips);
  }

  function finalError(t) {
    const e = t.final_joint_errors_deg;
    if (!e) return "—";
    const vals = Object.values(e).filter((v) => v !== null);
    return vals.length ? fmt(Math.max(...vals.map(Math.abs)), 4) : "—";
  }

  function renderTargets() {
    const rows = S.targets.map((t) => {
      const buttons = [];
      if (can("operator") && (t.state === "queued" || t.state === "interrupted")) {
        buttons.push(el("button", { class: "act danger", type: "button", onclick: () => act(`/api/targets/${t.id}/cancel`).then(refreshTargets) }, "cancel"));
      }
      if (can("operator") && t.state === "interrupted") {
        buttons.push(el("button", { class: "act", type: "button", onclick: () => act(`/api/targets/${t.id}/requeue`).then(refreshTargets) }, "requeue"));
      }
      return el("tr", { class: t.state === "interrupted" ? "needs-operator" : "" },
        el("td", { class: "num" }, t.id),
        el("td", { class: "num" }, t.batch_id),
        el("td", {}, t.request.pose_id || `#${t.seq}`),
        el("td", {}, pill(t.state)),
        el("td", { class: "reason", title: t.reason || "" }, t.reason || ""),
        el("td", { class: "num" }, finalError(t)),
        el("td", { class: "num sigma", title: t.model_id ? `model ${t.model_id}` : "" }, fmt(t.predicted_sigma_mm, 4)),
        el("td", {}, ...buttons),
      );
    });
    $("targets").tBodies[0].replaceChildren(...rows);
  }

  // ------------------------------------------------------------------ jobs and data sets

  async function refreshJobs() {
    try { S.jobs = await api("/api/jobs?limit=15"); renderJobs(); } catch (err) { /* status shows */ }
  }

  function renderJobs() {
    const rows = S.jobs.map((j) => {
      const note = jobNote(j);
      const step = j.state === "running" ? jobStep(j.message) : null;
      const cancel = can("engineer") && (j.state === "queued" || j.state === "running")
        ? el("button", { class: "act danger", type: "button", onclick: () => act(`/api/jobs/${j.id}/cancel`).then(refreshJobs) }, "cancel") : null;
      return el("tr", {},
        el("td", { class: "num" }, j.id),
        el("td", {}, j.kind),
        el("td", {}, pill(j.state)),
        el("td", {}, el("div", { class: "progress" }, el("span", { style: `width:${Math.round((j.progress || 0) * 100)}%` })),
          step ? el("div", { class: "job-step", "data-testid": "job-step" }, step.count) : null),
        el("td", { class: "reason", title: j.message || note || "" }, step ? step.what : note || ""),
        el("td", {}, cancel),
      );
    });
    $("jobs").tBodies[0].replaceChildren(...rows);
  }

  // a running fit's step as its progress message ends it ("fitting M: what 12 of 50, 38 to go"):
  // what it fits beside the bar, how many steps are done and remain under it
  function jobStep(message) {
    const m = /^(.*): (.+?) (\d+) of (\d+), (\d+) to go$/.exec(message || "");
    return m ? { what: `${m[1]} — ${m[2]}`, count: `${m[3]}/${m[4]}, ${m[5]} to go` } : null;
  }

  // what a job's note says: its progress message only while it runs; once ended, how it ended
  function jobNote(j) {
    if (j.state === "failed") return j.error || "failed";
    if (j.state === "cancelled") return "cancelled";
    if (j.state === "done") {
      if (j.kind === "fit") {
        const order = j.result && j.result.stats ? j.result.stats.order : null;
        return `${j.params.model || "model"} stored${order !== null && order !== undefined ? " (m=" + order + ")" : ""}`;
      }
      if (j.kind === "diagnosis") return "report ready";
      return "done";
    }
    if (j.state === "queued") return "waiting for a worker";
    return j.message || j.params.model || "";
  }

  async function refreshDatasets() {
    try { S.datasets = await api("/api/datasets?limit=10"); renderDatasets(); } catch (err) { /* status shows */ }
  }

  function renderDatasets() {
    const rows = S.datasets.map((d) => {
      const split = d.summary && d.summary.split && d.summary.split.column ? `${d.summary.split.fit}/${d.summary.split.check}` : "drawn";
      const actions = can("engineer") ? [
        el("button", { class: "act", type: "button", onclick: () => act("/api/fits", { dataset_id: d.id, model: "kinematic" }).then(refreshJobs) }, "fit kin."),
        el("button", { class: "act", type: "button", onclick: () => act("/api/fits", { dataset_id: d.id, model: "chebyshev", order: 3 }).then(refreshJobs) }, "fit cheb. 3"),
        el("button", { class: "act", type: "button", onclick: () => act("/api/diagnoses", { dataset_id: d.id }).then(refreshDiagnoses) }, "diagnose"),
      ] : [];
      return el("tr", {},
        el("td", { class: "num" }, d.id), el("td", { class: "reason", title: d.sha256 }, d.name),
        el("td", { class: "num" }, d.rows), el("td", {}, split), el("td", { class: "acts" }, ...actions));
    });
    $("datasets").tBodies[0].replaceChildren(...rows);
  }

  // ------------------------------------------------------------------ models, Table 2, Fig. 11

  async function refreshModels() {
    try {
      S.models = await api("/api/models?limit=20");
      if (!S.compareIds.length && S.models.length) {
        const active = S.models.find((m) => m.active);
        S.compareIds = [(active || S.models[0]).id];
      }
      S.compareIds = S.compareIds.filter((id) => S.models.some((m) => m.id === id));
      renderModels();
      await refreshCompare();
    } catch (err) { /* status shows */ }
  }

  function renderModels() {
    const rows = S.models.map((m) => {
      const t = m.stats && m.stats.table2 && m.stats.table2.model ? m.stats.table2.model["3d"] : null;
      const activate = can("engineer") && !m.active
        ? el("button", { class: "act", type: "button", onclick: (ev) => { ev.stopPropagation(); act(`/api/models/${m.id}/activate`).then(refreshModels); } }, "activate") : null;
      return el("tr", {
        class: `clickable ${S.compareIds.includes(m.id) ? "sel" : ""}`,
        onclick: () => toggleCompare(m.id),
      },
        el("td", { class: "num" }, m.id),
        el("td", {}, m.kind, " ", m.active ? pill("active") : null),
        el("td", { class: "num" }, m.order ?? "—"),
        el("td", { class: "num" }, t ? fmt(t.mean, 3) : "—"),
        el("td", { class: "num" }, t ? fmt(t.max, 3) : "—"),
        el("td", {}, m.dataset_id ?? "—"),
        el("td", {}, activate),
      );
    });
    $("models").tBodies[0].replaceChildren(...rows);
  }

  function toggleCompare(id) {
    const i = S.compareIds.indexOf(id);
    if (i >= 0) S.compareIds.splice(i, 1);
    else S.compareIds = [...S.compareIds, id].slice(-3);
    renderModels();
    refreshCompare();
  }

  async function refreshCompare() {
    if (!S.compareIds.length) { S.compare = null; renderCompare(); return; }
    try {
      S.compare = await api(`/api/models/compare?${S.compareIds.map((id) => `ids=${id}`).join("&")}`);
    } catch (err) { S.compare = null; }
    renderCompare();
  }

  function compareSeries() {
    if (!S.compare) return [];
    const series = [];
    const firstData = S.compare.models.length ? String(S.compare.models[0].dataset_id) : null;
    const nominal = firstData && S.compare.nominal_by_dataset[firstData];
    if (nominal) series.push({ label: "nominal", table: nominal.table2, errors: nominal.errors_3d_mm || [] });
    for (const m of S.compare.models) {
      series.push({ label: `#${m.model_id} ${m.kind}${m.order !== null && m.order !== undefined ? " m=" + m.order : ""}`, table: m.table2, errors: m.errors_3d_mm || [] });
    }
    return series;
  }

  function renderCompare() {
    const series = compareSeries();
    const rows = [];
    series.forEach((s, k) => {
      if (!s.table) return;
      ["x", "y", "z", "3d"].forEach((axis, i) => {
        const r = s.table[axis];
        const max = axis === "3d" ? r.max : r.max_abs;
        rows.push(el("tr", {},
          el("td", {}, i === 0 ? el("span", {}, el("i", { style: `display:inline-block;width:9px;height:9px;margin-right:5px;background:${COLORS[k % COLORS.length]}` }), s.label) : ""),
          el("td", {}, axis === "3d" ? "3-D" : axis),
          el("td", { class: "num" }, fmt(r.mean, 3)),
          el("td", { class: "num" }, fmt(r.std, 3)),
          el("td", { class: "num" }, fmt(max, 3)),
        ));
      });
    });
    $("table2").tBodies[0].replaceChildren(...rows);
    drawHistogram(series);
  }

  function drawHistogram(series) {
    const { ctx, w, h } = canvasCtx($("histogram"));
    const legend = $("hist-legend");
    legend.replaceChildren(...series.map((s, k) => el("span", {}, el("i", { style: `background:${COLORS[k % COLORS.length]}` }), s.label)));
    const all = series.flatMap((s) => s.errors);
    ctx.fillStyle = "#8796a5";
    if (!all.length) { ctx.fillText("select a model", 12, h / 2); return; }
    const top3d = Math.max(...all);
    const width = [0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1].find((w) => top3d / w <= 25) || 1;
    const nbins = Math.max(1, Math.ceil(top3d / width + 1e-9));
    const counts = series.map((s) => {
      const c = new Array(nbins).fill(0);
      for (const e of s.errors) c[Math.min(nbins - 1, Math.floor(e / width))] += 1;
      return c.map((n) => (s.errors.length ? (100 * n) / s.errors.length : 0));
    });
    const top = Math.max(...counts.flat()) * 1.1 || 1;
    const pad = { l: 34, r: 6, t: 8, b: 28 };
    const bw = (w - pad.l - pad.r) / nbins;
    const y = (v) => pad.t + (h - pad.t - pad.b) * (1 - v / top);
    ctx.strokeStyle = "#2a3642";
    for (const v of [0, top / 2, top]) {
      ctx.beginPath(); ctx.moveTo(pad.l, y(v)); ctx.lineTo(w - pad.r, y(v)); ctx.stroke();
      ctx.fillText(`${v.toFixed(0)}%`, 2, y(v) + 4);
    }
    counts.forEach((c, k) => {
      ctx.fillStyle = COLORS[k % COLORS.length];
      const sub = (bw * 0.85) / counts.length;
      c.forEach((v, i) => {
        if (!v) return;
        ctx.fillRect(pad.l + i * bw + bw * 0.075 + k * sub, y(v), Math.max(1, sub - 1), y(0) - y(v));
      });
    });
    ctx.fillStyle = "#8796a5";
    const step = Math.max(1, Math.ceil(nbins / 8));
    for (let i = 0; i <= nbins; i += step) ctx.fillText((i * width).toFixed(2), pad.l + i * bw - 10, h - 14);
    ctx.fillText("absolute positioning error (mm)", pad.l + 4, h - 2);
  }

  // ------------------------------------------------------------------ diagnoses

  async function refreshDiagnoses() {
    try { S.diagnoses = await api("/api/diagnoses?limit=10"); renderDiagnoses(); } catch (err) { /* status shows */ }
  }

  function renderDiagnoses() {
    const rows = S.diagnoses.map((d) => el("tr", {
      class: `clickable ${S.diagId === d.id ? "sel" : ""}`,
      onclick: () => d.state === "done" && openDiagnosis(d.id),
    },
      el("td", { class: "num" }, d.id),
      el("td", { class: "num" }, d.dataset_id ?? "—"),
      el("td", {}, pill(d.state)),
      el("td", { class: "reason", title: d.error || "" }, d.state === "failed" ? d.error : S.diagId === d.id && S.diagReport ? (S.diagReport.unmodelled.join(", ") || "none") : ""),
      el("td", {}, d.state === "done" ? el("button", { class: "act", type: "button", onclick: (ev) => { ev.stopPropagation(); openHtmlReport(d.id); } }, "HTML") : null),
    ));
    $("diagnoses").tBodies[0].replaceChildren(...rows);
  }

  async function openDiagnosis(id) {
    try {
      S.diagReport = await api(`/api/diagnoses/${id}`);
      S.diagId = id;
      renderDiagnoses();
      renderReport();
    } catch (err) { toast(err.message); }
  }

  async function openHtmlReport(id) {
    try {
      const headers = S.token ? { Authorization: `Bearer ${S.token}` } : {};
      const response = await fetch(`/api/diagnoses/${id}/report.html`, { headers });
      if (!response.ok) throw new Error((await response.json().catch(() => ({}))).message || `HTTP ${response.status}`);
      const blob = await response.blob();
      window.open(URL.createObjectURL(blob), "_blank", "noopener");
    } catch (err) { toast(err.message); }
  }

  function renderReport() {
    const r = S.diagReport;
    const box = $("diag-report");
    if (!r) { box.classList.add("hidden"); return; }
    box.classList.remove("hidden");
    const where = r.where || {};
    $("diag-summary").replaceChildren(
      el("div", {}, el("b", {}, "unmodelled: "), r.unmodelled.length ? r.unmodelled.join(", ") : "none",
        r.joints && r.joints.length ? ` · joints ${r.joints.join(", ")}` : ""),
      el("div", { class: "muted" }, `noise floor ${fmt(r.noise_floor_mm, 3)} mm · unexplained ${fmt(r.unexplained_rms_mm, 3)} mm · rows fit ${r.rows.fit} / check ${r.rows.check}`),
      where.summary ? whereSummary(where.summary) : null,
    );
    const steps = [{ effect: "nominal", joints: [], check_rms_mm: r.baseline.check_rms_mm, check_max_mm: r.baseline.check_max_mm, shrink_pct: null, significant: true }, ...r.steps];
    $("ladder").tBodies[0].replaceChildren(...steps.map((s) => el("tr", {},
      el("td", {}, stepLabel(s)),
      el("td", { class: "num" }, fmt(s.check_rms_mm, 3)), el("td", { class: "num" }, fmt(s.check_max_mm, 3)),
      el("td", { class: "num" }, s.shrink_pct === null || s.shrink_pct === undefined ? "" : fmt(s.shrink_pct, 1)),
      el("td", {}, s.significant ? pill("yes", "ok") : pill("no", "cancelled")))));
    drawLadder(steps, r.noise_floor_mm);
  }

  // the "where" text: its first sentence, the rest behind a click (it can run to a page)
  function whereSummary(text) {
    const cut = text.search(/\.\s/);
    if (cut < 0 || cut > text.length - 3) return el("div", { style: "margin-top:6px" }, text);
    return el("details", { class: "where" }, el("summary", {}, text.slice(0, cut + 1)), text.slice(cut + 2));
  }

  // a step is named by its effect and the joints it acts on: two backlash steps on A2 and on A3
  // read "backlash A2" and "backlash A3"
  const stepLabel = (s) => (s.joints && s.joints.length ? `${s.effect} ${s.joints.map((j) => `A${j}`).join(",")}` : s.effect);

  function drawLadder(steps, floor) {
    const svg = $("ladder-chart");
    const ns = "http://www.w3.org/2000/svg";
    const w = svg.clientWidth || 400;
    const h = 170;
    const pad = { l: 40, r: 6, t: 8, b: 34 };
    const top = Math.max(...steps.map((s) => s.check_rms_mm || 0), floor || 0) * 1.1 || 1;
    const bw = (w - pad.l - pad.r) / steps.length;
    const y = (v) => pad.t + (h - pad.t - pad.b) * (1 - v / top);
    const parts = [];
    const mk = (tag, attrs, text) => {
      const n = document.createElementNS(ns, tag);
      for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
      if (text !== undefined) n.textContent = text;
      return n;
    };
    steps.forEach((s, i) => {
      const v = s.check_rms_mm || 0;
      parts.push(mk("rect", { x: pad.l + i * bw + bw * 0.15, y: y(v), width: bw * 0.7, height: Math.max(1, y(0) - y(v)), fill: s.significant ? "#4fa3e0" : "#3a4552" }));
      // two lines under the bar: the effect, then its joints (long labels would run into each other)
      const label = mk("text", { x: pad.l + i * bw + bw / 2, y: h - 20, fill: "#8796a5", "font-size": 11, "text-anchor": "middle" });
      label.append(mk("tspan", { x: pad.l + i * bw + bw / 2 }, s.effect));
      if (s.joints && s.joints.length) {
        label.append(mk("tspan", { x: pad.l + i * bw + bw / 2, dy: 13, "font-size": 10 }, s.joints.map((j) => `A${j}`).join(",")));
      }
      parts.push(label);
    });
    if (floor) {
      parts.push(mk("line", { x1: pad.l, x2: w - pad.r, y1: y(floor), y2: y(floor), stroke: "#3fb950", "stroke-dasharray": "4 3" }));
      parts.push(mk("text", { x: w - pad.r, y: y(floor) - 3, fill: "#3fb950", "font-size": 10, "text-anchor": "end" }, "noise floor"));
    }
    parts.push(mk("text", { x: 2, y: pad.t + 8, fill: "#8796a5", "font-size": 10 }, `${top.toFixed(3)} mm`));
    parts.push(mk("text", { x: 2, y: y(0), fill: "#8796a5", "font-size": 10 }, "0"));
    svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
    svg.replaceChildren(...parts);
  }

  // ------------------------------------------------------------------ cell actions

  function renderCellActions() {
    const panel = $("p-actions");
    panel.classList.toggle("hidden", !can("viewer") || S.status === null);
    for (const node of panel.querySelectorAll("[data-needs]")) {
      node.classList.toggle("hidden", !can(node.dataset.needs));
    }
    $("actions-note").textContent = can("engineer") ? "engineer: all actions"
      : can("operator") ? "operator: targets and faults (campaigns and calibration need an engineer)"
        : "viewer: no actions";
    renderFault();
    renderGratings();
  }

  function confirmDialog(title, body, okText) {
    const dlg = $("confirm");
    $("confirm-title").textContent = title;
    $("confirm-body").replaceChildren(...body);
    $("confirm-ok").textContent = okText;
    return new Promise((resolve) => {
      dlg.addEventListener("close", () => resolve(dlg.returnValue === "ok"), { once: true });
      dlg.returnValue = "";
      dlg.showModal();
    });
  }

  const say = (box, cls, ...parts) => box.replaceChildren(el("div", { class: cls }, ...parts));
  const clock = () => new Date().toLocaleTimeString();

  function idempotencyKey(prefix) {
    const bytes = crypto.getRandomValues(new Uint8Array(8));
    return `${prefix}-${Date.now().toString(36)}-${[...bytes].map((b) => b.toString(16).padStart(2, "0")).join("")}`;
  }

  // where a refusal points: "row 3, column a3" (row 1 is the header), "target 2, field tx", a JSON path
  function refusalPlace(b) {
    const parts = [];
    if (b.path) parts.push(b.path);
    else if (b.row !== null && b.row !== undefined) parts.push(`${b.row_label || "row"} ${b.row}`);
    if (b.column) parts.push(`${b.row_label === "target" ? "field" : "column"} ${b.column}`);
    return parts.join(", ");
  }

  // the reason of a refusal without the place its message starts with ("x.csv, row 3, column 'a3': …"),
  // which the page shows on its own
  function refusalReason(b, err) {
    const message = b.message || err.message;
    const m = message.match(/^[^:]*?, (?:\$\S* )?(?:row|record|line|target) \d+(?:, column '[^']*')?: ([\s\S]*)$/);
    return m ? m[1] : message;
  }

  // ---- drop a file: a campaign becomes a data set, a target file is queued

  function splitCsvLine(line) {
    const cells = [];
    let cur = "";
    let quoted = false;
    for (let i = 0; i < line.length; i++) {
      const c = line[i];
      if (quoted) {
        if (c === '"' && line[i + 1] === '"') { cur += '"'; i++; } else if (c === '"') quoted = false; else cur += c;
      } else if (c === '"') quoted = true;
      else if (c === ",") { cells.push(cur); cur = ""; } else cur += c;
    }
    cells.push(cur);
    return cells;
  }

  function fileKind(name, text) {
    const body = text.replace(/^\ufeff/, "").trimStart();
    if (name.toLowerCase().endsWith(".json") || body.startsWith("[") || body.startsWith("{")) return "campaign";
    const header = splitCsvLine(body.split(/\r?\n/, 1)[0]).map((h) => h.trim());
    return ["x", "y", "z"].every((c) => header.includes(c)) ? "campaign" : "targets";
  }

  // the refused file around the row at fault, the cell at fault outlined (CSV only)
  function excerpt(text, row, column) {
    const lines = text.replace(/^\ufeff/, "").split(/\r?\n/);
    if (!row || row > lines.length) return null;
    const header = splitCsvLine(lines[0]).map((h) => h.trim());
    const col = column ? header.indexOf(column) : -1;
    const first = Math.max(2, row - 2);
    const last = Math.min(lines.length, row + 1);
    const tr = (n, cells, head) => el("tr", { class: n === row ? "bad-row" : "" },
      el(head ? "th" : "td", { class: "num muted" }, n),
      ...cells.map((c, k) => el(head ? "th" : "td", { class: n === row && (k === col || col < 0 && row === 1) ? "bad-cell" : "" }, c)));
    const rows = [tr(1, lines[0] === undefined ? [] : splitCsvLine(lines[0]), true)];
    for (let n = first; n <= last; n++) if (lines[n - 1] !== "" || n === row) rows.push(tr(n, splitCsvLine(lines[n - 1] || ""), false));
    return el("div", { class: "excerpt" }, el("table", { "data-testid": "refusal-excerpt" }, el("tbody", {}, ...rows)));
  }

  async function uploadFile(file) {
    const box = $("upload-result");
    const text = await file.text();
    const kind = fileKind(file.name, text);
    const needs = kind === "campaign" ? "engineer" : "operator";
    if (!can(needs)) {
      say(box, "bad", `${file.name} reads as a ${kind === "campaign" ? "campaign" : "target file"}: that needs the ${needs} role`);
      return;
    }
    const isJson = file.name.toLowerCase().endsWith(".json");
    say(box, "muted", `${kind === "campaign" ? "checking" : "queueing"} ${file.name}…`);
    try {
      const name = encodeURIComponent(file.name.slice(0, 200));
      if (kind === "campaign") {
        const d = await api(`/api/datasets?name=${name}`, {
          method: "POST", body: text, headers: { "Content-Type": isJson ? "application/json" : "text/csv" },
        });
        const split = d.summary && d.summary.split && d.summary.split.column ? `, ${d.summary.split.fit} fit / ${d.summary.split.check} check` : "";
        say(box, "ok", `${file.name}: stored as data set ${d.id} (${d.rows} rows${split})`);
        refreshDatasets();
      } else {
        const b = await api(`/api/batches/file?name=${name}`, {
          method: "POST", body: text, headers: { "Content-Type": "text/csv", "Idempotency-Key": idempotencyKey("file") },
        });
        say(box, "ok", `${file.name}: ${b.targets.length} target${b.targets.length === 1 ? "" : "s"} queued as batch ${b.id}`);
        refreshTargets();
      }
    } catch (err) {
      const b = err.body || {};
      const place = refusalPlace(b);
      box.replaceChildren(
        el("div", { class: "bad", "data-testid": "refusal" }, el("b", {}, `${file.name} refused`), place ? ` at ${place}` : "", ": ", refusalReason(b, err)),
        isJson ? null : excerpt(text, b.row, b.column),
      );
    }
  }

  const drop = $("drop");
  drop.addEventListener("dragover", (ev) => { ev.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (ev) => {
    ev.preventDefault();
    drop.classList.remove("over");
    const file = ev.dataTransfer && ev.dataTransfer.files[0];
    if (file) uploadFile(file);
  });
  drop.addEventListener("keydown", (ev) => { if (ev.key === "Enter" || ev.key === " ") { ev.preventDefault(); $("file-input").click(); } });
  $("file-input").addEventListener("change", (ev) => {
    const file = ev.target.files[0];
    if (file) uploadFile(file);
    ev.target.value = "";
  });

  // ---- one target from the form

  const FORMS = { axes: ["a1", "a2", "a3", "a4", "a5", "a6"], tcp: ["tx", "ty", "tz", "ta", "tb", "tc"] };

  function renderTargetFields() {
    const names = FORMS[$("t-form").value];
    $("t-fields").replaceChildren(...names.map((n) => el("label", {}, n,
      el("input", { id: `t-${n}`, name: n, inputmode: "decimal", placeholder: n.startsWith("t") && "abc".includes(n[1]) ? "optional" : "" }))));
  }
  $("t-form").addEventListener("change", renderTargetFields);
  renderTargetFields();

  $("t-current").addEventListener("click", () => {
    const joints = (S.snapshot && S.snapshot.joints) || [];
    $("t-form").value = "axes";
    renderTargetFields();
    for (const j of joints) if (j.axis_deg !== null && j.axis_deg !== undefined) $(`t-a${j.joint}`).value = Number(j.axis_deg).toFixed(4);
  });

  $("target-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const box = $("target-result");
    const record = {};
    const pose = $("t-pose").value.trim();
    if (pose) record.pose_id = pose;
    for (const n of FORMS[$("t-form").value]) {
      const input = $(`t-${n}`);
      input.classList.remove("bad");
      const v = input.value.trim();
      if (v === "") continue;
      const x = Number(v);
      record[n] = v !== "" && Number.isFinite(x) ? x : v; // the service names what is wrong with a non-number
    }
    const button = $("t-queue");
    button.disabled = true;
    try {
      const b = await api("/api/batches", {
        method: "POST", body: JSON.stringify({ targets: [record] }),
        headers: { "Content-Type": "application/json", "Idempotency-Key": idempotencyKey("form") },
      });
      const t = b.targets[0];
      say(box, "ok", `target ${t.id}${pose ? ` (${pose})` : ""} queued at ${clock()}`);
      refreshTargets();
    } catch (err) {
      const b = err.body || {};
      const field = b.column || (b.details && b.details[0] && b.details[0].field) || null;
      const name = field ? String(field).split(".").pop() : null;
      if (name && $(`t-${name}`)) $(`t-${name}`).classList.add("bad");
      const place = name ? `field ${name}` : "";
      say(box, "bad", el("b", {}, "refused"), place ? ` at ${place}` : "", ": ", refusalReason(b, err));
    } finally {
      button.disabled = false;
    }
  });

  // ---- fault: the latched fault's reason, reset with a confirmation

  function faultLatched() {
    return S.snapshot && S.snapshot.state === "fault" ? (S.snapshot.hold_reason || "a fault is latched") : null;
  }

  function renderFault() {
    const reason = faultLatched();
    const text = $("fault-text");
    if (reason) text.replaceChildren(pill("fault"), " ", el("span", { class: "fault-on" }, reason));
    else text.replaceChildren(el("span", { class: "muted" }, S.snapshot ? `no fault latched (${S.snapshot.state})` : "—"));
    $("reset-btn").disabled = !reason;
  }

  $("reset-btn").addEventListener("click", async () => {
    const reason = faultLatched();
    if (!reason) return;
    const ok = await confirmDialog("Reset the latched fault?", [
      el("p", {}, el("b", {}, "Fault: "), reason),
      el("p", { class: "muted" }, "Reset it only once its cause is cleared. A stop must also be cleared on the robot " +
        "(acknowledge on the smartPAD, start the program again: RSI_ON)."),
    ], "Reset fault");
    if (!ok) return;
    const box = $("fault-result");
    try {
      const r = await api("/api/loop/reset-fault", { method: "POST" });
      if (r.cleared) say(box, "ok", `${r.cleared.kind} (${r.cleared.reaction}) reset at ${clock()}`);
      else say(box, "muted", "no fault was latched any more");
      if (r.daemon) applySnapshot(r.daemon);
      refreshStatus();
    } catch (err) {
      say(box, "bad", `reset refused: ${(err.body && err.body.message) || err.message}`);
    }
  });

  // ---- grating calibration with its progress

  async function refreshGratings() {
    if (!can("viewer")) return;
    try {
      S.gratings = await api("/api/gratings");
    } catch (err) {
      S.gratings = { unavailable: (err.body && err.body.message) || err.message };
    }
    renderGratings();
    if (S.gratings.calibrating) schedule("gratings", refreshGratings, 700);
  }

  function renderGratings() {
    const g = S.gratings;
    const text = $("grating-text");
    const bar = $("grating-progress");
    const button = $("calibrate-btn");
    if (!g) { text.textContent = "—"; bar.classList.add("hidden"); button.disabled = true; return; }
    if (g.unavailable) { text.textContent = g.unavailable; bar.classList.add("hidden"); button.disabled = true; return; }
    const cal = g.calibration;
    const inUse = cal
      ? `in use: version ${cal.version}${cal.created_at ? ` of ${new Date(cal.created_at).toLocaleString()}` : ""}; residual rms ` +
        cal.joints.map((m) => `A${m.joint} ${m.residual_rms_deg.toFixed(4)}°`).join(", ")
      : "no calibration in use";
    const parts = [el("div", {}, inUse)];
    if (g.calibrating) {
      const done = g.poses_measured ?? 0;
      const total = g.poses_total;
      parts.unshift(el("div", { "data-testid": "grating-progress" }, el("b", {}, "calibrating: "),
        total ? `${done} of ${total} poses measured` : "starting"));
      bar.classList.remove("hidden");
      $("grating-bar").style.width = `${total ? Math.round((100 * done) / total) : 2}%`;
    } else {
      bar.classList.add("hidden");
      if (g.last_error) parts.push(el("div", { class: "fault-on" }, `last attempt failed: ${g.last_error}`));
      else if (g.finished_at && cal) parts.push(el("div", { class: "muted" }, `last run ended ${new Date(g.finished_at * 1000).toLocaleTimeString()}`));
    }
    text.replaceChildren(...parts);
    const busy = S.snapshot && ["compensating", "moving", "settling"].includes(S.snapshot.state);
    button.disabled = Boolean(g.calibrating || busy);
    button.title = busy ? "a target is active; calibrate between targets" : "";
  }

  $("calibrate-btn").addEventListener("click", async () => {
    const ok = await confirmDialog("Calibrate the gratings?", [
      el("p", {}, "The robot moves through the calibration poses near its home position (each approached " +
        "from both sides) while the gratings are read; no target runs meanwhile."),
      el("p", { class: "muted" }, "The new calibration replaces the one in use when it succeeds."),
    ], "Calibrate");
    if (!ok) return;
    const box = $("grating-result");
    try {
      S.gratings = await api("/api/gratings/calibrate", { method: "POST" });
      say(box, "muted", `started at ${clock()}`);
      renderGratings();
      schedule("gratings", refreshGratings, 500);
    } catch (err) {
      say(box, "bad", `not started: ${(err.body && err.body.message) || err.message}`);
    }
  });

  // ------------------------------------------------------------------ event log, actions, clock

  function logEvent(kind, payload) {
    const log = $("log");
    const t = new Date((payload.time || Date.now() / 1000) * 1000).toLocaleTimeString();
    const data = Object.assign({}, payload.data || {});
    delete data.id;
    const text = Object.entries(data).filter(([, v]) => v !== null && v !== undefined)
      .map(([k, v]) => `${k}=${typeof v === "object" ? JSON.stringify(v) : v}`).join(" ");
    log.prepend(el("div", {}, el("span", { class: "t" }, t), el("span", { class: "k" }, kind), text));
    while (log.childElementCount > 200) log.lastElementChild.remove();
  }

  function renderActions() {
    renderCellActions();
    renderTargets();
    renderJobs();
    renderDatasets();
    renderModels();
  }

  async function loadRecentEvents() {
    try {
      const rows = await api("/api/events/log?newest_first=true&limit=50");
      for (const e of rows.reverse()) {
        const data = Object.assign({}, e.message, e.target_id ? { target_id: e.target_id } : {}, e.job_id ? { job_id: e.job_id } : {});
        logEvent(e.kind, { time: Date.parse(e.time) / 1000, data });
      }
    } catch (err) { /* status shows */ }
  }

  function refreshAll() {
    refreshStatus();
    refreshTargets();
    refreshJobs();
    refreshDatasets();
    refreshModels();
    refreshDiagnoses();
  }

  function tick() {
    $("clock").textContent = new Date().toLocaleTimeString();
  }

  window.addEventListener("resize", () => { drawLatency(); if (S.snapshot) drawErrors(S.snapshot.joints || []); renderCompare(); });

  initToken();
  tick();
  loadRecentEvents();
  setInterval(tick, 1000);
  setInterval(refreshStatus, 5000);
  setInterval(refreshTargets, 15000);
  refreshAll();
  stream();
})();
