// The contact annotation page (annotate/server.py serves it and its API).
// Two bodies (person 0 = marker wearer, person 1 = partner), each in its own viewport with
// OrbitControls (rotate, move, zoom); a click (no drag) picks the facet under the pointer; one
// facet on each body makes a correspondence. The regions of the correspondences light up.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const BASE = [[0.93, 0.72, 0.52], [0.62, 0.80, 0.90]];  // skin tints of person 0 / 1
const REGION_RGB = [0.90, 0.22, 0.20];     // regions in contact
const FACET_RGB = [1.0, 0.95, 0.1];        // annotated facets
const PENDING_RGB = [0.2, 0.95, 0.3];      // the facet picked, waiting for its partner
const PENDING_REGION_RGB = [0.98, 0.6, 0.25];

const $ = (id) => document.getElementById(id);
const state = {
  session: null, faces: null, faceRegion: null, frame: 0, rest: false,
  start: null, end: null, fr: null, pairs: [], pending: [null, null], proposal: null,
  saved: null, ready: false, meshFrame: null, lastError: '',
};
window.annotateState = state;   // read by the browser tests and handy in the console

function banner(msg) {
  const b = $('banner');
  state.lastError = msg || '';
  b.textContent = msg || '';
  b.hidden = !msg;
}
function status(msg) { $('status').textContent = msg; }

async function getJSON(url, opts) {
  const r = await fetch(url, opts);
  const j = await r.json();
  if (!r.ok) throw new Error(j.error || `${url}: HTTP ${r.status}`);
  return j;
}

// ------------------------------------------------------------------ 3D bodies
class BodyView {
  constructor(person, canvas) {
    this.person = person;
    this.canvas = canvas;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(1);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x2b3038);
    this.camera = new THREE.PerspectiveCamera(35, 1, 0.01, 50);
    this.camera.up.set(0, 0, 1);   // the world is z-up
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444455, 1.6));
    const d = new THREE.DirectionalLight(0xffffff, 1.2);
    this.camera.add(d); d.position.set(0.3, 0.6, 1);
    this.scene.add(this.camera);
    this.controls = new OrbitControls(this.camera, canvas);
    this.controls.enableDamping = false;
    this.controls.addEventListener('change', () => this.render());
    this.geometry = new THREE.BufferGeometry();
    this.mesh = new THREE.Mesh(this.geometry, new THREE.MeshLambertMaterial({ vertexColors: true, flatShading: true, side: THREE.DoubleSide }));
    this.scene.add(this.mesh);
    this.raycaster = new THREE.Raycaster();
    let down = null;
    canvas.addEventListener('pointerdown', (e) => { down = [e.clientX, e.clientY, e.button]; });
    canvas.addEventListener('pointerup', (e) => {
      if (!down || down[2] !== 0) return;
      const moved = Math.hypot(e.clientX - down[0], e.clientY - down[1]);
      down = null;
      if (moved < 4) this.pick(e.clientX, e.clientY);
    });
    new ResizeObserver(() => this.resize()).observe(canvas);
    this.framed = false;
  }
  resize() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h) return;
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }
  setVertices(V, lookFrom) {
    const F = state.faces, nF = F.length / 3;
    const pos = new Float32Array(nF * 9);
    for (let f = 0; f < nF; f++) {
      for (let k = 0; k < 3; k++) {
        const v = F[3 * f + k];
        pos[9 * f + 3 * k] = V[3 * v]; pos[9 * f + 3 * k + 1] = V[3 * v + 1]; pos[9 * f + 3 * k + 2] = V[3 * v + 2];
      }
    }
    this.geometry.setAttribute('position', new THREE.BufferAttribute(pos, 3));
    if (!this.geometry.getAttribute('color')) this.geometry.setAttribute('color', new THREE.BufferAttribute(new Float32Array(nF * 9), 3));
    this.geometry.computeVertexNormals();
    this.geometry.computeBoundingBox();
    this.geometry.computeBoundingSphere();
    const box = this.geometry.boundingBox, c = new THREE.Vector3();
    box.getCenter(c);
    if (!this.framed || lookFrom) this.frameOn(c, box, lookFrom);
    this.recolor();
  }
  frameOn(center, box, dir) {
    // look at the body's centre from `dir` (horizontal), far enough to see it whole
    const size = new THREE.Vector3(); box.getSize(size);
    const d = (dir || new THREE.Vector3(0, -1, 0)).clone(); d.z = 0;
    if (d.length() < 1e-6) d.set(0, -1, 0);
    d.normalize();
    const dist = 1.15 * Math.max(size.z, 0.8) / (2 * Math.tan(THREE.MathUtils.degToRad(this.camera.fov / 2)));
    this.controls.target.copy(center);
    this.camera.position.copy(center).addScaledVector(d, dist);
    this.camera.position.z += 0.1 * size.z;
    this.controls.update();
    this.framed = true;
  }
  recolor() {
    const col = this.geometry.getAttribute('color');
    if (!col) return;
    const a = col.array, p = this.person, fr = state.faceRegion;
    const regions = new Set(state.pairs.map((q) => fr[q[p]]));
    const facets = new Set(state.pairs.map((q) => q[p]));
    const pend = state.pending[p];
    const pendRegion = pend == null ? -1 : fr[pend];
    const base = BASE[p];
    for (let f = 0; f < fr.length; f++) {
      let c = base;
      if (facets.has(f)) c = FACET_RGB;
      else if (f === pend) c = PENDING_RGB;
      else if (regions.has(fr[f])) c = REGION_RGB;
      else if (fr[f] === pendRegion) c = PENDING_REGION_RGB;
      for (let k = 0; k < 3; k++) { a[9 * f + 3 * k] = c[0]; a[9 * f + 3 * k + 1] = c[1]; a[9 * f + 3 * k + 2] = c[2]; }
    }
    col.needsUpdate = true;
    this.render();
  }
  pick(x, y) {
    const r = this.canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((x - r.left) / r.width) * 2 - 1, -((y - r.top) / r.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    const hit = this.raycaster.intersectObject(this.mesh, false)[0];
    if (!hit) { status(`no facet under the pointer (person ${this.person})`); return; }
    pickFacet(this.person, hit.faceIndex);
  }
  render() { this.renderer.render(this.scene, this.camera); }
}

