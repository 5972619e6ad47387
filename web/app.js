// The station page: drives `station serve`'s API (docs/serve.md). No build step;
// three.js is Debian's libjs-three, served by the station under /vendor/three.
import * as THREE from '/vendor/three/build/three.module.js';
import { OrbitControls } from '/vendor/three/examples/jsm/controls/OrbitControls.js';
import { PLYLoader } from '/vendor/three/examples/jsm/loaders/PLYLoader.js';

const $ = (id) => document.getElementById(id);
const state = {
  token: sessionStorage.getItem('station_token') || '',
  profiles: [], devices: [],
  session: null, detail: null, job: null, events: null,
  mode: 'none', meshGeometry: null, previewOn: false, cloudTimer: null,
};

// ---- API ---------------------------------------------------------------------
class ApiError extends Error {}

async function api(path, options = {}) {
  const headers = Object.assign({}, options.headers || {});
  if (state.token) headers['X-Station-Token'] = state.token;
  if (options.json !== undefined) {
    headers['Content-Type'] = 'application/json';
    options.body = JSON.stringify(options.json);
  }
  const res = await fetch(path, { method: options.method || 'GET', headers, body: options.body });
  if (res.status === 401) $('token-form').hidden = false;
  if (!res.ok) {
    let message = `${res.status} ${res.statusText}`;
    try { message = (await res.json()).error || message; } catch (e) { /* not JSON */ }
    throw new ApiError(message);
  }
  if (options.raw) return res.arrayBuffer();
  return res.json();
}

function showError(message) {
  const box = $('error');
  box.textContent = message;
  box.hidden = !message;
}

async function guarded(fn) {
  try {
    await fn();
  } catch (e) {
    showError(e instanceof ApiError ? e.message : `page: ${e.message}`);
  }
}

function sessionUrl(name, rest) { return `/api/sessions/${encodeURIComponent(name)}${rest ? '/' + rest : ''}`; }
function fileUrl(name, file) {
  return sessionUrl(name, 'files/' + file.split('/').map(encodeURIComponent).join('/'));
}

// ---- profiles, devices, sessions ---------------------------------------------
function fillDeviceSelect(select, kind, own) {
  select.replaceChildren();
  const add = (uri, label) => {
    const o = document.createElement('option');
    o.value = uri; o.textContent = label;
    select.append(o);
  };
  if (own) add('', `profile's: ${own}`);
  for (const d of state.devices)
    if (d.kind === kind && d.uri !== own)
      add(d.uri, `${d.uri}${d.available ? '' : ' (unavailable)'}${d.job ? ` (busy: job ${d.job})` : ''}`);
}

function profileChanged() {
  const p = state.profiles.find((x) => x.name === $('profile').value);
  if (!p) return;
  if (p.error) showError(p.error);
  fillDeviceSelect($('scanner'), 'scanner', p.scanner);
  fillDeviceSelect($('turntable'), 'turntable', p.turntable);
  if (p.views) $('views').value = p.views;
}

async function loadStation() {
  const st = await api('/api/status');
  $('status').textContent = `station ${st.version}, data ${st.data}`;
  $('token-form').hidden = true;
  state.profiles = (await api('/api/profiles')).profiles;
  state.devices = (await api('/api/devices')).devices;
  const sel = $('profile');
  sel.replaceChildren();
  for (const p of state.profiles) {
    const o = document.createElement('option');
    o.value = p.name; o.textContent = p.name;
    sel.append(o);
  }
  if (state.profiles.some((p) => p.name === 'default.yaml')) sel.value = 'default.yaml';
  profileChanged();
  await loadSessions();
}

async function loadSessions() {
  const list = (await api('/api/sessions')).sessions;
  const ul = $('sessions');
  ul.replaceChildren();
  for (const s of list) {
    const li = document.createElement('li');
    li.dataset.name = s.name;
    li.textContent = s.name;
    const badge = document.createElement('span');
    badge.className = 'badge';
    badge.textContent = s.error ? 'unreadable' :
      `${s.views}${s.planned_views ? '/' + s.planned_views : ''} views${s.mesh ? ', mesh' : ''}${s.job ? ', working' : ''}`;
    li.append(badge);
    if (s.name === state.session) li.classList.add('open');
    li.addEventListener('click', () => guarded(() => openSession(s.name)));
    ul.append(li);
  }
}

