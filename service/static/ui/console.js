// pmvir console: a static page over the public /v1 API.
// The API key lives in this tab's sessionStorage and travels only in the Authorization header.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { PLYLoader } from "three/addons/loaders/PLYLoader.js";
import { shadingAtGltfNormal } from "./shading.js";

const KEY_STORE = "pmvir.apiKey";
const app = document.getElementById("app");
const signoutButton = document.getElementById("signout");
let stopPolling = () => {};

// ---------------------------------------------------------------- helpers

function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k === "class") el.className = v;
    else if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "text") el.textContent = v;
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

const apiKey = () => sessionStorage.getItem(KEY_STORE);

class ApiError extends Error {
  constructor(status, body) {
    super((body && body.message) || `HTTP ${status}`);
    this.status = status;
    this.body = body || {};
  }
}

async function api(path, { method = "GET", body, headers = {}, raw = false, key } = {}) {
  const opts = { method, headers: { Authorization: `Bearer ${key || apiKey()}`, ...headers } };
  if (body !== undefined) {
    opts.body = typeof body === "string" ? body : JSON.stringify(body);
    opts.headers["Content-Type"] = "application/json";
  }
  const r = await fetch(path, opts);
  if (!r.ok) {
    let b = null;
    try { b = await r.json(); } catch (e) { b = { message: `HTTP ${r.status}` }; }
    if (r.status === 401 && !key) { signOut("Your API key was refused (401): sign in again."); }
    throw new ApiError(r.status, b);
  }
  if (raw) return r;
  if (r.status === 204) return null;
  return r.json();
}

// Start a job and wait while the server validates its capture (202, status "validating"); a refused
// capture comes back to "created" with its problems, shown as the 422 the start would have answered.
async function startAndValidate(id) {
  let job = await api(`/v1/jobs/${id}/start`, { method: "POST" });
  const deadline = Date.now() + 600_000;
  while (job && job.status === "validating" && Date.now() < deadline) {
    await new Promise((resolve) => setTimeout(resolve, 500));
    job = await api(`/v1/jobs/${id}`);
  }
  if (job && job.status === "created" && job.problems && job.problems.length) {
    throw new ApiError(422, { error: "invalid_capture", message: job.error || "The capture was refused.", errors: job.problems });
  }
  return job;
}

function errorBox(err) {
  const body = err.body || {};
  const box = h("div", { class: "error", role: "alert" }, body.message || String(err.message || err));
  if (body.errors && body.errors.length) {
    box.append(h("ul", {}, body.errors.map((e) =>
      h("li", {}, e.file ? h("b", {}, e.file + ": ") : (e.loc ? h("b", {}, e.loc.join(".") + ": ") : ""), e.msg))));
  }
  return box;
}

const fmtTime = (s) => (s ? new Date(s).toLocaleString() : "—");
const fmtBytes = (n) => (n < 1024 ? `${n} B` : n < 1 << 20 ? `${(n / 1024).toFixed(1)} KiB` : `${(n / (1 << 20)).toFixed(1)} MiB`);
const pct = (x) => `${Math.round((x || 0) * 100)}%`;
const bar = (x, wide) => h("span", { class: "bar" + (wide ? " wide" : ""), title: pct(x) }, h("span", { style: `width:${pct(x)}` }));
const badge = (status) => h("span", { class: `badge ${status}`, "data-status": status }, status);
const finished = (s) => ["succeeded", "failed", "canceled"].includes(s);

function navigate(path) {
  history.pushState({}, "", path);
  route();
}
document.addEventListener("click", (ev) => {
  const a = ev.target.closest("a[data-nav]");
  if (a && !ev.ctrlKey && !ev.metaKey && ev.button === 0) { ev.preventDefault(); navigate(a.getAttribute("href")); }
});
window.addEventListener("popstate", route);

function poll(fn, ms) {
  let alive = true, timer = null;
  const tick = async () => {
    if (!alive) return;
    try { await fn(); } catch (e) { if (!(e instanceof ApiError)) console.warn(e); }
    if (alive) timer = setTimeout(tick, ms);
  };
  tick();
  return () => { alive = false; clearTimeout(timer); };
}

async function blobUrl(path) {
  const r = await api(path, { raw: true });
  return URL.createObjectURL(await r.blob());
}