const views = [];

function regionName(f) {
  const r = state.faceRegion[f];
  return r >= 0 ? state.session.regions[r] : 'none';
}

function pickFacet(person, facet) {
  state.pending[person] = facet;
  if (state.pending[0] != null && state.pending[1] != null) {
    addPair([state.pending[0], state.pending[1]]);
    state.pending = [null, null];
  }
  showPending();
  views.forEach((v) => v.recolor());
}

function showPending() {
  const p = state.pending;
  $('pending').textContent = (p[0] == null && p[1] == null) ? '' :
    `picked: ${p.map((f, i) => f == null ? `person ${i}: click a facet` : `person ${i} facet ${f} (${regionName(f)})`).join(', ')}`;
}

function addPair(pair) {
  if (state.pairs.some((q) => q[0] === pair[0] && q[1] === pair[1])) return;
  state.pairs.push(pair);
  renderPairs();
  views.forEach((v) => v.recolor());
}

function removePair(i) {
  state.pairs.splice(i, 1);
  renderPairs();
  views.forEach((v) => v.recolor());
}

function renderPairs() {
  const tb = $('pairs').querySelector('tbody');
  tb.replaceChildren();
  state.pairs.forEach((q, i) => {
    const tr = document.createElement('tr');
    tr.className = 'pair';
    const cells = [String(i + 1), `${q[0]} (${regionName(q[0])})`, `${q[1]} (${regionName(q[1])})`];
    for (const t of cells) { const td = document.createElement('td'); td.textContent = t; tr.appendChild(td); }
    const td = document.createElement('td');
    const b = document.createElement('button');
    b.textContent = 'remove'; b.className = 'remove';
    b.addEventListener('click', () => removePair(i));
    td.appendChild(b); tr.appendChild(td); tb.appendChild(tr);
  });
  $('n-pairs').textContent = String(state.pairs.length);
}

