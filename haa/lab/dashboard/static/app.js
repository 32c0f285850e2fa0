// HAA dashboard page: one WebSocket to the haactl that served this page; four views (docs/dashboard.md).
// Plain JavaScript, no build step, nothing loaded from elsewhere.
"use strict";

// Agent states and their colours (thesis §6.1.4 item 2; the same names as `haactl agent list`).
const STATE_COLOURS = {
  spawning: "#29b6f6", active: "#43a047", freezing: "#fbc02d", frozen: "#bdbdbd", thawing: "#3949ab",
  crashed: "#e53935", recovering: "#ab47bc", failed: "#7f0000", new: "#9e9e9e",
};
const AVATAR_COLOURS = ["#1e88e5", "#e53935", "#43a047", "#fb8c00", "#8e24aa", "#00897b", "#6d4c41", "#d81b60"];

const S = {
  map: null, mapImage: null, obstacles: null, obstacleImage: null, overlay: null, truth: null, arena: null,
  agents: [], hosts: [], group: {}, sources: {}, ddb: new Map(), ddbSeq: 0, timeline: [], timelineNext: 0,
  t0: 0, clockSkew: 0, layers: {}, selected: null, collapsed: new Set(), ddbOpen: new Set(["", "avatar:"]),
  avatarColour: {},
};
// What the page has drawn, for tests and the latency measurement (times are Date.now(), ms).
window.HAA = { drawn: { map: null, overlay: null, agents: null, ddb: null }, messages: 0, connected: false };

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));

function colourOf(avatar) {
  if (!(avatar in S.avatarColour)) {
    S.avatarColour[avatar] = AVATAR_COLOURS[Object.keys(S.avatarColour).length % AVATAR_COLOURS.length];
  }
  return S.avatarColour[avatar];
}

function afterPaint(fn) { requestAnimationFrame(() => setTimeout(fn, 0)); }

// ------------------------------------------------------------------------------------------------ connection

let ws = null;
function connect() {
  ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws");
  ws.onopen = () => { setConn(true); };
  ws.onclose = () => { setConn(false); setTimeout(connect, 1000); };
  ws.onmessage = (ev) => { window.HAA.messages++; handle(JSON.parse(ev.data)); };
}
function setConn(ok) {
  window.HAA.connected = ok;
  $("conn").textContent = ok ? "live" : "disconnected";
  $("conn").className = ok ? "good" : "bad";
}

const dirty = { map: false, tree: false, ddb: false, timeline: false, detail: false };
function handle(m) {
  switch (m.type) {
    case "hello":
      $("cluster").textContent = m.cluster;
      S.clockSkew = Date.now() / 1000 - m.now;
      break;
    case "hosts":
      S.hosts = m.hosts; S.group = m.group || {}; S.sources = m.sources || {};
      showHosts(); dirty.timeline = true;
      break;
    case "agents":
      S.agents = m.agents; dirty.tree = true; dirty.timeline = true;
      $("agent-count").textContent = String(m.agents.length);
      if (S.selected && S.selected.kind === "agent") dirty.detail = true;
      break;
    case "map":
      S.map = m; S.mapImage = gridImage(m, (q) => { const g = 255 - q; return [g, g, g, 255]; });
      dirty.map = true;
      break;
    case "overlay":
      S.overlay = m; dirty.map = true; showMission(); showTranscript();
      break;
    case "truth":
      S.truth = m; dirty.map = true;
      break;
    case "arena":
      S.arena = m;
      S.obstacleImage = gridImage(m.obstacles, (q) => (q ? [200, 40, 40, 150] : [0, 0, 0, 0]));
      dirty.map = true;
      break;
    case "ddb":
      if (m.full) S.ddb = new Map();
      for (const e of m.entries || m.set || []) S.ddb.set(e[0], e);
      for (const k of m.del || []) S.ddb.delete(k);
      S.ddbSeq = m.seq; dirty.ddb = true;
      if (S.selected && S.selected.kind === "ddb" && ((m.set || []).some((e) => e[0] === S.selected.key) || m.full)) {
        requestObject(S.selected.key);
      }
      break;
    case "timeline":
      if (m.full) { S.timeline = []; S.timelineNext = 0; }
      if (m.t0) S.t0 = m.t0;
      for (const e of m.events) {
        if (e.i !== undefined && e.i <= S.timelineNext) continue;
        S.timeline.push(e); if (e.i !== undefined) S.timelineNext = e.i;
      }
      dirty.timeline = true;
      break;
    case "object":
      showObject(m.object);
      break;
  }
  schedule();
}