async function download(path, name) {
  const url = await blobUrl(path);
  const a = h("a", { href: url, download: name });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ---------------------------------------------------------------- sign-in

function signOut(message) {
  sessionStorage.removeItem(KEY_STORE);
  stopPolling();
  renderSignIn(message);
}
signoutButton.addEventListener("click", () => signOut());

function renderSignIn(message) {
  signoutButton.hidden = true;
  const input = h("input", { type: "password", id: "api-key", autocomplete: "off", placeholder: "API key", size: 40 });
  const msg = h("div", { id: "signin-message" });
  if (message) msg.append(h("div", { class: "error", role: "alert" }, message));
  const form = h("form", { class: "card", id: "signin" },
    h("h1", {}, "Sign in"),
    h("p", { class: "muted" }, "Enter one of the server's API keys (PMVIR_API_KEYS). It is kept only in this browser tab."),
    h("div", { class: "row" }, input, h("button", { class: "btn primary", type: "submit" }, "Sign in")),
    msg);
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const key = input.value.trim();
    msg.replaceChildren();
    if (!key) { msg.append(h("div", { class: "error", role: "alert" }, "Enter an API key.")); return; }
    try {
      await api("/v1/jobs?limit=1", { key });
      sessionStorage.setItem(KEY_STORE, key);
      route();
    } catch (e) {
      const text = e.status === 401
        ? "This API key was not accepted (401 unauthorized). Check the key: it must be one of the server's PMVIR_API_KEYS."
        : `The server could not be reached or answered ${e.status || "nothing"}: ${e.message}`;
      msg.append(h("div", { class: "error", role: "alert", id: "signin-error" }, text));
    }
  });
  app.replaceChildren(form);
  input.focus();
}

// ---------------------------------------------------------------- jobs list

function renderJobs() {
  const rows = h("tbody");
  const table = h("table", { id: "jobs" },
    h("thead", {}, h("tr", {}, ["Job", "Label", "Status", "Stage", "Progress", "Created", ""].map((t) => h("th", {}, t)))), rows);
  const listError = h("div");
  app.replaceChildren(renderUpload(), h("section", { class: "card" }, h("h2", {}, "Jobs"), listError, table));

  const refresh = async () => {
    const data = await api("/v1/jobs?limit=100");
    listError.replaceChildren();
    rows.replaceChildren(...data.jobs.map((j) => h("tr", { "data-job": j.id },
      h("td", { class: "mono" }, h("a", { href: `/ui/jobs/${j.id}`, "data-nav": true }, j.id.slice(0, 12))),
      h("td", {}, j.label || ""),
      h("td", {}, badge(j.status)),
      h("td", {}, j.stage || ""),
      h("td", {}, bar(j.progress), " ", pct(j.progress)),
      h("td", {}, fmtTime(j.created_at)),
      h("td", {}, jobActions(j, refresh)))));
    if (!data.jobs.length) rows.append(h("tr", {}, h("td", { colspan: 7, class: "muted" }, "No jobs yet: drop a zipped capture above.")));
  };
  stopPolling = poll(async () => {
    try { await refresh(); } catch (e) { listError.replaceChildren(errorBox(e)); throw e; }
  }, 2000);
}

function jobActions(job, after) {
  const out = [];
  if (!finished(job.status)) {
    out.push(h("button", { class: "btn", type: "button", onclick: async () => {
      try { await api(`/v1/jobs/${job.id}/cancel`, { method: "POST" }); } catch (e) { alert(e.message); }
      after();
    } }, "Cancel"));
  }
  out.push(h("button", { class: "btn danger", type: "button", onclick: async () => {
    if (!confirm(`Delete job ${job.id} and its files?`)) return;
    try { await api(`/v1/jobs/${job.id}`, { method: "DELETE" }); } catch (e) { alert(e.message); }
    after();
  } }, "Delete"));
  return out;
}