// ------------------------------------------------------------------ frames and interval
let meshToken = 0;
async function loadMeshes() {
  const token = ++meshToken;
  const url = state.rest || !state.session.has_fits ? '/api/mesh.bin?rest=1' : `/api/mesh.bin?frame=${state.frame}`;
  const r = await fetch(url);
  const buf = await r.arrayBuffer();
  if (token !== meshToken) return;
  state.meshFrame = r.headers.get('X-Mesh-Frame');
  const mf = state.meshFrame;
  $('mesh-note').textContent = mf === 'rest' ? (state.session.has_fits ? 'rest pose' : 'rest pose (no fits on disk)')
    : mf !== String(state.frame) ? `no fit at frame ${state.frame}: the meshes of frame ${mf}` : `meshes of frame ${mf}`;
  const V = new Float32Array(buf);
  const n = V.length / 2;
  const parts = [V.subarray(0, n), V.subarray(n)];
  const centre = (W) => {
    let x = 0, y = 0, z = 0; const m = W.length / 3;
    for (let i = 0; i < W.length; i += 3) { x += W[i]; y += W[i + 1]; z += W[i + 2]; }
    return new THREE.Vector3(x / m, y / m, z / m);
  };
  const c = parts.map(centre);
  const refit = !views[0].framed || state.refit;
  state.refit = false;
  for (let p = 0; p < 2; p++) {
    let dir = null;
    if (refit) {
      // posed: look from the other person's side (where the contact is); rest: from the front
      dir = state.rest || !state.session.has_fits ? frontOf(parts[p]) : c[1 - p].clone().sub(c[p]);
    }
    views[p].setVertices(parts[p], dir);
  }
  state.ready = true;
  document.body.dataset.ready = '1';
}

function frontOf(W) {
  // the direction from the back (upper_back regions) to the chest: the body's front
  const fr = state.faceRegion, F = state.faces, names = state.session.regions;
  const acc = [new THREE.Vector3(), new THREE.Vector3()], cnt = [0, 0];
  for (let f = 0; f < fr.length; f++) {
    const nm = names[fr[f]] || '';
    const k = nm.endsWith('chest_upper') ? 0 : nm.endsWith('upper_back') ? 1 : -1;
    if (k < 0) continue;
    const v = F[3 * f];
    acc[k].x += W[3 * v]; acc[k].y += W[3 * v + 1]; acc[k].z += W[3 * v + 2]; cnt[k]++;
  }
  if (!cnt[0] || !cnt[1]) return new THREE.Vector3(0, -1, 0);
  return acc[0].divideScalar(cnt[0]).sub(acc[1].divideScalar(cnt[1]));
}

function setFrame(f) {
  const n = state.session.n_frames;
  f = Math.max(0, Math.min(n - 1, Math.round(Number(f) || 0)));
  state.frame = f;
  $('frame-slider').value = String(f);
  $('frame-num').value = String(f);
  if (state.session.has_video) $('views').src = `/api/views.jpg?frame=${f}`;
  if (state.session.has_fits && !state.rest) loadMeshes();
  drawCurve();
}

function showInterval() {
  $('start-v').textContent = state.start == null ? '-' : state.start;
  $('end-v').textContent = state.end == null ? '-' : state.end;
  $('fr-v').textContent = state.fr == null ? '-' : state.fr;
  drawCurve();
}

