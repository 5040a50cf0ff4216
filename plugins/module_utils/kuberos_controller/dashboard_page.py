"""The dashboard's page: one HTML document, its style sheet and its script (no build step, no third-party code).

The script never puts data into HTML: every value goes in with ``textContent`` (names and messages come from
the cluster). It fetches ``/api/*`` and listens on ``/api/stream``; each change refetches what is on screen.
"""

from __future__ import annotations

from html import escape

HTML = """<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>KubeROS dashboard</title>
<link rel="stylesheet" href="/static/app.css">
<script src="/static/app.js" defer></script>
</head>
<body>
<header>
  <h1>KubeROS</h1>
  <nav id="tabs">
    <button data-tab="deployments" class="active">Deployments</button>
    <button data-tab="resources">Resources</button>
    <button data-tab="fleets">Fleets</button>
    <button data-tab="software">Software</button>
    <button data-tab="events">Events</button>
    <button data-tab="map">Placement map</button>
    <button data-tab="graph">ROS graph</button>
  </nav>
  <div id="live" title="updates arrive without reloading"><span class="dot"></span><span id="live-text">connecting</span></div>
</header>
<section id="summary"></section>
<main>
  <section id="view-deployments" class="view">
    <div class="toolbar" data-list="modules">
      <input type="search" placeholder="search robot, module, node, version, reason" data-filter="q">
      <select data-filter="deployment"><option value="">every deployment</option></select>
      <select data-filter="fleet"><option value="">every fleet</option></select>
      <select data-filter="tier"><option value="">every tier</option></select>
      <select data-filter="phase"><option value="">every phase</option></select>
      <select data-filter="module"><option value="">every module</option></select>
      <span class="pager"></span>
    </div>
    <table id="modules"><thead><tr>
      <th>Deployment</th><th>Robot</th><th>Module</th><th>Node</th><th>Tier</th><th>Phase</th><th>Version</th>
      <th>RTT / max</th><th>Why here</th><th>Last move</th></tr></thead><tbody></tbody></table>
    <section id="log-panel" hidden>
      <div class="toolbar"><b id="log-title"></b><span id="log-note" class="muted"></span>
        <button id="log-close" type="button">close</button></div>
      <pre id="log-lines"></pre>
    </section>
  </section>
  <section id="view-resources" class="view" hidden>
    <div class="toolbar" data-list="resources">
      <input type="search" placeholder="search node, robot, fleet, device" data-filter="q">
      <select data-filter="tier"><option value="">every tier</option></select>
      <select data-filter="fleet"><option value="">every fleet</option></select>
      <select data-filter="ready"><option value="">Ready or not</option></select>
      <span class="pager"></span>
    </div>
    <table id="resources"><thead><tr>
      <th>Node</th><th>Tier</th><th>Fleet</th><th>Robot</th><th>Arch</th><th>Devices</th><th>Ready</th>
      <th>CPU (cores)</th><th>Memory</th><th>GPU</th><th>Pods</th><th>Measured RTT</th></tr></thead><tbody></tbody></table>
  </section>
  <section id="view-fleets" class="view" hidden><div id="fleets"></div></section>
  <section id="view-software" class="view" hidden>
    <h2>Rollouts</h2><div id="rollouts"></div>
    <h2>Modules and versions</h2>
    <table id="software"><thead><tr><th>Module</th><th>Version</th><th>Image</th><th>Robots running it</th>
      </tr></thead><tbody></tbody></table>
    <h2>Deployments</h2>
    <table id="revisions"><thead><tr><th>Namespace</th><th>Deployment</th><th>Fleet</th><th>Revision</th></tr></thead>
      <tbody></tbody></table>
  </section>
  <section id="view-events" class="view" hidden>
    <div class="toolbar" data-list="events">
      <input type="search" placeholder="search events" data-filter="q">
      <select data-filter="kind"><option value="">every kind</option></select>
      <span class="pager"></span>
    </div>
    <ol id="events"></ol>
  </section>
  <section id="view-map" class="view" hidden>
    <div class="toolbar">
      <select id="map-deployment"></select>
      <input type="search" id="map-q" placeholder="robots whose name contains">
      <span id="map-note"></span>
    </div>
    <div id="map-frame"><img id="map" alt="placement map"></div>
  </section>
  <section id="view-graph" class="view" hidden>
    <div class="toolbar">
      <select id="graph-deployment"></select>
      <input type="search" id="graph-q" placeholder="robots whose name contains">
      <span id="graph-note" class="muted"></span>
    </div>
    <div id="graph"></div>
  </section>
</main>
</body>
</html>
"""