let scheduled = false;
function schedule() {
  if (scheduled) return;
  scheduled = true;
  requestAnimationFrame(() => {
    scheduled = false;
    if (dirty.map) { dirty.map = false; drawMap(); }
    if (dirty.tree) { dirty.tree = false; drawTree(); }
    if (dirty.ddb) { dirty.ddb = false; drawDdb(); }
    if (dirty.timeline) { dirty.timeline = false; drawTimeline(); }
    if (dirty.detail) { dirty.detail = false; showAgentDetail(); }
  });
}

// ------------------------------------------------------------------------------------------------ header

function showHosts() {
  const members = new Set(S.group.members || []);
  $("hosts").innerHTML = S.hosts.map((h) => {
    const c = h.state !== "alive" ? "bad" : members.size && !members.has(h.name) ? "dim" : "good";
    const lead = S.group.leader === h.name ? "*" : "";
    return `<span class="${c}" title="${esc(h.state)} ${esc(h.address)}">${esc(h.name)}${lead}</span>`;
  }).join(" ");
}

function showMission() {
  const o = S.overlay; const st = o && o.status; const mi = o && o.mission;
  if (!st && !mi) { $("mission").textContent = ""; return; }
  const parts = [];
  if (mi && mi.name) parts.push(`mission ${mi.name}`);
  if (st) {
    parts.push(st.state);
    if (typeof st.t === "number") parts.push(`t ${st.t.toFixed(1)} s`);
    if (typeof st.explored === "number") parts.push(`explored ${(100 * st.explored).toFixed(1)} %`);
  }
  $("mission").textContent = parts.join(" · ");
}

function showTranscript() {
  const lines = (S.overlay && S.overlay.transcript) || [];
  const el = $("transcript");
  const atEnd = el.scrollTop + el.clientHeight >= el.scrollHeight - 4;
  el.innerHTML = lines.map((l) => {
    const t = typeof l.t === "number" ? `${String(Math.floor(l.t / 60)).padStart(2, "0")}:${String(Math.floor(l.t % 60)).padStart(2, "0")} ` : "";
    return `<div><span class="dim">${t}</span>${esc(l.text || "")}</div>`;
  }).join("");
  if (atEnd) el.scrollTop = el.scrollHeight;
}

// ------------------------------------------------------------------------------------------------ map

function gridImage(g, colour) {
  const cells = Uint8Array.from(atob(g.cells), (c) => c.charCodeAt(0));
  const cv = document.createElement("canvas");
  cv.width = g.w; cv.height = g.h;
  const ctx = cv.getContext("2d");
  const img = ctx.createImageData(g.w, g.h);
  for (let r = 0; r < g.h; r++) {
    const dst = (g.h - 1 - r) * g.w; // row 0 is the lowest y: drawn at the bottom
    for (let c = 0; c < g.w; c++) {
      const rgba = colour(cells[r * g.w + c]);
      const i = (dst + c) * 4;
      img.data[i] = rgba[0]; img.data[i + 1] = rgba[1]; img.data[i + 2] = rgba[2]; img.data[i + 3] = rgba[3];
    }
  }
  ctx.putImageData(img, 0, 0);
  return cv;
}