function drawCurve() {
  const cv = $('curve'), g = cv.getContext('2d');
  const W = cv.width, H = cv.height, n = state.session ? state.session.n_frames : 1;
  const x = (f) => (f + 0.5) / n * W;
  g.clearRect(0, 0, W, H);
  if (state.start != null && state.end != null) {
    g.fillStyle = 'rgba(230,60,50,0.30)';
    g.fillRect(x(state.start - 0.5), 0, x(state.end + 0.5) - x(state.start - 0.5), H);
  }
  const p = state.proposal;
  if (p && p.status === 'ready' && p.distance_mm) {
    const d = p.distance_mm.map((v) => (v == null ? null : Math.max(-30, Math.min(300, v))));
    const lo = -30, hi = Math.max(50, ...d.filter((v) => v != null));
    const y = (v) => H - 4 - (v - lo) / (hi - lo) * (H - 8);
    g.strokeStyle = '#8ab'; g.beginPath();
    let started = false;
    p.frames.forEach((f, i) => {
      if (d[i] == null) return;
      if (!started) { g.moveTo(x(f), y(d[i])); started = true; } else g.lineTo(x(f), y(d[i]));
    });
    g.stroke();
    g.strokeStyle = '#665'; g.beginPath(); g.moveTo(0, y(0)); g.lineTo(W, y(0)); g.stroke();
  }
  if (state.fr != null) { g.fillStyle = '#fd3'; g.fillRect(x(state.fr) - 1, 0, 3, H); }
  g.fillStyle = '#fff'; g.fillRect(x(state.frame) - 0.5, 0, 1.5, H);
}

// ------------------------------------------------------------------ proposal
async function pollProposal() {
  let p;
  try { p = await getJSON('/api/proposal'); } catch (e) { $('proposal-body').textContent = String(e.message); return; }
  state.proposal = p;
  const body = $('proposal-body');
  if (p.status === 'computing') {
    body.textContent = `computing from the ${state.session.has_fits ? 'fitted surfaces' : 'keypoints'}... ${p.done || 0}/${p.total || '?'} frames`;
    setTimeout(pollProposal, 700);
    return;
  }
  body.replaceChildren();
  if (p.status !== 'ready') { body.textContent = `no proposal: ${p.why}`; return; }
  // nothing saved and no frame asked for: show the proposed contact frame
  if (!state.saved && !state.session.frame_given && p.fr_id != null && state.pairs.length === 0) setFrame(p.fr_id);
  const line = document.createElement('div');
  if (p.interval == null) {
    line.textContent = p.source === 'fits'
      ? `the fitted surfaces never come within ${p.near_mm} mm (closest ${Math.min(...p.distance_mm).toFixed(1)} mm)`
      : 'the keypoints could not be triangulated';
  } else {
    line.textContent = `${p.source === 'fits' ? `surfaces within ${p.near_mm} mm` : 'keypoints closest'}: interval ${p.interval[0]}..${p.interval[1]}, contact frame ${p.fr_id} `;
    const b = document.createElement('button');
    b.id = 'accept-interval'; b.textContent = 'accept interval';
    b.addEventListener('click', () => { [state.start, state.end] = p.interval; state.fr = p.fr_id; showInterval(); setFrame(p.fr_id); });
    line.appendChild(b);
  }
  body.appendChild(line);
  if (p.pairs && p.pairs.length) {
    const l2 = document.createElement('div');
    l2.textContent = `${p.pairs.length} candidate facet pairs at frame ${p.fr_id} `;
    const b = document.createElement('button');
    b.id = 'accept-pairs'; b.textContent = 'accept all';
    b.addEventListener('click', () => { p.pairs.forEach((q) => addPair([q[0], q[1]])); });
    l2.appendChild(b);
    const ul = document.createElement('div');
    ul.style.maxHeight = '120px'; ul.style.overflow = 'auto';
    p.pairs.forEach((q, i) => {
      const it = document.createElement('div');
      it.textContent = `${regionName(q[0])} - ${regionName(q[1])} (${p.pair_distance_mm[i]} mm) `;
      const a = document.createElement('button');
      a.textContent = '+'; a.title = 'accept this pair';
      a.addEventListener('click', () => addPair([q[0], q[1]]));
      it.appendChild(a); ul.appendChild(it);
    });
    body.append(l2, ul);
  }
  drawCurve();
}