function renderUpload() {
  const fileInput = h("input", { type: "file", accept: ".zip,application/zip", hidden: true, id: "capture-file" });
  const label = h("input", { type: "text", placeholder: "label (optional)", size: 30, id: "job-label" });
  const options = h("textarea", { rows: 2, cols: 60, placeholder: '{"refine": {"solver": {"max_iterations": 20}}}  (options, optional)', id: "job-options" });
  const status = h("div", { id: "upload-status" });
  const drop = h("div", { class: "drop", id: "drop", tabindex: 0 }, "Drop a zipped capture here, or click to choose one");
  drop.addEventListener("click", () => fileInput.click());
  drop.addEventListener("dragover", (ev) => { ev.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (ev) => {
    ev.preventDefault();
    drop.classList.remove("over");
    if (ev.dataTransfer.files.length) submit(ev.dataTransfer.files[0]);
  });
  fileInput.addEventListener("change", () => fileInput.files.length && submit(fileInput.files[0]));

  function submit(file) {
    status.replaceChildren();
    if (!/\.zip$/i.test(file.name)) { status.append(h("div", { class: "error" }, `${file.name}: choose a .zip of a capture folder`)); return; }
    const text = options.value.trim();
    if (text) { try { JSON.parse(text); } catch (e) { status.append(h("div", { class: "error" }, `options: not valid JSON: ${e.message}`)); return; } }
    const form = new FormData();
    form.append("capture", file, file.name);
    if (text) form.append("options", text);
    if (label.value.trim()) form.append("label", label.value.trim());
    const progress = bar(0, true);
    const line = h("div", { class: "muted" }, `Uploading ${file.name} (${fmtBytes(file.size)})…`);
    status.append(line, progress);
    const xhr = new XMLHttpRequest();
    xhr.open("POST", "/v1/jobs");
    xhr.setRequestHeader("Authorization", `Bearer ${apiKey()}`);
    xhr.upload.addEventListener("progress", (ev) => {
      if (ev.lengthComputable) progress.firstChild.style.width = pct(ev.loaded / ev.total);
    });
    xhr.addEventListener("error", () => status.replaceChildren(h("div", { class: "error" }, "The upload failed: the server could not be reached.")));
    xhr.addEventListener("load", async () => {
      let body = {};
      try { body = JSON.parse(xhr.responseText); } catch (e) { body = { message: xhr.responseText }; }
      if (xhr.status !== 201 && xhr.status !== 200) { status.replaceChildren(errorBox(new ApiError(xhr.status, body))); return; }
      line.textContent = `Uploaded; starting job ${body.id.slice(0, 12)}…`;
      try {
        await startAndValidate(body.id);
        status.replaceChildren(h("div", {}, "Job started: ", h("a", { href: `/ui/jobs/${body.id}`, "data-nav": true }, body.id)));
      } catch (e) {
        status.replaceChildren(h("div", {}, "The capture was uploaded but the job could not start (job ",
          h("a", { href: `/ui/jobs/${body.id}`, "data-nav": true }, body.id.slice(0, 12)), "):"), errorBox(e));
      }
    });
    xhr.send(form);
  }
  return h("section", { class: "card" }, h("h2", {}, "New job"), drop, fileInput,
    h("div", { class: "row", style: "margin-top:10px" }, label, options), status);
}

// ---------------------------------------------------------------- job page

function renderJob(id) {
  const head = h("div");
  const info = h("div", { class: "grow" });
  const timings = h("div", { class: "grow" });
  const errors = h("div", { id: "job-error" });
  const log = h("div", { class: "log", id: "log" });
  const results = h("div", { id: "results" });
  app.replaceChildren(
    h("p", {}, h("a", { href: "/ui/", "data-nav": true }, "← all jobs")),
    h("section", { class: "card" }, head, errors, h("div", { class: "row" }, info, timings)),
    results,
    h("section", { class: "card" }, h("h2", {}, "Log"), log));
  let since = 0, shownResults = false;
  stopPolling = poll(async () => {
    let job;
    try { job = await api(`/v1/jobs/${id}`); } catch (e) { head.replaceChildren(errorBox(e)); throw e; }
    head.replaceChildren(
      h("h1", {}, `Job ${job.id}`, " ", badge(job.status)),
      h("div", { class: "row" }, h("div", { class: "grow" }, bar(job.progress, true)), h("b", { id: "job-progress" }, pct(job.progress))),
      h("p", {}, h("span", { class: "muted" }, "stage: "), h("b", { id: "job-stage" }, job.stage || "—"), " ", jobActions(job, () => {})));
    info.replaceChildren(h("dl", { class: "kv" },
      h("dt", {}, "label"), h("dd", {}, job.label || "—"),
      h("dt", {}, "created"), h("dd", {}, fmtTime(job.created_at)),
      h("dt", {}, "started"), h("dd", {}, fmtTime(job.started_at)),
      h("dt", {}, "finished"), h("dd", {}, fmtTime(job.finished_at)),
      h("dt", {}, "capture files"), h("dd", {}, `${job.files.length} (${fmtBytes(job.files.reduce((a, f) => a + f.size, 0))})`)));
    const t = Object.entries(job.stage_timings || {});
    timings.replaceChildren(h("h2", {}, "Stage timings"), t.length
      ? h("table", { id: "timings" }, h("tbody", {}, t.map(([k, v]) => h("tr", {}, h("td", {}, k), h("td", {}, `${v.toFixed(1)} s`)))))
      : h("p", { class: "muted" }, "none yet"));
    errors.replaceChildren();
    if (job.error) errors.append(h("div", { class: "error", role: "alert" }, job.error));
    const data = await api(`/v1/jobs/${id}/log?since=${since}&limit=1000`);
    for (const line of data.lines) log.append(`${new Date(line.time).toLocaleTimeString()}  ${line.message}\n`);
    if (data.lines.length) log.scrollTop = log.scrollHeight;
    since = data.next;
    if (finished(job.status) && !shownResults) {
      shownResults = true;
      renderResults(job, results).catch((e) => results.replaceChildren(errorBox(e)));
    }
    if (finished(job.status) && since >= data.total) stopPolling();
  }, 1500);
}

async function renderResults(job, box) {
  const listing = await api(`/v1/jobs/${job.id}/results`);
  const paths = new Set(listing.files.map((f) => f.path));
  const base = `/v1/jobs/${job.id}/results/`;
  const sections = [];
  let illumination = null, report = null;
  if (paths.has("illumination.json")) illumination = await api(base + "illumination.json");
  if (paths.has("report.json")) report = await api(base + "report.json");
  const views = [...new Set(listing.files.map((f) => f.path.match(/^(?:previews|residuals)\/(.+)_(?:int|dop|aop|intensity|epol)\.png$/)).filter(Boolean).map((m) => m[1]))].sort();
  const viewSelect = h("select", { id: "view-select" }, views.map((v) => h("option", { value: v }, v)));

  if (paths.has("mesh.glb")) sections.push(await viewerSection(job, base, paths, illumination, viewSelect));
  if (report && report.refine) sections.push(plotSection(report.refine.stages));
  if (views.length) sections.push(imagesSection(base, paths, views, viewSelect));
  sections.push(downloadsSection(job, listing, base));
  box.replaceChildren(...sections);
}

function downloadsSection(job, listing, base) {
  // single files first; the files of a folder (previews/, residuals/, poses/) under one fold each,
  // with the folder as one zip (GET /v1/jobs/{id}/result/{folder}.zip) beside it
  const link = (f) => h("li", {}, h("a", { "data-path": f.path, title: f.description,
    onclick: () => download(base + f.path, f.path.replace(/\//g, "_")) }, f.path), " ", h("span", { class: "muted" }, fmtBytes(f.size)));
  const folders = new Map();
  const singles = [];
  for (const f of listing.files) {
    const slash = f.path.indexOf("/");
    if (slash < 0) { singles.push(f); continue; }
    const name = f.path.slice(0, slash);
    if (!folders.has(name)) folders.set(name, []);
    folders.get(name).push(f);
  }
  const zips = new Set(job.results || []);
  const blocks = [...folders].map(([name, files]) => h("details", { "data-folder": name },
    h("summary", {}, `${name}/ — ${files.length} files, ${fmtBytes(files.reduce((a, f) => a + f.size, 0))}`,
      zips.has(`${name}.zip`) ? h("span", {}, " · ", h("a", { "data-zip": `${name}.zip`,
        onclick: (ev) => { ev.preventDefault(); download(`/v1/jobs/${job.id}/result/${name}.zip`, `${name}.zip`); } }, `${name}.zip`)) : ""),
    h("ul", { class: "downloads" }, files.map(link))));
  return h("section", { class: "card", id: "downloads" }, h("h2", {}, "Downloads"),
    h("ul", { class: "downloads" }, singles.map(link)), blocks);
}

// ---------------------------------------------------------------- 3D view

async function viewerSection(job, base, paths, illumination, viewSelect) {
  const holder = h("div", { id: "viewer" });
  const mode = (value, text, checked) => h("label", {}, h("input", { type: "radio", name: "mode", value, checked }), text);
  const initialBox = h("input", { type: "checkbox", id: "show-initial", disabled: !paths.has("initial.ply") });
  const note = h("span", { class: "muted", id: "viewer-note" });
  const section = h("section", { class: "card" }, h("h2", {}, "Refined mesh"),
    h("div", { class: "toolbar" }, mode("albedo", "albedo", true), mode("shaded", "shaded with the lighting of view", false), viewSelect,
      mode("normals", "normals", false), h("label", {}, initialBox, "initial surface beside"), note),
    holder);

  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.outputColorSpace = THREE.SRGBColorSpace;
  holder.append(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x20252f);
  const camera = new THREE.PerspectiveCamera(40, 1, 0.001, 1000);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = true;
  scene.add(new THREE.HemisphereLight(0xffffff, 0x444455, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5);
  sun.position.set(1, 2, 1.5);
  scene.add(sun);

  const glbBuffer = await (await api(base + "mesh.glb", { raw: true })).arrayBuffer();
  const gltf = await new GLTFLoader().parseAsync(glbBuffer, "");
  let mesh = null;
  gltf.scene.traverse((o) => { if (o.isMesh && !mesh) mesh = o; });
  const geom = mesh.geometry;
  geom.computeBoundingBox();
  const box = geom.boundingBox, size = new THREE.Vector3(), centre = new THREE.Vector3();
  box.getSize(size); box.getCenter(centre);
  const linearAlbedo = geom.getAttribute("color");
  const normals = geom.getAttribute("normal");
  // The albedo shares a per-channel scale with rgb_scale (only their product is known), so it is
  // shown exposed: its 99th percentile (brightest channel) maps to white, as the previews do.
  const peaks = [];
  for (let i = 0; i < linearAlbedo.count; i += 7) peaks.push(Math.max(linearAlbedo.getX(i), linearAlbedo.getY(i), linearAlbedo.getZ(i)));
  peaks.sort((a, b) => a - b);
  const exposure = 1 / Math.max(peaks[Math.floor(peaks.length * 0.99)] || 1, 1e-6);
  const albedo = new THREE.BufferAttribute(linearAlbedo.array.map((v) => Math.min(v * exposure, 1)), 3);
  const shaded = new THREE.BufferAttribute(new Float32Array(albedo.count * 3), 3);
  const materials = {
    // double-sided: a surface trimmed to the dense points may have holes, through which its inside shows
    albedo: new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide }),
    shaded: new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.DoubleSide }),
    normals: new THREE.MeshNormalMaterial({ side: THREE.DoubleSide }),
  };
  const refined = new THREE.Mesh(geom, materials.albedo);
  refined.position.sub(centre);
  const group = new THREE.Group();
  group.add(refined);
  scene.add(group);
  let initial = null;

  function shade() {
    if (!illumination) { note.textContent = "no illumination.json"; return; }
    const stem = viewSelect.value;
    const frame = illumination.frames.find((f) => f.file.replace(/^.*\//, "").replace(/\.[^.]*$/, "") === stem) || illumination.frames[0];
    const values = new Float32Array(albedo.count * 3);
    let peak = [];
    for (let i = 0; i < albedo.count; i++) {
      const s = Math.max(0, shadingAtGltfNormal(normals.getX(i), normals.getY(i), normals.getZ(i), frame.sh, frame.sh_high));
      for (let c = 0; c < 3; c++) values[3 * i + c] = linearAlbedo.array[3 * i + c] * s * frame.rgb_scale[c];
      if (i % 7 === 0) peak.push(Math.max(values[3 * i], values[3 * i + 1], values[3 * i + 2]));
    }
    peak.sort((a, b) => a - b);
    const white = peak[Math.floor(peak.length * 0.99)] || 1;
    for (let i = 0; i < values.length; i++) values[i] = Math.min(values[i] / white, 1);
    shaded.array.set(values);
    shaded.needsUpdate = true;
    note.textContent = `lighting of ${frame.file}`;
  }

  function apply() {
    const m = section.querySelector("input[name=mode]:checked").value;
    if (m === "shaded") { shade(); geom.setAttribute("color", shaded); } else geom.setAttribute("color", albedo);
    if (m === "albedo") note.textContent = `linear albedo × ${exposure.toFixed(2)} (99th percentile to white)`;
    else if (m !== "shaded") note.textContent = "";
    refined.material = materials[m];
    holder.dataset.mode = m;
  }
  section.addEventListener("change", async (ev) => {
    if (ev.target === initialBox) {
      if (initialBox.checked && !initial) {
        const buf = await (await api(base + "initial.ply", { raw: true })).arrayBuffer();
        const g = new PLYLoader().parse(buf);
        g.deleteAttribute("color");
        g.applyMatrix4(new THREE.Matrix4().makeRotationX(-Math.PI / 2)); // capture +Z up -> +Y up, as mesh.glb
        g.computeVertexNormals();
        initial = new THREE.Mesh(g, new THREE.MeshStandardMaterial({ color: 0xb8bcc6, roughness: 0.9, side: THREE.DoubleSide }));
        initial.position.copy(centre).negate();
        group.add(initial);
      }
      if (initial) initial.visible = initialBox.checked;
      refined.position.set(-centre.x - (initialBox.checked ? size.x * 0.6 : 0), -centre.y, -centre.z);
      if (initial) initial.position.set(-centre.x + size.x * 0.6, -centre.y, -centre.z);
      frame(initialBox.checked ? 2.2 : 1.0);
      return;
    }
    if (ev.target === viewSelect && section.querySelector("input[name=mode]:checked").value !== "shaded") return;
    apply();
  });

  function frame(widen) {
    const radius = 0.5 * size.length() * widen;
    camera.position.set(0, radius * 0.45, radius * 1.75);
    camera.near = radius / 100;
    camera.far = radius * 100;
    camera.updateProjectionMatrix();
    controls.target.set(0, 0, 0);
    controls.update();
  }
  function resize() {
    const w = holder.clientWidth || 800, hh = holder.clientHeight || 460;
    renderer.setSize(w, hh);
    camera.aspect = w / hh;
    camera.updateProjectionMatrix();
  }
  new ResizeObserver(resize).observe(holder);
  resize();
  frame(1.0);
  apply();
  renderer.setAnimationLoop(() => {
    if (!document.body.contains(holder)) { renderer.setAnimationLoop(null); renderer.dispose(); return; }
    controls.update();
    renderer.render(scene, camera);
  });
  holder.dataset.vertices = String(geom.getAttribute("position").count);
  holder.dataset.ready = "1";
  return section;
}

// ---------------------------------------------------------------- convergence plot

const TERM_COLOURS = { total: "#1d2430", pho: "#2f6fde", pol: "#c9342b", gsm: "#1e8e4a", psm: "#b7791f" };

function plotSection(stages) {
  const svgNS = "http://www.w3.org/2000/svg";
  const terms = [];
  for (const st of stages) for (const e of st.energies || []) for (const k of Object.keys(e)) if (!terms.includes(k)) terms.push(k);
  const W = 1000, H = 300, L = 60, R = 10, T = 10, B = 34;
  const counts = stages.map((st) => (st.energies || []).length);
  const total = counts.reduce((a, b) => a + b, 0);
  let lo = Infinity, hi = -Infinity;
  for (const st of stages) for (const e of st.energies || []) for (const k of terms) if (e[k] > 0) { lo = Math.min(lo, e[k]); hi = Math.max(hi, e[k]); }
  if (!isFinite(lo)) { lo = 1; hi = 10; }
  const llo = Math.floor(Math.log10(lo)), lhi = Math.max(Math.ceil(Math.log10(hi)), llo + 1);
  const x = (i) => L + (W - L - R) * (total > 1 ? i / (total - 1) : 0.5);
  const y = (v) => T + (H - T - B) * (1 - (Math.log10(v) - llo) / (lhi - llo));
  const el = (tag, attrs) => { const e = document.createElementNS(svgNS, tag); for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v); return e; };
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, preserveAspectRatio: "none", role: "img", "aria-label": "energy per iteration" });
  for (let p = llo; p <= lhi; p++) {
    svg.append(el("line", { x1: L, x2: W - R, y1: y(10 ** p), y2: y(10 ** p), stroke: "#e3e6ec" }));
    const t = el("text", { x: L - 6, y: y(10 ** p) + 4, "text-anchor": "end", "font-size": 11, fill: "#6b7485" });
    t.textContent = `1e${p}`;
    svg.append(t);
  }
  let offset = 0;
  stages.forEach((st, s) => {
    const x0 = x(offset), x1 = x(offset + Math.max(counts[s] - 1, 0));
    if (s % 2 === 1) svg.append(el("rect", { x: x0, y: T, width: Math.max(x1 - x0, 1), height: H - T - B, fill: "#f3f5f8" }));
    const t = el("text", { x: (x0 + x1) / 2, y: H - 10, "text-anchor": "middle", "font-size": 11, fill: "#6b7485" });
    t.textContent = `stage ${s + 1} (${Math.max(counts[s] - 1, 0)} it.)`;
    svg.append(t);
    offset += counts[s];
  });
  for (const k of terms) {
    let d = "", i = 0;
    for (const st of stages) {
      let pen = "M";
      for (const e of st.energies || []) {
        if (e[k] > 0) { d += `${pen}${x(i).toFixed(1)},${y(e[k]).toFixed(1)} `; pen = "L"; } else pen = "M";
        i++;
      }
    }
    svg.append(el("path", { d: d || `M${L},${H - B}`, fill: "none", stroke: TERM_COLOURS[k] || "#777", "stroke-width": k === "total" ? 2.5 : 1.8, class: "term-line", "data-term": k, "vector-effect": "non-scaling-stroke" }));
  }
  return h("section", { class: "card", id: "plot" }, h("h2", {}, "Convergence: every energy term per iteration (log scale)"), svg,
    h("div", { class: "legend" }, terms.map((k) => h("span", {}, h("i", { style: `background:${TERM_COLOURS[k] || "#777"}` }), k === "total" ? "total" : `E_${k}`))));
}

// ---------------------------------------------------------------- per-view images

function imagesSection(base, paths, views, viewSelect) {
  const kinds = [
    ["previews", "int", "I_int"], ["previews", "dop", "DoP"], ["previews", "aop", "AoP (hue) / DoP (saturation)"],
    ["residuals", "intensity", "observed − rendered (blue −, red +)"], ["residuals", "epol", "E_pol per pixel"],
  ];
  const grid = h("div", { class: "images", id: "view-images" });
  const urls = [];
  async function show() {
    const stem = viewSelect.value;
    urls.splice(0).forEach((u) => URL.revokeObjectURL(u));
    grid.replaceChildren(...kinds.map(([folder, kind, caption]) => {
      const path = `${folder}/${stem}_${kind}.png`;
      const img = h("img", { alt: `${caption} of view ${stem}`, "data-path": path });
      if (paths.has(path)) blobUrl(base + path).then((u) => { urls.push(u); img.src = u; });
      return h("figure", {}, img, h("figcaption", {}, caption));
    }));
  }
  viewSelect.addEventListener("change", show);
  const step = (d) => () => { viewSelect.selectedIndex = (viewSelect.selectedIndex + d + views.length) % views.length; viewSelect.dispatchEvent(new Event("change", { bubbles: true })); };
  show();
  return h("section", { class: "card" }, h("h2", {}, "Views"),
    h("div", { class: "toolbar" }, h("button", { class: "btn", type: "button", onclick: step(-1) }, "◀"),
      h("span", {}, "view (same choice as the lighting above)"), h("button", { class: "btn", type: "button", onclick: step(1) }, "▶")),
    grid);
}

// ---------------------------------------------------------------- routing

function route() {
  stopPolling();
  if (!apiKey()) { renderSignIn(); return; }
  signoutButton.hidden = false;
  const m = location.pathname.match(/^\/ui\/jobs\/([0-9a-f]{32})\/?$/);
  if (m) renderJob(m[1]); else renderJobs();
}

route();