function worldBounds() {
  const g = S.map || (S.arena && S.arena.obstacles);
  if (g) return { x0: g.x0, y0: g.y0, w: g.w * g.res, h: g.h * g.res };
  return { x0: 0, y0: 0, w: 4, h: 4 };
}

function drawMap() {
  const cv = $("map");
  const dpr = window.devicePixelRatio || 1;
  const W = cv.clientWidth, H = cv.clientHeight;
  if (cv.width !== Math.round(W * dpr) || cv.height !== Math.round(H * dpr)) {
    cv.width = Math.round(W * dpr); cv.height = Math.round(H * dpr);
  }
  const ctx = cv.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#fafafa"; ctx.fillRect(0, 0, W, H);
  const b = worldBounds();
  const pad = 8;
  const s = Math.max(1e-6, Math.min((W - 2 * pad) / b.w, (H - 2 * pad) / b.h));
  const ox = (W - s * b.w) / 2, oy = (H - s * b.h) / 2;
  const X = (x) => ox + (x - b.x0) * s;
  const Y = (y) => oy + (b.h - (y - b.y0)) * s;
  const L = S.layers;
  ctx.imageSmoothingEnabled = false;
  if (L.grid && S.mapImage) {
    ctx.drawImage(S.mapImage, X(S.map.x0), Y(S.map.y0 + S.map.h * S.map.res), S.map.w * S.map.res * s, S.map.h * S.map.res * s);
  } else {
    ctx.fillStyle = "#bdbdbd"; ctx.fillRect(X(b.x0), Y(b.y0 + b.h), b.w * s, b.h * s);
  }
  if (L.obstacles && S.obstacleImage) {
    const g = S.arena.obstacles;
    ctx.drawImage(S.obstacleImage, X(g.x0), Y(g.y0 + g.h * g.res), g.w * g.res * s, g.h * g.res * s);
  }
  ctx.strokeStyle = "#90a4ae"; ctx.lineWidth = 1; ctx.strokeRect(X(b.x0), Y(b.y0 + b.h), b.w * s, b.h * s);
  const o = S.overlay || {};
  if (L.particles && o.particles) {
    for (const [a, p] of Object.entries(o.particles)) {
      ctx.fillStyle = colourOf(a) + "90";
      for (const [x, y] of p.points) ctx.fillRect(X(x) - 1, Y(y) - 1, 2, 2);
    }
  }
  if (L.paths) {
    for (const [a, pts] of Object.entries(o.paths || {})) polyline(ctx, pts, X, Y, colourOf(a), 1, []);
    for (const [a, pts] of Object.entries(o.planned || {})) polyline(ctx, pts, X, Y, colourOf(a), 1.5, [5, 4]);
  }
  if (L.landmarks) {
    if (L.truth && S.arena) {
      for (const m of S.arena.landmarks) {
        ctx.strokeStyle = "#546e7a"; ctx.lineWidth = 1;
        ctx.strokeRect(X(m.x) - 4, Y(m.y) - 4, 8, 8);
      }
    }
    for (const [id, v] of Object.entries(o.landmarks || {})) {
      const [x, y, sd] = v;
      ctx.strokeStyle = "#00838f"; ctx.lineWidth = 1.5;
      cross(ctx, X(x), Y(y), 5);
      if (sd > 0) { // one standard deviation
        ctx.strokeStyle = "#00838f60"; ctx.lineWidth = 1;
        ctx.beginPath(); ctx.arc(X(x), Y(y), Math.max(2, sd * s), 0, 2 * Math.PI); ctx.stroke();
      }
      ctx.fillStyle = "#00838f"; ctx.font = "10px sans-serif"; ctx.fillText(id, X(x) + 6, Y(y) - 4);
    }
  }
  if (L.targets) {
    for (const [a, t] of Object.entries(o.targets || {})) {
      if (typeof t.x !== "number") continue;
      const e = (o.estimates || {})[a];
      ctx.strokeStyle = colourOf(a); ctx.lineWidth = 1;
      if (e) { ctx.setLineDash([2, 3]); ctx.beginPath(); ctx.moveTo(X(e.x), Y(e.y)); ctx.lineTo(X(t.x), Y(t.y)); ctx.stroke(); ctx.setLineDash([]); }
      ctx.lineWidth = 2; cross(ctx, X(t.x), Y(t.y), 6, true);
    }
  }
  if (L.truth && S.truth) {
    for (const [a, p] of Object.entries(S.truth.avatars || {})) {
      if (p.status && p.status !== "active") continue;
      pose(ctx, X(p.x), Y(p.y), p.theta, Math.max(4, (p.radius || 0.1) * s), "#37474f", false);
    }
  }
  if (L.estimates) {
    for (const [a, e] of Object.entries(o.estimates || {})) {
      const r = Math.max(4, radiusOf(a) * s);
      const sd = e.std ? Math.hypot(e.std[0], e.std[1]) : 0;
      if (sd > 0) { // one standard deviation of the position estimate
        ctx.strokeStyle = colourOf(a) + "a0"; ctx.lineWidth = 1; ctx.setLineDash([4, 3]);
        ctx.beginPath(); ctx.arc(X(e.x), Y(e.y), sd * s, 0, 2 * Math.PI); ctx.stroke(); ctx.setLineDash([]);
      }
      pose(ctx, X(e.x), Y(e.y), e.theta, r, colourOf(a), true);
      ctx.fillStyle = "#000"; ctx.font = "11px sans-serif"; ctx.fillText(a, X(e.x) + r + 2, Y(e.y) + r + 8);
    }
  }
  const info = [];
  if (S.map) info.push(`map ${S.map.w}×${S.map.h} cells of ${S.map.res} m (DDB v${S.map.version})`);
  else info.push("no map published yet (slam/map)");
  if (S.truth) info.push(`true poses at t ${S.truth.t.toFixed(1)} s (haa-sim, display only)`);
  else info.push(S.sources.truth ? `ground truth: ${S.sources.truth}` : "");
  if (o.particles && Object.keys(o.particles).length) info.push("particles of the latest SLAM checkpoint");
  $("map-info").textContent = info.filter(Boolean).join(" · ");
  const now = Date.now();
  const mapV = S.map ? S.map.version : null, ovSeq = o.seq;
  afterPaint(() => {
    window.HAA.drawn.map = { version: mapV, at: now, painted: Date.now() };
    window.HAA.drawn.overlay = { seq: ovSeq, at: now, painted: Date.now() };
  });
}