STYLE = """
:root { --ok: #2e7d32; --warn: #ef6c00; --bad: #c62828; --muted: #666; --line: #ddd; --head: #16324f; }
* { box-sizing: border-box; }
body { margin: 0; font: 13px/1.4 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color: #222; background: #f6f7f9; }
header { display: flex; align-items: center; gap: 16px; padding: 8px 16px; background: var(--head); color: #fff; }
header h1 { font-size: 17px; margin: 0; letter-spacing: .5px; }
nav button { background: none; border: 0; color: #cfd8e3; padding: 6px 10px; font: inherit; cursor: pointer; border-radius: 4px; }
nav button.active, nav button:hover { background: rgba(255,255,255,.15); color: #fff; }
#live { margin-left: auto; display: flex; align-items: center; gap: 6px; color: #cfd8e3; }
#live .dot { width: 9px; height: 9px; border-radius: 50%; background: #999; }
#live.on .dot { background: #66bb6a; } #live.off .dot { background: #ef5350; }
#summary { display: flex; flex-wrap: wrap; gap: 8px; padding: 10px 16px; }
.chip { background: #fff; border: 1px solid var(--line); border-radius: 6px; padding: 6px 10px; }
.chip b { font-size: 15px; margin-right: 4px; }
.chip.bad b { color: var(--bad); } .chip.warn b { color: var(--warn); }
main { padding: 0 16px 24px; }
.toolbar { display: flex; flex-wrap: wrap; gap: 8px; align-items: center; margin: 6px 0 8px; }
.toolbar input[type=search] { width: 280px; padding: 5px 8px; border: 1px solid #bbb; border-radius: 4px; }
.toolbar select { padding: 4px; border: 1px solid #bbb; border-radius: 4px; background: #fff; }
.pager { margin-left: auto; display: flex; gap: 6px; align-items: center; color: var(--muted); }
.pager button { padding: 2px 8px; }
table { border-collapse: collapse; width: 100%; background: #fff; border: 1px solid var(--line); }
th, td { text-align: left; padding: 4px 8px; border-bottom: 1px solid #eee; vertical-align: top; white-space: nowrap; }
th { background: #eef1f5; position: sticky; top: 0; font-weight: 600; }
td.why { max-width: 300px; overflow: hidden; text-overflow: ellipsis; color: var(--muted); }
td.move { color: var(--muted); }
.phase { border-radius: 10px; padding: 1px 8px; font-size: 12px; color: #fff; background: #888; white-space: nowrap; }
.phase.Running, .phase.Ready { background: var(--ok); } .phase.Pending, .phase.Moving { background: var(--warn); }
.phase.Stranded, .phase.Missing, .phase.NotReady { background: var(--bad); } .phase.Remote { background: #5c6bc0; }
.over { color: var(--bad); font-weight: 600; }
.bar { position: relative; width: 120px; height: 14px; background: #e8eaed; border-radius: 3px; overflow: hidden; }
.bar span { position: absolute; left: 0; top: 0; bottom: 0; background: #64b5f6; }
.bar.full span { background: #e57373; }
.bar em { position: relative; font-style: normal; font-size: 11px; padding-left: 4px; }
.fleet { background: #fff; border: 1px solid var(--line); border-radius: 6px; padding: 10px 14px; margin-bottom: 12px; }
.fleet h3 { margin: 0 0 6px; }
.muted { color: var(--muted); }
#events li { background: #fff; border-left: 4px solid #90a4ae; margin: 4px 0; padding: 4px 10px; list-style: none; }
#events li.warning { border-color: var(--bad); } #events li.move { border-color: var(--warn); }
#events li.rollout { border-color: #5c6bc0; }
#events { padding: 0; }
#events time { color: var(--muted); margin-right: 8px; font-variant-numeric: tabular-nums; }
.progress { width: 240px; height: 12px; background: #e8eaed; border-radius: 3px; overflow: hidden; display: inline-block; }
.progress span { display: block; height: 100%; background: #5c6bc0; }
#modules tbody tr { cursor: pointer; } #modules tbody tr.chosen { background: #e3ecf7; }
#log-panel { margin-top: 10px; background: #fff; border: 1px solid var(--line); padding: 6px 10px; }
#log-panel .toolbar { margin: 0 0 6px; } #log-close { margin-left: auto; }
#log-lines { margin: 0; max-height: 40vh; overflow: auto; font: 12px/1.35 ui-monospace, monospace; white-space: pre-wrap; }
.robot-graph { background: #fff; border: 1px solid var(--line); margin: 0 0 10px; padding: 6px 10px; }
.robot-graph.bad { border-color: var(--bad); } .robot-graph h3 { margin: 2px 0 6px; font-size: 14px; }
.robot-graph ul { color: var(--bad); margin: 4px 0; } td.unmatched { color: var(--bad); font-weight: 600; }
#map-frame { background: #fff; border: 1px solid var(--line); overflow: auto; max-height: 80vh; }
form.login { max-width: 520px; margin: 60px auto; background: #fff; padding: 20px; border: 1px solid var(--line); }
form.login textarea { width: 100%; height: 120px; font-family: monospace; }
"""