// ---- a session: views, stages, results --------------------------------------
function viewFigure(name, v) {
  const fig = document.createElement('figure');
  fig.dataset.view = v.index ?? v.view;
  if (v.colour_image) {
    const img = document.createElement('img');
    img.src = fileUrl(name, v.colour_image);
    img.alt = `view ${fig.dataset.view}`;
    fig.append(img);
  }
  const cap = document.createElement('figcaption');
  cap.textContent = `${fig.dataset.view}${v.angle != null ? ` @ ${Number(v.angle).toFixed(0)}°` : ''}`;
  fig.append(cap);
  return fig;
}

function stageRow(name) {
  let row = document.querySelector(`#stages tr[data-stage="${name}"]`);
  if (row) return row;
  row = document.createElement('tr');
  row.dataset.stage = name;
  row.innerHTML = '<td></td><td><progress max="1" value="0"></progress><div class="sub"></div></td><td class="num"></td>';
  row.cells[0].textContent = name;
  $('stages').tBodies[0].append(row);
  return row;
}

function setStage(name, fraction, note, seconds) {
  const row = stageRow(name);
  const bar = row.querySelector('progress');
  if (fraction == null) bar.removeAttribute('value'); else bar.value = fraction;
  if (note !== undefined) row.querySelector('.sub').textContent = note;
  if (seconds != null) row.cells[2].textContent = Number(seconds).toFixed(2);
}

function renderDetail(d) {
  $('session-title').textContent = d.name;
  const strip = $('views-strip');
  strip.replaceChildren(...(d.view_list || []).map((v) => viewFigure(d.name, v)));
  $('stages').tBodies[0].replaceChildren();
  if (d.views) setStage('scan', d.planned_views ? d.views / d.planned_views : 1,
                        `${d.views}${d.planned_views ? ' of ' + d.planned_views : ''} views`);
  for (const s of d.stages || []) setStage(s.name, 1, s.reused ? 'kept from an earlier run' : '', s.seconds);
  // Registration per view: the prior used, corrected or rejected, and the residual.
  const reg = (d.stages || []).find((s) => s.name === 'register');
  const body = $('registration').tBodies[0];
  body.replaceChildren();
  if (reg) {
    (d.view_list || []).forEach((v, i) => {
      const tr = document.createElement('tr');
      const prior = (reg.view_prior || [])[i] || '';
      const res = (reg.per_view || [])[i];
      tr.innerHTML = '<td class="num"></td><td class="num"></td><td></td><td class="num"></td>';
      tr.cells[0].textContent = i;
      tr.cells[1].textContent = v.angle != null ? Number(v.angle).toFixed(1) : '-';
      tr.cells[2].textContent = prior;
      tr.cells[2].className = `prior-${prior}`;
      tr.cells[3].textContent = res != null && res >= 0 ? Number(res).toFixed(3) : '-';
      body.append(tr);
    });
  }
  const links = [];
  const f = d.files || {};
  if (f['run/mesh.ply']) {
    links.push(['mesh (PLY)', fileUrl(d.name, 'run/mesh.ply') + '?download=1', 'download-ply', 'mesh.ply']);
    links.push(['mesh (OBJ)', sessionUrl(d.name, 'mesh.obj'), 'download-obj', 'mesh.obj']);
  }
  if (f['run/report.html']) links.push(['report', fileUrl(d.name, 'run/report.html'), 'report']);
  if (f['run/run.yaml']) links.push(['run.yaml', fileUrl(d.name, 'run/run.yaml') + '?download=1', 'run-yaml', 'run.yaml']);
  if (f['run/merged.ply']) links.push(['registered cloud', fileUrl(d.name, 'run/merged.ply') + '?download=1', 'download-merged', 'merged.ply']);
  else if (f['merged.ply']) links.push(['merged cloud', fileUrl(d.name, 'merged.ply') + '?download=1', 'download-merged', 'merged.ply']);
  const p = $('downloads');
  p.replaceChildren();
  for (const [label, href, id, file] of links) {
    const a = document.createElement('a');
    a.href = href; a.textContent = label; a.id = id;
    if (id === 'report') a.target = '_blank';
    else a.download = `${d.name}-${file}`;
    p.append(a);
  }
  if (!links.length) p.textContent = 'nothing yet';
}