function radiusOf(a) {
  const t = S.truth && S.truth.avatars && S.truth.avatars[a];
  return t && t.radius ? t.radius : 0.1;
}

function polyline(ctx, pts, X, Y, colour, width, dash) {
  if (!pts || pts.length < 2) return;
  ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.setLineDash(dash);
  ctx.beginPath(); ctx.moveTo(X(pts[0][0]), Y(pts[0][1]));
  for (const p of pts) ctx.lineTo(X(p[0]), Y(p[1]));
  ctx.stroke(); ctx.setLineDash([]);
}

function cross(ctx, x, y, r, diag) {
  ctx.beginPath();
  if (diag) { ctx.moveTo(x - r, y - r); ctx.lineTo(x + r, y + r); ctx.moveTo(x - r, y + r); ctx.lineTo(x + r, y - r); }
  else { ctx.moveTo(x - r, y); ctx.lineTo(x + r, y); ctx.moveTo(x, y - r); ctx.lineTo(x, y + r); }
  ctx.stroke();
}

function pose(ctx, x, y, theta, r, colour, filled) {
  ctx.beginPath(); ctx.arc(x, y, r, 0, 2 * Math.PI);
  if (filled) { ctx.fillStyle = colour; ctx.fill(); }
  ctx.strokeStyle = filled ? "#000" : colour; ctx.lineWidth = filled ? 1 : 1.5; ctx.setLineDash(filled ? [] : [3, 2]);
  ctx.stroke(); ctx.setLineDash([]);
  ctx.beginPath(); ctx.moveTo(x, y); ctx.lineTo(x + Math.cos(theta) * r * 1.6, y - Math.sin(theta) * r * 1.6);
  ctx.strokeStyle = filled ? "#000" : colour; ctx.lineWidth = 1.5; ctx.stroke();
}