SCRIPT = r"""
'use strict';
const state = { tab: 'deployments', filters: { modules: {}, resources: {}, events: {} }, pages: { modules: 0, resources: 0, events: 0 },
                generation: 0, shown: -1, summary: null, log: null };
const $ = (sel, root) => (root || document).querySelector(sel);
const $$ = (sel, root) => Array.from((root || document).querySelectorAll(sel));

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === null || v === undefined || v === false) continue;
    if (k === 'class') node.className = v; else if (k === 'text') node.textContent = v; else node.setAttribute(k, v);
  }
  for (const child of children) {
    if (child === null || child === undefined) continue;
    node.appendChild(typeof child === 'string' || typeof child === 'number' ? document.createTextNode(String(child)) : child);
  }
  return node;
}

async function get(path) {
  const response = await fetch(path, { credentials: 'same-origin', headers: { 'Accept': 'application/json' } });
  if (response.status === 401) { location.href = '/login'; throw new Error('login needed'); }
  if (!response.ok) throw new Error(path + ': ' + response.status);
  return response.json();
}

function query(list) {
  const params = new URLSearchParams();
  for (const [k, v] of Object.entries(state.filters[list])) if (v) params.set(k, v);
  params.set('page', state.pages[list]);
  params.set('size', 100);
  return params.toString();
}

function fmtBytes(n) {
  if (!n) return '0';
  const units = ['B', 'KiB', 'MiB', 'GiB', 'TiB'];
  let i = 0; while (n >= 1024 && i < units.length - 1) { n /= 1024; i++; }
  return n.toFixed(n >= 10 || i === 0 ? 0 : 1) + ' ' + units[i];
}
function fmtNum(n) { return Number.isInteger(n) ? String(n) : n.toFixed(2); }

function bar(used, total, fmt) {
  const share = total > 0 ? Math.min(used / total, 1) : 0;
  const b = el('div', { class: 'bar' + (share > 0.9 ? ' full' : ''), title: fmt(used) + ' of ' + fmt(total) });
  const fill = el('span'); fill.style.width = (share * 100).toFixed(1) + '%';
  b.appendChild(fill); b.appendChild(el('em', { text: fmt(used) + ' / ' + fmt(total) }));
  return b;
}

function phase(text) { return el('span', { class: 'phase ' + text, text: text }); }

function fillSelects(list, facets) {
  for (const select of $$(`.toolbar[data-list="${list}"] select`)) {
    const key = select.dataset.filter, values = facets[key];
    if (!values) continue;
    const current = select.value;
    const first = select.options[0];
    select.replaceChildren(first);
    for (const [value, count] of Object.entries(values)) {
      if (value === '') continue;
      select.appendChild(el('option', { value: value, text: `${value} (${count})` }));
    }
    select.value = current;
  }
}

function pager(list, data) {
  const box = $(`.toolbar[data-list="${list}"] .pager`);
  const from = data.total ? data.page * data.size + 1 : 0, to = Math.min(data.total, (data.page + 1) * data.size);
  const prev = el('button', { text: '‹', disabled: data.page <= 0 ? 'disabled' : null });
  const next = el('button', { text: '›', disabled: data.page >= data.pages - 1 ? 'disabled' : null });
  prev.onclick = () => { state.pages[list] = data.page - 1; refresh(); };
  next.onclick = () => { state.pages[list] = data.page + 1; refresh(); };
  box.replaceChildren(el('span', { class: 'count', text: `${from}–${to} of ${data.total}` }), prev, next);
}

function renderSummary(s) {
  const box = $('#summary');
  const phases = s.phases || {};
  const chips = [
    ['nodes Ready', `${s.ready}/${s.nodes}`, s.ready < s.nodes ? 'bad' : ''],
    ['robots', s.robots, ''],
    ['deployments', s.deployments, ''],
    ['module instances', s.instances, ''],
    ['running (robot, module)', `${phases.Running || 0}/${s.rows}`, (phases.Running || 0) < s.rows ? 'warn' : ''],
    ['stranded', s.stranded, s.stranded ? 'bad' : ''],
    ['over max_latency', s.over_latency, s.over_latency ? 'bad' : ''],
    ['leader', s.leader || 'none', s.leader ? '' : 'bad'],
  ];
  box.replaceChildren(...chips.map(([label, value, cls]) => el('div', { class: 'chip ' + cls }, el('b', { text: String(value) }), label)));
  for (const bad of s.unreadable_records || []) {
    box.appendChild(el('div', { class: 'chip bad' }, el('b', { text: '!' }), `record ${bad.namespace}/${bad.name}: ${bad.error}`));
  }
  for (const why of s.unreadable_reservations || []) {
    box.appendChild(el('div', { class: 'chip warn' }, el('b', { text: '!' }), why));
  }
}

function renderModules(data) {
  fillSelects('modules', data.facets); pager('modules', data);
  const rows = data.rows.map(r => {
    const moved = r.last_move && r.last_move.to;
    const move = moved ? `${r.last_move.at}: ${r.last_move.from} → ${r.last_move.to} (${r.last_move.why})` : '';
    const moveShort = moved ? `${r.last_move.from} → ${r.last_move.to}, ${String(r.last_move.at).slice(11, 19)}` : '';
    const rtt = r.rtt_ms === null || r.rtt_ms === undefined ? (r.max_latency_ms ? 'not measured' : '') : `${fmtNum(r.rtt_ms)} ms`;
    const limit = r.max_latency_ms === null || r.max_latency_ms === undefined ? '' : ` / ${fmtNum(r.max_latency_ms)} ms`;
    return el('tr', { 'data-instance': r.instance, 'data-robot': r.robot, 'data-module': r.module, 'data-deployment': r.deployment },
      el('td', { text: r.deployment }), el('td', { text: r.robot }), el('td', { text: r.module + (r.shared ? ' (shared)' : '') }),
      el('td', { class: 'node', text: r.node }), el('td', { text: r.tier }),
      el('td', { class: 'phase-cell' }, phase(r.phase)),
      el('td', { class: 'version', text: r.version + (r.version !== r.planned && r.planned ? ` → ${r.planned}` : '') }),
      el('td', { class: r.over_latency ? 'over' : '', text: rtt + limit }),
      el('td', { class: 'why', title: r.note || r.reason, text: r.note ? 'stranded: ' + r.note : r.reason }),
      el('td', { class: 'move', title: move, text: moveShort }));
  });
  for (const row of rows) {
    row.classList.toggle('chosen', row.dataset.instance === state.log);
    row.onclick = () => openLog(row.dataset.instance, `${row.dataset.robot} / ${row.dataset.module}`);
  }
  $('#modules tbody').replaceChildren(...rows);
}

// The last lines of the instance whose row was clicked, asked for every 2 s while the panel is open.
let logTimer = null;
async function showLog() {
  if (!state.log) return;
  try {
    const data = await get('/api/logs?' + new URLSearchParams({ instance: state.log }).toString());
    $('#log-note').textContent = data.refused || data.missing ||
      ` · pod ${data.pod} on ${data.node} · ${data.lines.length} lines · ${new Date().toLocaleTimeString()}`;
    const pre = $('#log-lines');
    const atEnd = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
    pre.textContent = (data.lines || []).join('\n');
    if (atEnd) pre.scrollTop = pre.scrollHeight;
    document.body.dataset.logLines = String((data.lines || []).length);
  } catch (error) {
    $('#log-note').textContent = 'error: ' + error.message;
  }
}
function openLog(instance, title) {
  state.log = instance;
  $('#log-title').textContent = title + ' (' + instance + ')';
  $('#log-panel').hidden = false;
  for (const row of $$('#modules tbody tr')) row.classList.toggle('chosen', row.dataset.instance === instance);
  clearInterval(logTimer);
  showLog();
  logTimer = setInterval(showLog, 2000);
}
function closeLog() {
  state.log = null; clearInterval(logTimer); $('#log-panel').hidden = true;
  for (const row of $$('#modules tbody tr')) row.classList.remove('chosen');
}

function renderResources(data) {
  fillSelects('resources', data.facets); pager('resources', data);
  const rows = data.rows.map(r => {
    const rtt = Object.entries(r.rtt_ms || {}).sort((a, b) => a[1] - b[1]);
    const rttText = rtt.slice(0, 4).map(([peer, ms]) => `${peer} ${fmtNum(ms)} ms`).join(', ') + (rtt.length > 4 ? ` … (${rtt.length})` : '');
    return el('tr', { 'data-node': r.name },
      el('td', { text: r.name }), el('td', { text: r.tier }), el('td', { text: r.fleet }), el('td', { text: r.robot }),
      el('td', { text: r.arch }), el('td', { text: (r.devices || []).join(', ') }),
      el('td', null, phase(r.ready ? 'Ready' : 'NotReady')),
      el('td', null, bar(r.allocated.cpu, r.allocatable.cpu, fmtNum)),
      el('td', null, bar(r.allocated.memory, r.allocatable.memory, fmtBytes)),
      el('td', { text: r.allocatable.gpu ? `${r.allocated.gpu} / ${r.allocatable.gpu}` : '' }),
      el('td', { text: `${r.allocated.pods} / ${r.allocatable.pods}` }),
      el('td', { class: 'why', title: rtt.map(([p, ms]) => `${p} ${ms} ms`).join('\n'), text: rttText }));
  });
  $('#resources tbody').replaceChildren(...rows);
}

function renderFleets(data) {
  const cards = data.fleets.map(f => el('div', { class: 'fleet', 'data-fleet': f.fleet },
    el('h3', { text: `Fleet ${f.fleet}` }),
    el('div', { class: 'muted', text: `namespace ${f.namespace || '–'} · ${f.robots.length} robots ` +
      `(${f.robots.length - f.offline.length} online) · ` +
      `${f.nodes.length} edge/cloud nodes in use · deployments: ${f.deployments.join(', ') || 'none'}` }),
    f.offline.length ? el('p', { class: 'offline', text: 'Offline (their modules stay and run on them): ' +
      f.offline.map(r => `${r.robot} since ${r.since || '?'}`).join(', ') }) : null,
    el('table', null, el('thead', null, el('tr', null, ...['Discovery server', 'Node', 'Tier', 'Port', 'Phase'].map(t => el('th', { text: t })))),
      el('tbody', null, ...f.discovery.map(s => el('tr', { 'data-server': s.name },
        el('td', { text: `${s.name} (id ${s.id})` }), el('td', { class: 'node', text: s.node }), el('td', { text: s.tier }),
        el('td', { text: String(s.port) }), el('td', null, phase(s.phase)))))),
    f.bridges.length ? el('p', { text: 'Bridges: ' + f.bridges.map(b => `${b.name} → ${b.cluster} on ${b.node}:${b.port}`).join(', ') }) : null,
    (f.reservations || []).length ? el('p', { class: 'reserved', text: 'Reserved in the robot pool (production leaves them out): ' +
      f.reservations.map(r => `${r.robot} by ${r.owner} until ${r.until}${r.active ? '' : ' (ended)'}${r.reason ? ': ' + r.reason : ''}`).join('; ') }) : null,
    el('details', null, el('summary', { text: 'robots' }), el('p', { class: 'muted', text: f.robots.join(', ') }))));
  $('#fleets').replaceChildren(...cards);
}

function renderSoftware(data) {
  const rollouts = data.rollouts.map(r => {
    const p = el('span'); p.style.width = (r.instances ? 100 * r.done / r.instances : 0).toFixed(0) + '%';
    return el('p', null, `${r.namespace}/${r.deployment}: revision ${r.from} → ${r.to} since ${r.started} `,
      el('span', { class: 'progress', title: `${r.done} of ${r.instances}` }, p), ` ${r.done}/${r.instances} instances`);
  });
  $('#rollouts').replaceChildren(...(rollouts.length ? rollouts : [el('p', { class: 'muted', text: 'no rollout in progress' })]));
  const rows = [];
  for (const m of data.modules) {
    m.versions.forEach((v, i) => rows.push(el('tr', { 'data-module': m.module, 'data-version': v.version },
      el('td', { text: i === 0 ? m.module + (m.in_catalog ? '' : ' (not in a catalog)') : '' }), el('td', { text: v.version }),
      el('td', { class: 'why', text: v.image }),
      el('td', { title: v.robot_names.join(', '),
        text: v.robots ? `${v.robots}: ${v.robot_names.slice(0, 6).join(', ')}${v.robots > 6 ? ' …' : ''}` : '–' }))));
  }
  $('#software tbody').replaceChildren(...rows);
  $('#revisions tbody').replaceChildren(...data.revisions.map(r => el('tr', null, el('td', { text: r.namespace }),
    el('td', { text: r.deployment }), el('td', { text: r.fleet }), el('td', { text: String(r.revision || '–') }))));
}

function renderEvents(data) {
  fillSelects('events', data.facets); pager('events', data);
  $('#events').replaceChildren(...data.rows.map(e => el('li', { class: `${e.kind}${e.warning ? ' warning' : ''}` },
    el('time', { text: e.at }), el('b', { text: e.reason }), ' ', e.namespace ? `${e.namespace}/` : '', e.object ? `${e.object}: ` : '', e.message)));
}

async function renderMap() {
  const select = $('#map-deployment');
  const software = await get('/api/software');
  const options = software.revisions.map(r => `${r.namespace}/${r.deployment}`);
  if (select.options.length !== options.length) {
    const current = select.value;
    select.replaceChildren(...options.map(o => el('option', { value: o, text: o })));
    if (current) select.value = current;
  }
  const params = new URLSearchParams({ deployment: select.value || options[0] || '', q: $('#map-q').value, g: state.generation });
  if (options.length) $('#map').src = '/api/placement.svg?' + params.toString();
  $('#map-note').textContent = options.length ? 'the robots whose names match, at most 12 (type to choose others)' : 'nothing deployed';
}

// The ROS graph per robot, as the deployment's last live check saw it (after a deploy, after each rollout wave).
async function renderGraph() {
  const params = new URLSearchParams({ deployment: $('#graph-deployment').value, q: $('#graph-q').value });
  const data = await get('/api/graph?' + params.toString());
  const select = $('#graph-deployment');
  if (select.options.length !== data.deployments.length) {
    select.replaceChildren(...data.deployments.map(d => el('option', { value: d, text: d })));
    select.value = data.deployment;
  }
  $('#graph-note').textContent = data.deployments.length
    ? `${data.shown} of ${data.total} robots (type to choose others)` : 'no deployment declares topics, or none was checked yet';
  const endpoints = nodes => nodes.length ? nodes.join(', ') : 'none';
  const cards = Object.entries(data.robots).map(([robot, g]) => el('div', { class: 'robot-graph' + (g.ok ? '' : ' bad'), 'data-robot': robot },
    el('h3', { text: `${robot || 'fleet-wide topics'} · ${g.ok ? 'connected as declared' : 'NOT as declared'} · checked ${g.at}` }),
    g.problems.length ? el('ul', null, ...g.problems.map(p => el('li', { text: p }))) : null,
    el('table', null, el('thead', null, el('tr', null, ...['Topic', 'Type', 'Publishers', 'Subscribers', 'Rate'].map(t => el('th', { text: t })))),
      el('tbody', null, ...g.topics.map(t => el('tr', null,
        el('td', { text: t.name }), el('td', { text: t.type }),
        el('td', { class: t.publishers.length ? '' : 'unmatched', text: endpoints(t.publishers) }),
        el('td', { class: t.subscribers.length ? '' : 'unmatched', text: endpoints(t.subscribers) }),
        el('td', { text: t.rate === null || t.rate === undefined ? '' : `${fmtNum(t.rate)} Hz` })))))));
  $('#graph').replaceChildren(...cards);
}

async function refresh() {
  try {
    const s = await get('/api/summary');
    state.summary = s; renderSummary(s);
    if (state.tab === 'deployments') renderModules(await get('/api/modules?' + query('modules')));
    else if (state.tab === 'resources') renderResources(await get('/api/resources?' + query('resources')));
    else if (state.tab === 'fleets') renderFleets(await get('/api/fleets'));
    else if (state.tab === 'software') renderSoftware(await get('/api/software'));
    else if (state.tab === 'events') renderEvents(await get('/api/events?' + query('events')));
    else if (state.tab === 'map') await renderMap();
    else if (state.tab === 'graph') await renderGraph();
    state.shown = s.generation;
    if (!document.body.dataset.firstPaintMs) document.body.dataset.firstPaintMs = String(Math.round(performance.now()));
    document.body.dataset.generation = String(s.generation);
    document.body.dataset.tab = state.tab;
    $('#live-text').textContent = `live · view ${s.generation} · ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    $('#live-text').textContent = 'error: ' + error.message;
  }
}

let pending = null, running = false;
function schedule() {
  if (running) { pending = true; return; }
  running = true;
  refresh().finally(() => { running = false; if (pending) { pending = null; schedule(); } });
}

function connect() {
  const source = new EventSource('/api/stream');
  source.addEventListener('change', event => { state.generation = JSON.parse(event.data).generation; $('#live').className = 'on'; schedule(); });
  source.onerror = () => { $('#live').className = 'off'; $('#live-text').textContent = 'reconnecting'; };
}

function setTab(tab) {
  state.tab = tab;
  for (const b of $$('#tabs button')) b.classList.toggle('active', b.dataset.tab === tab);
  for (const v of $$('.view')) v.hidden = v.id !== 'view-' + tab;
  history.replaceState(null, '', '#' + tab);
  schedule();
}

document.addEventListener('DOMContentLoaded', () => {
  for (const b of $$('#tabs button')) b.onclick = () => setTab(b.dataset.tab);
  for (const toolbar of $$('.toolbar[data-list]')) {
    const list = toolbar.dataset.list;
    for (const input of $$('[data-filter]', toolbar)) {
      let timer = null;
      const apply = () => { state.filters[list][input.dataset.filter] = input.value; state.pages[list] = 0; schedule(); };
      input.addEventListener(input.tagName === 'SELECT' ? 'change' : 'input', () => { clearTimeout(timer); timer = setTimeout(apply, 200); });
    }
  }
  $('#log-close').onclick = closeLog;
  $('#map-deployment').onchange = schedule;
  $('#graph-deployment').onchange = schedule;
  let graphTimer = null;
  $('#graph-q').oninput = () => { clearTimeout(graphTimer); graphTimer = setTimeout(schedule, 300); };
  let mapTimer = null;
  $('#map-q').oninput = () => { clearTimeout(mapTimer); mapTimer = setTimeout(schedule, 300); };
  const fromHash = () => {
    const wanted = location.hash.slice(1);
    setTab($$('#tabs button').some(b => b.dataset.tab === wanted) ? wanted : 'deployments');
  };
  window.addEventListener('hashchange', fromHash);
  fromHash();
  connect();
});
"""


def login_html(failed: str) -> str:
    message = {"forbidden": "That token is valid but may not read the dashboard.", "unknown": "That token is not valid."}
    note = f'<p class="over">{escape(message.get(failed, ""))}</p>' if failed in message else ""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>KubeROS dashboard: sign in</title>
<link rel="stylesheet" href="/static/app.css"></head>
<body><form class="login" method="post" action="/login">
<h2>KubeROS dashboard</h2>
<p>Paste a Kubernetes bearer token of a user or ServiceAccount allowed to <code>get</code> the non-resource URL
<code>/kuberos/dashboard</code> (for example: <code>kubectl create token kuberos-dashboard-viewer -n kuberos-system</code>).</p>
{note}<textarea name="token" autocomplete="off" spellcheck="false" required></textarea>
<p><button type="submit">Sign in</button></p></form></body></html>
"""
