// The engine's web console (engine/ops/console.py): state from /console/events (server-sent
// events, once a second), a live tap from /tap/ROUTE (JSON lines). No library, no build step.
// Under run --workers N the supervisor serves it (engine/ops/supervisor_admin.py): the state
// then has the workers, shown in their own table, and each route names the workers running it.
// URLs are built on location.origin: a page opened as https://user:token@host/ has credentials
// in its own URL, and fetch() refuses a URL that carries them.
"use strict";

const origin = window.location.origin;
const TAP_LINES = 100;

function el(tag, attributes, text) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes || {})) node.setAttribute(key, value);
  if (text !== undefined && text !== null) node.textContent = String(text);
  return node;
}

function svg(tag, attributes, text) {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [key, value] of Object.entries(attributes || {})) node.setAttribute(key, value);
  if (text !== undefined) node.textContent = String(text);
  return node;
}

function time(seconds) {
  return seconds ? new Date(seconds * 1000).toLocaleTimeString() : "";
}

function rate(perSecond) {
  return perSecond == null ? "" : perSecond.toFixed(1);
}

function colour(name) {
  let hash = 2166136261;  // FNV-1a: a stable colour per agent
  for (const c of name) hash = Math.imul(hash ^ c.charCodeAt(0), 16777619) >>> 0;
  return `hsl(${hash % 360}, 70%, 42%)`;
}

function renderRoutes(routes) {
  const body = document.querySelector("#routes tbody");
  const rows = Object.entries(routes).map(([name, route]) => {
    const messages = route.messages || {};
    const row = el("tr", {"data-route": name, "class": "state-" + route.state});
    row.append(el("td", {"class": "name"}, name), el("td", {"class": "state"}, route.state),
      el("td", {"class": "num received"}, messages.received), el("td", {"class": "num delivered"}, messages.delivered),
      el("td", {"class": "num dead-lettered"}, messages.dead_lettered),
      el("td", {"class": "num"}, rate(route.received_per_s)), el("td", {"class": "num"}, rate(route.delivered_per_s)),
      el("td", {"class": "on-workers workers"}, (route.workers || []).join(", ")),
      el("td", {"class": "error", "title": time(route.last_error_at)}, route.last_error || ""));
    return row;
  });
  body.replaceChildren(...rows);
  const select = document.getElementById("tap-route");
  const names = Object.keys(routes);
  if (select.options.length !== names.length || names.some((name, i) => select.options[i].value !== name)) {
    const chosen = select.value;
    select.replaceChildren(...names.map((name) => el("option", {value: name}, name)));
    if (names.includes(chosen)) select.value = chosen;
  }
}

function duration(seconds) {
  if (!seconds) return "";
  return seconds < 120 ? `${Math.round(seconds)} s` : seconds < 7200 ? `${Math.round(seconds / 60)} min` : `${(seconds / 3600).toFixed(1)} h`;
}

const cpuSeen = new Map();  // worker index -> {pid, cpu, at}: its CPU share from two successive states

function cpuShare(worker, now) {
  const before = cpuSeen.get(worker.index);
  if (worker.cpu_s == null) return "";
  cpuSeen.set(worker.index, {pid: worker.pid, cpu: worker.cpu_s, at: now});
  if (!before || before.pid !== worker.pid || now <= before.at) return "";
  return (100 * (worker.cpu_s - before.cpu) / ((now - before.at) / 1000)).toFixed(0);
}

function renderWorkers(workers) {
  const panel = document.getElementById("workers-panel");
  document.body.classList.toggle("workers", workers.length > 0);
  panel.hidden = workers.length === 0;  // one engine: no workers, no table
  if (!workers.length) return;
  const now = Date.now();
  const up = workers.filter((w) => w.up).length;
  document.getElementById("workers-count").textContent = `(${up}/${workers.length} up)`;
  document.querySelector("#workers tbody").replaceChildren(...workers.map((worker) => {
    const row = el("tr", {"data-worker": worker.index, "class": worker.up ? "worker-up" : "worker-down"});
    const state = worker.up ? "up" : (worker.last_exit != null ? `down (exit ${worker.last_exit})` : "starting");
    row.append(el("td", {"class": "index"}, worker.index), el("td", {"class": "num pid"}, worker.pid),
      el("td", {"class": "state"}, state), el("td", {"class": "num restarts"}, worker.restarts),
      el("td", {"class": "num uptime"}, duration(worker.uptime_s)), el("td", {"class": "num cpu"}, cpuShare(worker, now)),
      el("td", {"class": "num cpu-s"}, worker.cpu_s), el("td", {"class": "num rss"}, worker.rss_mib),
      el("td", {"class": "routes"}, (worker.routes || []).join(", ")));
    return row;
  }));
}

function renderDeadLetters(entries) {
  const body = document.querySelector("#dead-letters tbody");
  body.replaceChildren(...entries.map((entry) => {
    const row = el("tr", {"data-route": entry.route});
    row.append(el("td", {"title": entry.worker != null ? `worker ${entry.worker}` : ""}, time(entry.at)),
      el("td", {}, entry.route), el("td", {"class": "stage"}, entry.stage), el("td", {"class": "reason"}, entry.reason));
    return row;
  }));
}