// ------------------------------------------------------------------------------------------------ hierarchy

function badge(state) {
  return `<span class="badge" style="background:${STATE_COLOURS[state] || "#607d8b"}">${esc(state)}</span>`;
}
function rate(v) { return v === null || v === undefined ? "–" : v < 10 ? v.toFixed(1) : v.toFixed(0); }

function drawTree() {
  const byId = new Map(S.agents.map((a) => [a.id, a]));
  const kids = new Map();
  for (const a of S.agents) {
    const p = byId.has(a.parent) ? a.parent : "";
    if (!kids.has(p)) kids.set(p, []);
    kids.get(p).push(a);
  }
  const counts = {};
  for (const a of S.agents) counts[a.state] = (counts[a.state] || 0) + 1;
  $("tree-summary").textContent = Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(", ");
  const sel = S.selected && S.selected.kind === "agent" ? S.selected.id : null;
  const render = (parent, depth) => {
    const list = kids.get(parent) || [];
    if (!list.length) return "";
    return `<ul class="tree">` + list.map((a) => {
      const has = (kids.get(a.id) || []).length;
      const open = !S.collapsed.has(a.id);
      const tw = has ? `<span class="twisty" data-tw="${a.id}">${open ? "▾" : "▸"}</span>` : `<span class="twisty"></span>`;
      const line = `<div class="node${sel === a.id ? " sel" : ""}" data-agent="${a.id}">${tw}<b>${esc(a.name)}</b> ` +
        `${esc(a.type)} ${badge(a.state)} <span class="dim">on</span> ${esc(a.host || "–")} ` +
        `<span class="num">cpu ${(100 * a.cpu).toFixed(1)} %</span> ` +
        `<span class="num">msg/s ${rate(a.rate_in)} in ${rate(a.rate_out)} out</span>` +
        (has ? ` <span class="dim">(${has})</span>` : "") + `</div>`;
      return `<li>${line}${has && open ? render(a.id, depth + 1) : ""}</li>`;
    }).join("") + `</ul>`;
  };
  $("tree").innerHTML = render("", 0) || `<div class="dim">no agents</div>`;
  const now = Date.now(), n = S.agents.length;
  afterPaint(() => { window.HAA.drawn.agents = { count: n, at: now }; });
}

$("tree").addEventListener("click", (ev) => {
  const tw = ev.target.closest("[data-tw]");
  if (tw) {
    const id = tw.dataset.tw;
    if (S.collapsed.has(id)) S.collapsed.delete(id); else S.collapsed.add(id);
    drawTree(); return;
  }
  const n = ev.target.closest("[data-agent]");
  if (n) { S.selected = { kind: "agent", id: n.dataset.agent }; drawTree(); showAgentDetail(); }
});