// ------------------------------------------------------------------ load / save
function applySaved(saved) {
  state.saved = saved;
  if (!saved) return;
  state.pairs = saved.pairs.map((q) => [q[0], q[1]]);
  [state.start, state.end] = saved.interval;
  state.fr = saved.fr_id;
  if (saved.annotator && !$('annotator').value) $('annotator').value = saved.annotator;
  renderPairs();
  showInterval();
  views.forEach((v) => v.recolor());
}

async function save() {
  banner('');
  if (state.start == null || state.end == null || state.fr == null) {
    banner('Set the interval (start, end) and the contact frame before saving.');
    return;
  }
  status('saving...');
  try {
    const r = await getJSON('/api/save', {
      method: 'POST', headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify({ fr_id: state.fr, start: state.start, end: state.end, pairs: state.pairs, annotator: $('annotator').value }),
    });
    applySaved(r.saved);
    status(`saved ${state.pairs.length} pairs to ${r.path} at ${new Date().toLocaleTimeString()}`);
    document.body.dataset.saved = String(Number(document.body.dataset.saved || 0) + 1);
  } catch (e) {
    status('');
    banner(`Not saved: ${e.message}`);
  }
}

async function main() {
  let s;
  try { s = await getJSON('/api/session'); } catch (e) { banner(`Cannot load the session: ${e.message}`); return; }
  state.session = s;
  state.faceRegion = Int32Array.from(s.face_region);
  state.faces = new Int32Array(await (await fetch('/api/faces.bin')).arrayBuffer());
  $('title').textContent = `Contact annotation: ${s.sequence}`;
  $('file').textContent = s.out;
  $('annotator').value = s.annotator || '';
  $('title-0').textContent = `person 0: ${s.people[0]}${s.markerless ? '' : ' (markers)'}`;
  $('title-1').textContent = `person 1: ${s.people[1]} (partner)`;
  $('frame-slider').max = String(s.n_frames - 1);
  $('frame-num').max = String(s.n_frames - 1);
  if (!s.has_video) { $('views').hidden = true; $('no-video').hidden = false; }
  if (!s.has_fits) { $('rest').checked = true; $('rest').disabled = true; state.rest = true; }
  views.push(new BodyView(0, $('view3d-0')), new BodyView(1, $('view3d-1')));
  views.forEach((v) => v.resize());
  $('frame-slider').addEventListener('input', (e) => setFrame(e.target.value));
  $('frame-num').addEventListener('change', (e) => setFrame(e.target.value));
  $('prev').addEventListener('click', () => setFrame(state.frame - 1));
  $('next').addEventListener('click', () => setFrame(state.frame + 1));
  document.addEventListener('keydown', (e) => {
    if (e.target.tagName === 'INPUT' && e.target.type !== 'range') return;
    if (e.key === 'ArrowLeft') setFrame(state.frame - 1);
    if (e.key === 'ArrowRight') setFrame(state.frame + 1);
  });
  $('set-start').addEventListener('click', () => {
    state.start = state.frame;
    if (state.end != null && state.end < state.start) state.end = state.start;
    if (state.fr == null || state.fr < state.start) state.fr = state.start;
    showInterval();
  });
  $('set-end').addEventListener('click', () => {
    state.end = state.frame;
    if (state.start != null && state.start > state.end) state.start = state.end;
    if (state.fr == null || state.fr > state.end) state.fr = state.start == null ? state.end : Math.max(state.start, Math.min(state.fr ?? state.end, state.end));
    showInterval();
  });
  $('set-contact').addEventListener('click', () => { state.fr = state.frame; showInterval(); });
  $('rest').addEventListener('change', (e) => { state.rest = e.target.checked; state.refit = true; loadMeshes(); });
  $('save').addEventListener('click', save);
  if (s.load_error) banner(`The saved file was refused: ${s.load_error}`);
  applySaved(s.saved);
  state.refit = true;
  setFrame(s.saved ? s.saved.fr_id : s.frame);
  if (!s.has_fits || state.rest) await loadMeshes();
  pollProposal();
}

main();