// Equirectangular projection around the fleet's centre: metres east and north, the same scale
// on both axes (drawn to scale over the few kilometres of a field), with a scale bar.
function renderFleet(agents) {
  const map = document.getElementById("map");
  const width = 600, height = 400, margin = 40;
  document.getElementById("fleet-count").textContent = agents.length ? `(${agents.length} agents)` : "(no positions yet)";
  const shapes = [];
  if (agents.length) {
    const lat0 = agents.reduce((sum, a) => sum + a.lat, 0) / agents.length;
    const lon0 = agents.reduce((sum, a) => sum + a.lon, 0) / agents.length;
    const perDegreeNorth = 111320, perDegreeEast = 111320 * Math.cos(lat0 * Math.PI / 180);
    const points = agents.map((a) => ({agent: a, x: (a.lon - lon0) * perDegreeEast, y: (a.lat - lat0) * perDegreeNorth}));
    const spanX = Math.max(...points.map((p) => Math.abs(p.x))), spanY = Math.max(...points.map((p) => Math.abs(p.y)));
    const scale = Math.min((width / 2 - margin) / Math.max(spanX, 50), (height / 2 - margin) / Math.max(spanY, 50));
    for (const p of points) {
      const x = width / 2 + p.x * scale, y = height / 2 - p.y * scale;
      const id = p.agent.agent_id;
      const title = `${id} ${p.agent.lat.toFixed(6)}, ${p.agent.lon.toFixed(6)}` +
        (p.agent.alt_rel != null ? ` ${p.agent.alt_rel} m` : "") +
        ` (${p.agent.route}${p.agent.worker != null ? ", worker " + p.agent.worker : ""}, ${time(p.agent.at)})`;
      const dot = svg("circle", {cx: x.toFixed(1), cy: y.toFixed(1), r: 6, fill: colour(id), "data-agent": id});
      dot.append(svg("title", {}, title));
      shapes.push(dot, svg("text", {x: (x + 9).toFixed(1), y: (y + 4).toFixed(1), "class": "agent-label"}, id));
    }
    // a scale bar of a round length near a fifth of the width
    const target = width / 5 / scale;
    const step = Math.pow(10, Math.floor(Math.log10(target)));
    const metres = [1, 2, 5, 10].map((k) => k * step).filter((m) => m <= target).pop() || step;
    const length = metres * scale;
    shapes.push(svg("line", {x1: 16, y1: height - 16, x2: 16 + length, y2: height - 16, "class": "scale"}),
      svg("text", {x: 16, y: height - 22, "class": "scale-label"}, metres >= 1000 ? `${metres / 1000} km` : `${metres} m`));
  }
  shapes.push(svg("text", {x: width - 16, y: 20, "text-anchor": "end"}, "N ↑"));
  map.replaceChildren(...shapes);
}

function render(state) {
  const routes = state.routes || {};
  const connections = Object.values(state.connections || {});
  const up = connections.filter((c) => c.up).length;
  const workers = state.workers || [];
  document.getElementById("summary").textContent =
    `generation ${state.generation} · ${Object.keys(routes).length} routes · ${up}/${connections.length} connections up` +
    (workers.length ? ` · ${workers.filter((w) => w.up).length}/${workers.length} workers up` : "");
  renderWorkers(workers);
  renderRoutes(routes);
  renderDeadLetters(state.recent_dead_letters || []);
  renderFleet(state.fleet || []);
}

function connect() {
  const live = document.getElementById("live");
  const events = new EventSource(origin + "/console/events");
  events.addEventListener("state", (event) => {
    live.textContent = "live";
    live.className = "up";
    render(JSON.parse(event.data));
  });
  events.onerror = () => { live.textContent = "reconnecting"; live.className = "down"; };  // EventSource retries by itself
}

let tap = null;  // the AbortController of the open tap

async function startTap(route) {
  const list = document.getElementById("tap-lines"), state = document.getElementById("tap-state");
  const controller = new AbortController();
  tap = controller;
  list.replaceChildren();
  state.textContent = `tapping ${route}`;
  try {
    const response = await fetch(origin + "/tap/" + encodeURIComponent(route), {signal: controller.signal});
    if (!response.ok) throw new Error(`${response.status} ${await response.text()}`);
    const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
    let pending = "";
    for (;;) {
      const {value, done} = await reader.read();
      if (done) break;
      pending += value;
      const lines = pending.split("\n");
      pending = lines.pop();
      for (const line of lines.filter((l) => l)) {
        const record = JSON.parse(line);
        const item = el("li", {"class": "outcome-" + record.outcome},
          `${time(record.ts)} ${record.outcome}${record.error ? " " + record.error : ""} ` +
          JSON.stringify(record.canonical ?? record.source));  // a message dead-lettered before its mapping: as received
        list.prepend(item);
        while (list.children.length > TAP_LINES) list.lastChild.remove();
      }
    }
    state.textContent = `tap of ${route} ended`;
  } catch (error) {
    if (!controller.signal.aborted) state.textContent = `tap of ${route} failed: ${error.message}`;
  }
}

function stopTap() {
  if (tap) tap.abort();
  tap = null;
  document.getElementById("tap-state").textContent = "";
}

document.getElementById("tap-toggle").addEventListener("click", (event) => {
  const button = event.target;
  if (tap) {
    stopTap();
    button.textContent = "start";
  } else {
    startTap(document.getElementById("tap-route").value);
    button.textContent = "stop";
  }
});
document.getElementById("tap-route").addEventListener("change", (event) => {
  if (tap) { stopTap(); startTap(event.target.value); }
});

connect();