function showAgentDetail() {
  if (!S.selected || S.selected.kind !== "agent") return;
  const a = S.agents.find((x) => x.id === S.selected.id);
  if (!a) { $("detail").textContent = "(agent gone)"; return; }
  const parent = S.agents.find((x) => x.id === a.parent);
  const children = S.agents.filter((x) => x.parent === a.id).map((x) => `${x.name} (${x.type})`);
  $("detail-title").textContent = `Agent ${a.name}`;
  $("detail").textContent = [
    `id        ${a.id}`, `type      ${a.type}`, `state     ${a.state} (table: ${a.status})`,
    `host      ${a.host || "-"}   owner ${a.owner || "-"}   allocated to ${a.alloc || "-"}`,
    `parent    ${parent ? parent.name + " (" + parent.type + ")" : a.parent ? a.parent.slice(0, 8) : "- (top level)"}`,
    `children  ${children.join(", ") || "-"}`,
    `cpu       ${(100 * a.cpu).toFixed(1)} % of a core`,
    `messages  ${a.msgs_in} in, ${a.msgs_out} out (${rate(a.rate_in)} / ${rate(a.rate_out)} per s) on ${a.host || "-"}`,
    `epoch     ${a.epoch}   pid ${a.pid || "-"}   queued ${a.queued}`,
    `recovery  ${a.recovery}   backup ${a.backup ? "yes" : "no"}`,
    a.fail_reason ? `failed    ${a.fail_reason}` : "",
  ].filter(Boolean).join("\n");
}

// ------------------------------------------------------------------------------------------------ DDB browser

function avatarOf(key, avatars) {
  const parts = key.split("/");
  for (let i = 1; i < parts.length; i++) if (avatars.has(parts[i])) return parts[i];
  return "";
}

function drawDdb() {
  const byAvatar = $("by-avatar").checked;
  const avatars = new Set();
  for (const k of S.ddb.keys()) if (k.startsWith("avatars/")) avatars.add(k.slice(8));
  // a tree of nodes {name, path, children: Map, entry, count, bytes}
  const root = { name: "", path: "", children: new Map(), count: 0, bytes: 0 };
  let total = 0;
  for (const [key, e] of S.ddb) {
    total += e[2];
    let parts = key.split("/");
    let node = root;
    if (byAvatar) {
      const a = avatarOf(key, avatars);
      if (a) {
        node = child(node, `avatar ${a}`, "avatar:" + a);
        if (key === `avatars/${a}`) { node.entry = e; node.key = key; node.count++; node.bytes += e[2]; root.count++; root.bytes += e[2]; continue; }
        parts = parts.filter((p) => p !== a);
      }
    }
    root.count++; root.bytes += e[2];
    for (let i = 0; i < parts.length; i++) {
      node = child(node, parts[i], node.path + "/" + parts[i]);
      node.count++; node.bytes += e[2];
    }
    node.entry = e; node.key = key;
  }
  $("ddb-summary").textContent = `${S.ddb.size} objects, ${fmtBytes(total)}, seq ${S.ddbSeq}`;
  const sel = S.selected && S.selected.kind === "ddb" ? S.selected.key : null;
  const render = (node) => {
    const kids = [...node.children.values()].sort((a, b) => natural(a.name, b.name));
    return `<ul class="tree">` + kids.map((n) => {
      const has = n.children.size > 0;
      const open = S.ddbOpen.has(n.path);
      const tw = has ? `<span class="twisty" data-dtw="${esc(n.path)}">${open ? "▾" : "▸"}</span>` : `<span class="twisty"></span>`;
      const meta = n.entry ? `<span class="dim">${n.entry[1]}, ${fmtBytes(n.entry[2])}, v${n.entry[3]}</span>` : "";
      const agg = has ? ` <span class="dim">(${n.count} objects, ${fmtBytes(n.bytes)})</span>` : "";
      const attr = n.key ? ` data-key="${esc(n.key)}"` : ` data-dtw="${esc(n.path)}"`;
      return `<li><div class="node${n.key && n.key === sel ? " sel" : ""}"${attr}>${tw}${esc(n.name)} ${meta}${agg}</div>` +
        `${has && open ? render(n) : ""}</li>`;
    }).join("") + `</ul>`;
  };
  $("ddb").innerHTML = render(root);
  const now = Date.now(), seq = S.ddbSeq;
  afterPaint(() => { window.HAA.drawn.ddb = { seq, at: now }; });
}