function setJobState(text, st) {
  const el = $('job-state');
  el.textContent = text;
  el.dataset.state = st;
  $('stop').hidden = st !== 'running';
  const d = state.detail;
  const incomplete = d && d.planned_views && d.views < d.planned_views;
  $('resume-scan').hidden = st === 'running' || !incomplete;
  $('rerun').hidden = st === 'running' || !d || !d.views || incomplete;
}

async function openSession(name, jobId) {
  showError('');
  if (state.events) { state.events.close(); state.events = null; }
  state.session = name;
  state.meshGeometry = null;
  const d = await api(sessionUrl(name, ''));
  state.detail = d;
  renderDetail(d);
  document.querySelectorAll('#sessions li').forEach((li) => li.classList.toggle('open', li.dataset.name === name));
  const job = jobId || d.job;
  if (job) {
    followJob(job);
  } else {
    setJobState(d.files && d.files['run/mesh.ply'] ? 'finished' : 'no job', d.files && d.files['run/mesh.ply'] ? 'finished' : 'none');
    if (d.files && d.files['run/mesh.ply']) await show('mesh');
    else if (d.views) await show('growing');
  }
}

function followJob(id) {
  state.job = id;
  setJobState(`job ${id}: running`, 'running');
  $('log').textContent = '';
  const es = new EventSource(`/api/jobs/${id}/events`);
  state.events = es;
  let stage = null;
  es.onmessage = (msg) => {
    const e = JSON.parse(msg.data);
    switch (e.type) {
      case 'line':
        $('log').textContent += e.text + '\n';
        break;
      case 'view': {
        const strip = $('views-strip');
        if (!strip.querySelector(`figure[data-view="${e.view}"]`)) strip.append(viewFigure(state.session, e));
        setStage('scan', (e.view + 1) / e.total, `view ${e.view + 1} of ${e.total}: ${e.points} points`, e.t);
        scheduleCloud();
        break;
      }
      case 'stage':
        stage = e.stage;
        if (e.status === 'start') setStage(e.stage, null, 'working');
        else setStage(e.stage, 1, e.status === 'kept' ? 'kept from an earlier run' : 'done', e.seconds);
        break;
      case 'step':
        if (stage && e.label.trim().startsWith(stage))
          setStage(stage, e.total ? e.done / e.total : null, `${e.label.trim()} ${e.done}/${e.total} ${e.note || ''}`);
        break;
      case 'end':
        es.close();
        state.events = null;
        setJobState(`job ${id}: ${e.state}`, e.state);
        if (e.error) showError(e.error);
        guarded(async () => {
          state.detail = await api(sessionUrl(state.session, ''));
          renderDetail(state.detail);
          setJobState(`job ${id}: ${e.state}`, e.state);
          if (state.detail.files['run/mesh.ply']) await show('mesh');
          await loadSessions();
        });
        break;
      default:
        break;
    }
  };
  es.onerror = () => { /* EventSource reconnects by itself, from the last event it saw */ };
}

async function startScan() {
  showError('');
  const body = {
    profile: $('profile').value,
    scanner: $('scanner').value,
    turntable: $('turntable').value,
    views: Number($('views').value) || 0,
    session: $('session-name').value.trim(),
    run: $('then-run').checked,
  };
  if (state.previewOn) togglePreview();
  const r = await api('/api/scan', { method: 'POST', json: body });
  $('stages').tBodies[0].replaceChildren();
  $('views-strip').replaceChildren();
  await loadSessions();
  await openSession(r.session, r.job);
}

// ---- the 3-D viewer ----------------------------------------------------------
const viewer = {};

