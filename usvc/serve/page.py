"""GET /: a small page to try the service: choose a map, drop a photo (or take one with a phone's
camera), see the answer (pose, confidence, warnings, timings, the raw JSON) and the camera drawn
in a 3D view of the map's points and mapping cameras (GET /v1/maps/{name}/scene).

The 3D view is plotly.js, served by the service itself (/static/plotly.min.js, from the `plotly`
package): nothing is fetched from elsewhere, and the page works offline. The shown pose values
carry stable ids (pose-center, pose-quat, pose-t, pose-confidence, ...) for tests.
"""

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>usvc serve</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<style>
body{font-family:system-ui,sans-serif;max-width:78rem;margin:1rem auto;padding:0 1rem;color:#222}
h1{margin:.2rem 0 .4rem;font-size:1.6rem} p{margin:.4rem 0}
.cols{display:grid;grid-template-columns:minmax(18rem,27rem) 1fr;gap:1rem;align-items:start}
@media (max-width:50rem){.cols{grid-template-columns:1fr}}
#drop{border:2px dashed #888;border-radius:8px;padding:1.2rem;text-align:center;margin:.6rem 0;cursor:pointer}
#drop.over{background:#eef}
pre{background:#f4f4f4;padding:.6rem;overflow:auto;max-height:22rem;font-size:.8rem;margin:.3rem 0}
label{margin-right:.6rem;display:inline-block;margin-bottom:.3rem} input[type=text],input[type=password]{width:8rem}
.button{border:1px solid #888;border-radius:4px;padding:.15rem .5rem;background:#f4f4f4;cursor:pointer}
table{border-collapse:collapse;width:100%;font-size:.9rem} td{padding:.2rem .3rem;border-bottom:1px solid #ddd;vertical-align:top}
td:first-child{color:#555;white-space:nowrap} td.num{font-family:ui-monospace,monospace}
#view{width:100%;height:36rem;border:1px solid #ddd;border-radius:6px}
.bad{color:#a00} .good{color:#060} .note{color:#555;font-size:.85rem}
</style></head><body>
<h1>usvc serve</h1>
<p>A photo's camera pose in a mapped place. API: <a href="docs">/docs</a>, <code>POST /v1/maps/NAME/localize</code>.</p>
<div class="cols"><div>
<p><label>Map <select id="map"></select></label>
<label>Focal (px, optional) <input id="focal" type="text" inputmode="decimal"></label></p>
<p><label>Token (if needed) <input id="token" type="password" autocomplete="off"></label>
<button id="reload" type="button">load maps</button></p>
<div id="drop">Drop a photo here, or click to choose one<input id="file" type="file" accept="image/*" hidden></div>
<p><label class="button">Take a photo (device camera)<input id="shoot" type="file" accept="image/*" capture="environment" hidden></label></p>
<p id="status"></p>
<table id="pose"><tbody>
<tr><td>photo</td><td id="pose-name"></td></tr>
<tr><td>position</td><td class="num" id="pose-center"></td></tr>
<tr><td>rotation q<br>(w x y z)</td><td class="num" id="pose-quat"></td></tr>
<tr><td>t</td><td class="num" id="pose-t"></td></tr>
<tr><td>confidence</td><td class="num" id="pose-confidence"></td></tr>
<tr><td>inliers / cells</td><td class="num" id="pose-inliers"></td></tr>
<tr><td>warnings</td><td id="pose-warnings"></td></tr>
<tr><td>seconds</td><td class="num" id="pose-seconds"></td></tr>
</tbody></table>
<p class="note">World to camera: x_cam = R x_world + t, q is R's quaternion; the position is the camera's centre, -R<sup>T</sup>t.</p>
</div><div>
<div id="view"></div><p class="note" id="scene-note"></p>
</div></div>
<details id="raw" open><summary>the answer's JSON</summary><pre id="out"></pre></details>
<script src="static/plotly.min.js"></script>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
let scene = null, answer = null;
function headers() { const t = $("token").value.trim(); return t ? {"Authorization": "Bearer " + t} : {}; }
function show(text, ok) { $("status").textContent = text; $("status").className = ok ? "good" : "bad"; }
const fixed = (v, d) => v.map((x) => Number(x).toFixed(d)).join(" ");
async function loadMaps() {
  try {
    const r = await fetch("v1/maps", {headers: headers()});
    const j = await r.json();
    if (!r.ok) { show(j.error || ("HTTP " + r.status), false); return; }
    const sel = $("map"); sel.replaceChildren();
    for (const m of j.maps) { const o = document.createElement("option"); o.value = m.name; o.textContent = m.name; sel.append(o); }
    show(j.maps.length + " map(s)", true);
    if (j.maps.length) await loadScene();
  } catch (e) { show(String(e), false); }
}
async function loadScene() {
  scene = null; answer = null; draw();
  try {
    const r = await fetch("v1/maps/" + encodeURIComponent($("map").value) + "/scene", {headers: headers()});
    const j = await r.json();
    if (!r.ok) { $("scene-note").textContent = "no 3D view: " + (j.error || ("HTTP " + r.status)); return; }
    scene = j; draw();
  } catch (e) { $("scene-note").textContent = "no 3D view: " + e; }
}
function rotation(q) {  // world-to-camera R of a unit (w, x, y, z) quaternion, as rows
  const [w, x, y, z] = q;
  return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
}
function frustum(rec, size) {  // the camera's pyramid: centre to the image corners at depth `size`
  const R = rotation(rec.q_wxyz), c = rec.camera_center, cam = rec.camera || {};
  const f = cam.params ? cam.params[0] : 1, hw = (cam.width || 4) / (2 * f), hh = (cam.height || 3) / (2 * f);
  const at = (u, v) => [0, 1, 2].map((i) => c[i] + size * (u * R[0][i] + v * R[1][i] + R[2][i]));
  const k = [at(-hw, -hh), at(hw, -hh), at(hw, hh), at(-hw, hh)];
  const path = [c, k[0], k[1], c, k[2], k[3], c, null, k[0], k[3], null, k[1], k[2]];
  const pick = (i) => path.map((p) => p === null ? null : p[i]);
  return {x: pick(0), y: pick(1), z: pick(2)};
}
function draw() {
  if (typeof Plotly === "undefined") { $("scene-note").textContent = "no 3D view: plotly.js did not load"; return; }
  const traces = [], radius = (scene && scene.radius) || 1;
  if (scene) {
    const p = scene.points;
    traces.push({type: "scatter3d", mode: "markers", name: "map points (" + p.shown + " of " + p.total + ")", x: p.x, y: p.y, z: p.z,
                 marker: {size: 1.5, color: "#888", opacity: 0.6}, hoverinfo: "skip"});
    const c = scene.cameras;
    if (c.centers.length) {
      const lx = [], ly = [], lz = [], s = 0.15 * radius;
      c.centers.forEach((o, i) => { const d = c.forward[i]; lx.push(o[0], o[0] + s * d[0], null); ly.push(o[1], o[1] + s * d[1], null); lz.push(o[2], o[2] + s * d[2], null); });
      traces.push({type: "scatter3d", mode: "lines+markers", name: "mapping cameras (" + c.total + ")", x: lx, y: ly, z: lz,
                   line: {color: "#3b6fd8", width: 2}, marker: {size: 2, color: "#3b6fd8"}, hoverinfo: "skip"});
    }
    $("scene-note").textContent = p.total + " points (" + p.source + ", " + p.shown + " shown), " + c.total + " mapping cameras" + (c.source ? " (" + c.source + ")" : "");
  }
  if (answer && answer.success) {
    const f = frustum(answer, 0.25 * radius);
    traces.push({type: "scatter3d", mode: "lines", name: "localized camera", x: f.x, y: f.y, z: f.z, line: {color: "#e0301e", width: 6}, hoverinfo: "skip"});
    const c = answer.camera_center;
    traces.push({type: "scatter3d", mode: "markers", name: "camera centre", x: [c[0]], y: [c[1]], z: [c[2]], marker: {size: 6, color: "#e0301e"},
                 text: [answer.name || "photo"], hoverinfo: "text+x+y+z"});
  }
  const up = scene && scene.up ? {x: scene.up[0], y: scene.up[1], z: scene.up[2]} : {x: 0, y: 0, z: 1};
  const layout = {margin: {l: 0, r: 0, t: 0, b: 0}, showlegend: true, legend: {x: 0, y: 1, bgcolor: "rgba(255,255,255,0.7)"},
                  uirevision: scene ? scene.name : "none",
                  scene: {aspectmode: "data", camera: {up: up}, xaxis: {title: {text: "x"}}, yaxis: {title: {text: "y"}}, zaxis: {title: {text: "z"}}}};
  Plotly.react("view", traces, layout, {displaylogo: false, responsive: true});
}
function showPose(rec) {
  const ok = rec && rec.success;
  $("pose-name").textContent = rec ? (rec.name || "") : "";
  $("pose-center").textContent = ok ? fixed(rec.camera_center, 4) : "";
  $("pose-quat").textContent = ok ? fixed(rec.q_wxyz, 5) : "";
  $("pose-t").textContent = ok ? fixed(rec.t, 4) : "";
  $("pose-confidence").textContent = rec && rec.confidence !== undefined ? Number(rec.confidence).toFixed(4) : "";
  $("pose-inliers").textContent = rec && rec.inliers !== undefined ? rec.inliers + " / " + rec.cells : "";
  const w = $("pose-warnings"); w.replaceChildren();
  const notes = (rec && rec.warnings) || [];
  if (rec && rec.rejected) notes.unshift("refused: " + rec.rejected);
  if (!notes.length && rec) w.textContent = "none";
  for (const n of notes) { const d = document.createElement("div"); d.textContent = n; w.append(d); }
  const s = (rec && rec.seconds) || {};
  $("pose-seconds").textContent = Object.keys(s).map((k) => k + " " + Number(s[k]).toFixed(3)).join(", ");
}
async function send(file) {
  const form = new FormData(); form.append("photo", file, file.name);
  const f = $("focal").value.trim(); if (f) form.append("focal", f);
  show("localizing " + file.name + " ...", true); $("out").textContent = ""; answer = null; showPose(null);
  const t0 = performance.now();
  try {
    const r = await fetch("v1/maps/" + encodeURIComponent($("map").value) + "/localize", {method: "POST", body: form, headers: headers()});
    const j = await r.json();
    const ms = Math.round(performance.now() - t0);
    show(r.ok ? ("pose found in " + ms + " ms") : ("HTTP " + r.status + ": " + (j.error || "")), r.ok);
    $("out").textContent = JSON.stringify(j, null, 2);
    answer = r.ok ? j : (j.record || null);
    showPose(answer); draw();
  } catch (e) { show(String(e), false); }
}
$("reload").onclick = loadMaps;
$("map").onchange = loadScene;
$("drop").onclick = () => $("file").click();
function picked(e) { const file = e.target.files[0]; e.target.value = ""; if (file) send(file); }  // the same file again: a new change
$("file").onchange = picked;
$("shoot").onchange = picked;
$("drop").ondragover = (e) => { e.preventDefault(); $("drop").classList.add("over"); };
$("drop").ondragleave = () => $("drop").classList.remove("over");
$("drop").ondrop = (e) => { e.preventDefault(); $("drop").classList.remove("over"); if (e.dataTransfer.files[0]) send(e.dataTransfer.files[0]); };
loadMaps();
</script></body></html>
"""