function child(node, name, path) {
  let c = node.children.get(name);
  if (!c) { c = { name, path, children: new Map(), count: 0, bytes: 0 }; node.children.set(name, c); }
  return c;
}
function natural(a, b) { return a.localeCompare(b, undefined, { numeric: true }); }
function fmtBytes(n) { return n < 1024 ? `${n} B` : n < 1048576 ? `${(n / 1024).toFixed(1)} KiB` : `${(n / 1048576).toFixed(2)} MiB`; }

$("ddb").addEventListener("click", (ev) => {
  const k = ev.target.closest("[data-key]");
  const tw = ev.target.closest("[data-dtw]");
  if (tw && (!k || ev.target.classList.contains("twisty"))) {
    const p = tw.dataset.dtw;
    if (S.ddbOpen.has(p)) S.ddbOpen.delete(p); else S.ddbOpen.add(p);
    drawDdb();
    if (!k) return;
  }
  if (k) { S.selected = { kind: "ddb", key: k.dataset.key }; requestObject(k.dataset.key); drawDdb(); }
});
$("by-avatar").addEventListener("change", drawDdb);

let lastObjectAsk = 0;
function requestObject(key) {
  const now = Date.now();
  if (now - lastObjectAsk < 500 && S.selected && S.selected.key === key && $("detail").dataset.key === key) return;
  lastObjectAsk = now;
  if (ws && ws.readyState === 1) ws.send(JSON.stringify({ op: "object", key }));
}

function showObject(o) {
  if (!S.selected || S.selected.kind !== "ddb" || S.selected.key !== o.key) return;
  $("detail-title").textContent = `DDB ${o.key}`;
  $("detail").dataset.key = o.key;
  if (o.missing) { $("detail").textContent = "(deleted)"; return; }
  $("detail").textContent = `${o.type}, ${fmtBytes(o.size)}, version ${o.version} (created at ${o.created})\n\n` +
    (o.text || "") + (o.items ? "\n\nnewest items:\n" + o.items.join("\n") : "");
}

// ------------------------------------------------------------------------------------------------ timeline

const EVENT_STATE = {
  spawning: "spawning", active: "active", freezing: "freezing", frozen: null, thawing: "thawing",
  thawed: "active", crashed: "crashed", recovering: "recovering", recovered: "active", removed: null,
  failed: "failed", backoff: "crashed",
};

function timelineRows() {
  // per host: agents it ever ran, each with its segments [t0, t1, state]
  const hosts = new Map();
  const agentInfo = {};
  for (const a of S.agents) agentInfo[a.id] = a;
  const cur = {}; // agent -> {host, state, since, name, type}
  const hostRow = (h) => { if (!hosts.has(h)) hosts.set(h, { agents: new Map(), marks: [] }); return hosts.get(h); };
  for (const h of S.hosts) hostRow(h.name);
  const close = (agent, t) => {
    const c = cur[agent];
    if (!c || !c.state || !c.host) return;
    const row = hostRow(c.host);
    if (!row.agents.has(agent)) row.agents.set(agent, { name: c.name, type: c.type, segs: [] });
    row.agents.get(agent).segs.push([c.since, t, c.state]);
  };
  const types = {};
  for (const e of S.timeline) {
    if (!e.agent) { if (e.host) hostRow(e.host).marks.push([e.t, e.event]); continue; }
    if (e.type) types[e.agent] = e.type;
    if (!(e.event in EVENT_STATE)) continue;
    close(e.agent, e.t);
    const st = EVENT_STATE[e.event];
    cur[e.agent] = { host: e.host, state: st, since: e.t, name: e.name, type: types[e.agent] || (agentInfo[e.agent] || {}).type || "" };
  }
  const now = Date.now() / 1000 - S.clockSkew;
  for (const a of Object.keys(cur)) close(a, now);
  return { hosts, now };
}

