"""GET /: a small page to try the service: choose a map, drop a photo, see the answer."""

PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>usvc serve</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,sans-serif;max-width:52rem;margin:2rem auto;padding:0 1rem;color:#222}
#drop{border:2px dashed #888;border-radius:8px;padding:2rem;text-align:center;margin:1rem 0;cursor:pointer}
#drop.over{background:#eef}
pre{background:#f4f4f4;padding:1rem;overflow:auto;max-height:32rem}
label{margin-right:1rem} input[type=text],input[type=password]{width:14rem}
.bad{color:#a00} .good{color:#060}
</style></head><body>
<h1>usvc serve</h1>
<p>A photo's camera pose in a mapped place. API: <a href="docs">/docs</a>, <code>POST /v1/maps/NAME/localize</code>.</p>
<p><label>Map <select id="map"></select></label>
<label>Focal (px, optional) <input id="focal" type="text" inputmode="decimal"></label></p>
<p><label>Token (if the server needs one) <input id="token" type="password" autocomplete="off"></label>
<button id="reload" type="button">load maps</button></p>
<div id="drop">Drop a photo here, or click to choose one<input id="file" type="file" accept="image/*" hidden></div>
<p id="status"></p><pre id="out"></pre>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
function headers() { const t = $("token").value.trim(); return t ? {"Authorization": "Bearer " + t} : {}; }
function show(text, ok) { $("status").textContent = text; $("status").className = ok ? "good" : "bad"; }
async function loadMaps() {
  try {
    const r = await fetch("v1/maps", {headers: headers()});
    const j = await r.json();
    if (!r.ok) { show(j.error || ("HTTP " + r.status), false); return; }
    const sel = $("map"); sel.replaceChildren();
    for (const m of j.maps) { const o = document.createElement("option"); o.value = m.name; o.textContent = m.name; sel.append(o); }
    show(j.maps.length + " map(s)", true);
  } catch (e) { show(String(e), false); }
}
async function send(file) {
  const form = new FormData(); form.append("photo", file, file.name);
  const f = $("focal").value.trim(); if (f) form.append("focal", f);
  show("localizing " + file.name + " ...", true); $("out").textContent = "";
  const t0 = performance.now();
  try {
    const r = await fetch("v1/maps/" + encodeURIComponent($("map").value) + "/localize", {method: "POST", body: form, headers: headers()});
    const j = await r.json();
    const ms = Math.round(performance.now() - t0);
    show(r.ok ? ("pose found in " + ms + " ms") : ("HTTP " + r.status + ": " + (j.error || "")), r.ok);
    $("out").textContent = JSON.stringify(j, null, 2);
  } catch (e) { show(String(e), false); }
}
$("reload").onclick = loadMaps;
$("drop").onclick = () => $("file").click();
$("file").onchange = (e) => { if (e.target.files[0]) send(e.target.files[0]); };
$("drop").ondragover = (e) => { e.preventDefault(); $("drop").classList.add("over"); };
$("drop").ondragleave = () => $("drop").classList.remove("over");
$("drop").ondrop = (e) => { e.preventDefault(); $("drop").classList.remove("over"); if (e.dataTransfer.files[0]) send(e.dataTransfer.files[0]); };
loadMaps();
</script></body></html>
"""