function initViewer() {
  const box = $('viewer');
  try {
    viewer.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  } catch (e) {
    $('viewer-note').textContent = 'this browser has no WebGL: the 3-D view is off (downloads still work)';
    return;
  }
  viewer.renderer.setPixelRatio(window.devicePixelRatio || 1);
  viewer.renderer.setSize(box.clientWidth, box.clientHeight);
  viewer.renderer.setClearColor(0x20242c);
  box.append(viewer.renderer.domElement);
  viewer.scene = new THREE.Scene();
  viewer.camera = new THREE.PerspectiveCamera(35, box.clientWidth / box.clientHeight, 0.001, 100);
  viewer.scene.add(new THREE.HemisphereLight(0xffffff, 0x444455, 0.9));
  const sun = new THREE.DirectionalLight(0xffffff, 0.6);
  viewer.camera.add(sun);
  sun.position.set(1, 1, 2);
  viewer.scene.add(viewer.camera);
  viewer.controls = new OrbitControls(viewer.camera, viewer.renderer.domElement);
  viewer.controls.addEventListener('change', render);
  window.addEventListener('resize', () => {
    viewer.renderer.setSize(box.clientWidth, box.clientHeight);
    viewer.camera.aspect = box.clientWidth / box.clientHeight;
    viewer.camera.updateProjectionMatrix();
    render();
  });
  render();
}

function render() { if (viewer.renderer) viewer.renderer.render(viewer.scene, viewer.camera); }

function upAxis() {
  const reg = ((state.detail && state.detail.stages) || []).find((s) => s.name === 'register');
  const f = reg && reg.figures;
  if (f && f.up_x !== undefined) return new THREE.Vector3(f.up_x, f.up_y, f.up_z).normalize();
  return new THREE.Vector3(0, 1, 0);
}

function setObject(obj, keepCamera) {
  if (viewer.object) {
    viewer.scene.remove(viewer.object);
    viewer.object.geometry.dispose();
    viewer.object.material.dispose();
  }
  viewer.object = obj;
  viewer.scene.add(obj);
  obj.geometry.computeBoundingSphere();
  const s = obj.geometry.boundingSphere;
  if (!keepCamera || !viewer.framed) {
    const up = upAxis();
    viewer.camera.up.copy(up);
    // Look from the side, a little above: the view an operator has of the table.
    const side = Math.abs(up.z) < 0.9 ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(1, 0, 0);
    side.addScaledVector(up, -side.dot(up)).normalize().addScaledVector(up, 0.45).normalize();
    viewer.camera.position.copy(s.center).addScaledVector(side, s.radius * 3.6);
    viewer.camera.near = s.radius / 50;
    viewer.camera.far = s.radius * 50;
    viewer.camera.updateProjectionMatrix();
    viewer.controls.target.copy(s.center);
    viewer.controls.update();
    viewer.framed = true;
  }
  render();
}

function cloudObject(buf, byView) {
  const dv = new DataView(buf);
  const n = dv.getUint32(0, true);
  const views = Math.max(1, dv.getUint32(4, true));
  const xyz = new Float32Array(buf, 8, 3 * n);
  const view = new Uint16Array(buf.slice(8 + 12 * n, 8 + 14 * n));
  const rgb = new Uint8Array(buf, 8 + 14 * n, 3 * n);
  const colours = new Float32Array(3 * n);
  const c = new THREE.Color();
  for (let i = 0; i < n; i++) {
    if (byView) {
      c.setHSL((view[i] * 0.618034) % 1, 0.75, 0.55);
      colours.set([c.r, c.g, c.b], 3 * i);
    } else {
      colours.set([rgb[3 * i] / 255, rgb[3 * i + 1] / 255, rgb[3 * i + 2] / 255], 3 * i);
    }
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(new Float32Array(xyz), 3));
  g.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  g.computeBoundingSphere();
  const m = new THREE.PointsMaterial({ size: g.boundingSphere.radius / 250, vertexColors: THREE.VertexColors });
  $('viewer-note').textContent = `${n} points of ${views} views` + (byView ? ', one colour per view' : '');
  return new THREE.Points(g, m);
}