function drawTimeline() {
  const { hosts, now } = timelineRows();
  const cv = $("timeline"), wrap = $("timeline-wrap");
  const rowH = 13, labelW = 190, hostH = 16;
  let rows = 0;
  const names = [...hosts.keys()].sort(natural);
  for (const h of names) rows += 1 + hosts.get(h).agents.size;
  const W = wrap.clientWidth - 2, H = Math.max(wrap.clientHeight - 4, rows * rowH + names.length * (hostH - rowH) + 20);
  const dpr = window.devicePixelRatio || 1;
  cv.style.width = W + "px"; cv.style.height = H + "px";
  cv.width = Math.round(W * dpr); cv.height = Math.round(H * dpr);
  const ctx = cv.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, W, H);
  const t0 = S.t0 || (S.timeline.length ? S.timeline[0].t : now - 60);
  const span = Math.max(10, now - t0);
  const X = (t) => labelW + ((t - t0) / span) * (W - labelW - 10);
  // time axis
  ctx.font = "10px sans-serif"; ctx.fillStyle = "#78909c"; ctx.strokeStyle = "#eceff1";
  const step = niceStep(span / 8);
  for (let t = 0; t <= span; t += step) {
    const x = X(t0 + t);
    ctx.beginPath(); ctx.moveTo(x, 12); ctx.lineTo(x, H); ctx.stroke();
    ctx.fillText(`${String(Math.floor(t / 60)).padStart(2, "0")}:${String(Math.floor(t % 60)).padStart(2, "0")}`, x - 12, 10);
  }
  let y = 16;
  const states = new Map(S.hosts.map((h) => [h.name, h.state]));
  for (const h of names) {
    const row = hosts.get(h);
    ctx.fillStyle = "#eceff1"; ctx.fillRect(0, y, W, hostH);
    ctx.fillStyle = "#263238"; ctx.font = "bold 11px sans-serif";
    const st = states.get(h);
    ctx.fillText(`${h}${st && st !== "alive" ? " (" + st + ")" : ""}`, 4, y + 12);
    for (const [t, what] of row.marks) {
      const x = X(t);
      ctx.fillStyle = what === "removed" ? "#e53935" : "#43a047";
      ctx.fillRect(x - 1, y, 2, hostH);
      ctx.font = "10px sans-serif"; ctx.fillText(what, x + 3, y + 12);
    }
    y += hostH;
    const agents = [...row.agents.entries()].sort((a, b) => natural(a[1].name, b[1].name));
    for (const [, a] of agents) {
      ctx.fillStyle = "#37474f"; ctx.font = "10.5px sans-serif";
      ctx.fillText(`${a.name} ${a.type}`.slice(0, 34), 10, y + 10);
      for (const [s0, s1, st] of a.segs) {
        ctx.fillStyle = STATE_COLOURS[st] || "#607d8b";
        ctx.fillRect(X(s0), y + 2, Math.max(2, X(s1) - X(s0)), rowH - 3);
      }
      y += rowH;
    }
  }
  ctx.strokeStyle = "#263238"; ctx.beginPath(); ctx.moveTo(X(now), 12); ctx.lineTo(X(now), H); ctx.stroke();
}

function niceStep(x) {
  for (const s of [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 1800, 3600]) if (s >= x) return s;
  return 7200;
}

// ------------------------------------------------------------------------------------------------ start

$("legend").innerHTML = ["spawning", "active", "freezing", "thawing", "crashed", "recovering", "failed"].map(
  (s) => `<span><i style="background:${STATE_COLOURS[s]}"></i>${s}</span>`).join("");
for (const cb of document.querySelectorAll("input[data-layer]")) {
  S.layers[cb.dataset.layer] = cb.checked;
  cb.addEventListener("change", () => { S.layers[cb.dataset.layer] = cb.checked; drawMap(); });
}
window.addEventListener("resize", () => { dirty.map = true; dirty.timeline = true; schedule(); });
setInterval(() => { dirty.timeline = true; schedule(); }, 1000);
connect();
drawMap();