async function meshObject(colour) {
  if (!state.meshGeometry) {
    const buf = await api(fileUrl(state.session, 'run/mesh.ply'), { raw: true });
    const g = new PLYLoader().parse(buf);
    if (!g.getAttribute('normal')) g.computeVertexNormals();
    state.meshGeometry = g;
  }
  const g = state.meshGeometry.clone();
  const hasColour = !!g.getAttribute('color');
  const m = new THREE.MeshStandardMaterial({
    vertexColors: colour && hasColour ? THREE.VertexColors : THREE.NoColors,
    color: colour && hasColour ? 0xffffff : 0xb8bec8, roughness: 0.85, metalness: 0.0,
    side: THREE.DoubleSide,
  });
  $('viewer-note').textContent =
    `${g.getAttribute('position').count} vertices, ${g.index ? g.index.count / 3 : 0} faces` +
    (hasColour ? '' : ', no colour');
  return new THREE.Mesh(g, m);
}

async function show(mode) {
  if (!viewer.renderer || !state.session) return;
  state.mode = mode;
  document.querySelectorAll('#viewer-modes button').forEach((b) => b.classList.toggle('off', b.dataset.mode !== mode));
  const box = $('viewer');
  if (mode === 'mesh') {
    const colour = $('mesh-colour').checked;
    setObject(await meshObject(colour), true);
    box.dataset.shown = colour ? 'mesh-colour' : 'mesh-plain';
  } else {
    const q = mode === 'growing' ? '?poses=turntable&max=60000' : '?max=60000';
    const buf = await api(sessionUrl(state.session, 'cloud' + q), { raw: true });
    setObject(cloudObject(buf, mode === 'registered'), mode === 'growing');
    box.dataset.shown = mode;
  }
}

// The scanned cloud grows view by view: reloaded at most once a second.
function scheduleCloud() {
  if (state.cloudTimer || (state.mode !== 'growing' && state.mode !== 'none')) return;
  state.cloudTimer = setTimeout(() => {
    state.cloudTimer = null;
    guarded(() => show('growing'));
  }, 1000);
}

// ---- live preview ------------------------------------------------------------
function previewUrl() {
  const q = new URLSearchParams({ profile: $('profile').value, t: String(Date.now()) });
  if ($('scanner').value) q.set('scanner', $('scanner').value);
  return `/api/preview.png?${q}`;
}

function nextPreview() {
  if (state.previewOn) $('preview').src = previewUrl();
}

function togglePreview() {
  state.previewOn = !state.previewOn;
  $('preview-box').hidden = !state.previewOn;
  $('preview-toggle').classList.toggle('off', state.previewOn);
  if (state.previewOn) nextPreview();
}

function initPreview() {
  const img = $('preview');
  img.addEventListener('load', () => {
    $('preview-note').textContent = 'depth (near red, far blue) and colour';
    setTimeout(nextPreview, 250);
  });
  img.addEventListener('error', async () => {
    try {
      await api(previewUrl());
    } catch (e) {
      $('preview-note').textContent = e.message;
    }
    setTimeout(nextPreview, 2000);
  });
}

// ---- wiring --------------------------------------------------------------------
function init() {
  initViewer();
  initPreview();
  $('profile').addEventListener('change', profileChanged);
  $('start').addEventListener('click', () => guarded(startScan));
  $('preview-toggle').addEventListener('click', togglePreview);
  $('refresh').addEventListener('click', () => guarded(loadSessions));
  $('stop').addEventListener('click', () => guarded(() => api(`/api/jobs/${state.job}/stop`, { method: 'POST', json: {} })));
  $('resume-scan').addEventListener('click', () => guarded(async () => {
    const r = await api('/api/scan', { method: 'POST', json: { session: state.session, resume: true, run: true, profile: $('profile').value } });
    await openSession(r.session, r.job);
  }));
  $('rerun').addEventListener('click', () => guarded(async () => {
    const r = await api('/api/run', { method: 'POST', json: { session: state.session, resume: true, profile: $('profile').value } });
    await openSession(r.session, r.job);
  }));
  document.querySelectorAll('#viewer-modes button').forEach((b) =>
    b.addEventListener('click', () => guarded(() => show(b.dataset.mode))));
  $('mesh-colour').addEventListener('change', () => guarded(() => show('mesh')));
  $('token-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    state.token = $('token').value.trim();
    sessionStorage.setItem('station_token', state.token);
    // Downloads and the event stream carry it as a cookie (same site only).
    document.cookie = `station_token=${state.token}; SameSite=Strict; path=/`;
    guarded(loadStation);
  });
  guarded(loadStation);
}

init();
