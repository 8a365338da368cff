// The viewer page: loads /data/index.json and the maps, draws the maps, relights the surface under
// the light dragged on the disc, scrubs the capture and turns the depth map. Every string from the
// server comes from files (result.json, a capture), so it goes into the page as text
// (textContent), never parsed as markup.
//
// URL parameters: view=all|relight|orbit (relight, orbit: only that canvas, 1:1 at the top left,
// for screenshots), light=x,y,z (start light, normalised), exposure=GAIN (absolute display gain),
// t=US (or a frame index: the capture's start position), yaw=DEG and pitch=DEG (the surface's
// start angles). Once everything shown is drawn, the page sets data-ready on <html> and fetches
// /ready?ms=… (milliseconds since navigation began).

import { drawMap, showAt } from "./maps.js";
import { Orbit } from "./orbit.js";
import { parseLight, Shader } from "./shading.js";
import { Timeline } from "./timeline.js";

const params = new URLSearchParams(location.search);
const DEG = Math.PI / 180;

function report(message) {
  fetch(`/log?error=${encodeURIComponent(String(message).slice(0, 400))}`).catch(() => {});
}
window.addEventListener("error", (e) => report(e.message));
window.addEventListener("unhandledrejection", (e) => report(e.reason && e.reason.message ? e.reason.message : e.reason));

async function fetchOk(url) {
  const answer = await fetch(url);
  if (!answer.ok) throw new Error(`${url}: HTTP ${answer.status}`);
  return answer;
}

async function floats(url, count) {
  const buffer = await (await fetchOk(url)).arrayBuffer();
  if (buffer.byteLength !== 4 * count) throw new Error(`${url}: ${buffer.byteLength} bytes, expected ${4 * count}`);
  return new Float32Array(buffer);
}

function element(tag, text) {
  const e = document.createElement(tag);
  if (text !== undefined) e.textContent = String(text);
  return e;
}

function number(text, fallback) {
  const v = text === null ? NaN : Number(text);
  return Number.isFinite(v) ? v : fallback;
}

function byId(ids) {
  return Object.fromEntries(ids.map((id) => [id, document.getElementById(id)]));
}

// renderMs: how long one relighting of the whole image took (what a drag of the light costs)
function signalReady(renderMs) {
  document.documentElement.dataset.ready = "1";
  return fetch(`/ready?ms=${performance.now().toFixed(1)}&render_ms=${renderMs.toFixed(2)}`).catch(() => {});
}

function describe(index) {
  document.title = `${index.label} · pstoolkit view`;
  document.getElementById("title").textContent = index.label;
  document.getElementById("status").textContent = `${index.width}×${index.height} · maps: ${index.order.join(", ")}`;
  const notes = document.getElementById("notes");
  for (const note of index.notes) notes.append(element("li", note));
  const table = document.getElementById("info");
  const rows = [...Object.entries(index.info), ...Object.entries(index.options).map(([k, v]) => [`option ${k}`, v])];
  if (index.capture) rows.push(["capture scrubbed", index.capture.path], ["light model", index.capture.light_model ?? "none"]);
  for (const [key, value] of rows) {
    const tr = element("tr");
    tr.append(element("td", key), element("td", typeof value === "number" ? Number(value.toPrecision(6)) : value));
    table.append(tr);
  }
}

function panels(index, maps, mask) {
  const row = document.getElementById("maps");
  for (const name of index.order) {
    const figure = element("figure");
    const canvas = element("canvas");
    drawMap(canvas, maps[name], name, mask, index.colormap);
    showAt(canvas, index.width, index.height, 192);
    const caption = element("figcaption", name);
    if (maps[name].png) {
      const link = element("a", "PNG");
      link.href = maps[name].png;
      caption.append(" · ", link);
    }
    figure.append(canvas, caption);
    row.append(figure);
  }
}

// The light disc: the light's (x, y) seen from the camera; dragging sets z = sqrt(1 - x² - y²).
function lightDisc(canvas, state, changed) {
  const ctx = canvas.getContext("2d");
  const c = canvas.width / 2;
  const r = c - 8;
  let dragging = false;
  function draw() {
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = "#1d1d22";
    ctx.beginPath();
    ctx.arc(c, c, r, 0, 2 * Math.PI);
    ctx.fill();
    ctx.strokeStyle = "#445";
    ctx.beginPath();
    ctx.moveTo(c - r, c);
    ctx.lineTo(c + r, c);
    ctx.moveTo(c, c - r);
    ctx.lineTo(c, c + r);
    ctx.stroke();
    ctx.fillStyle = "#ffd45a";
    ctx.beginPath();
    ctx.arc(c + state.light[0] * r, c - state.light[1] * r, 6, 0, 2 * Math.PI);
    ctx.fill();
  }
  function move(e) {
    const box = canvas.getBoundingClientRect();
    let x = (((e.clientX - box.left) * canvas.width) / box.width - c) / r;
    let y = (c - ((e.clientY - box.top) * canvas.height) / box.height) / r;
    const radius = Math.hypot(x, y);
    if (radius > 0.999) {
      x *= 0.999 / radius;
      y *= 0.999 / radius;
    }
    state.light = [x, y, Math.sqrt(Math.max(0, 1 - x * x - y * y))];
    draw();
    changed();
  }
  canvas.addEventListener("pointerdown", (e) => {
    dragging = true;
    canvas.setPointerCapture(e.pointerId);
    move(e);
  });
  canvas.addEventListener("pointermove", (e) => dragging && move(e));
  canvas.addEventListener("pointerup", () => {
    dragging = false;
  });
  draw();
}

async function main() {
  const index = await (await fetchOk("/data/index.json")).json();
  const maps = {};
  await Promise.all(
    index.order.map(async (name) => {
      const m = index.maps[name];
      maps[name] = { ...m, data: await floats(m.url, m.shape[0] * m.shape[1] * m.shape[2]) };
    }),
  );
  const shader = new Shader(index, maps);
  const state = { light: parseLight(params.get("light")) || [0, 0, 1], exposure: number(params.get("exposure"), index.exposure) };
  const relit = document.getElementById("relight");
  relit.width = index.width;
  relit.height = index.height;
  const context = relit.getContext("2d");
  const image = context.createImageData(index.width, index.height);
  let orbit = null;
  let renderMs = 0;
  const draw = () => {
    const e = state.exposure;
    const started = performance.now();
    shader.render(image, state.light, [e, e, e]);
    renderMs = performance.now() - started;
    context.putImageData(image, 0, 0);
    if (orbit) orbit.render(image.data);
    document.getElementById("light-out").textContent = `light (${state.light.map((v) => v.toFixed(2)).join(", ")})`;
  };
  const yaw = number(params.get("yaw"), 30) * DEG;
  const pitch = number(params.get("pitch"), 20) * DEG;
  const only = params.get("view");
  if (only === "relight" || (only === "orbit" && maps.depth)) {
    // one canvas, 1:1 at the top left of a black page: what the screenshot tests compare
    const started = performance.now();
    shader.render(image, state.light, [state.exposure, state.exposure, state.exposure]);
    renderMs = performance.now() - started;
    context.putImageData(image, 0, 0);
    let canvas = relit;
    if (only === "orbit") {
      canvas = document.getElementById("orbit");
      new Orbit(canvas, maps.depth, shader.mask, yaw, pitch).render(image.data);
    }
    document.body.className = "bare";
    document.body.replaceChildren(canvas);
    canvas.style.width = `${canvas.width}px`;
    canvas.style.height = `${canvas.height}px`;
    await signalReady(renderMs);
    return;
  }
  describe(index);
  panels(index, maps, shader.mask);
  showAt(relit, index.width, index.height, 320);
  document.getElementById("brdf").textContent =
    index.brdf === "ggx" ? "GGX: diffuse albedo + specular lobe (F0, roughness)" : "Lambertian (no F0 and roughness maps)";
  if (maps.depth) {
    document.getElementById("orbit-section").hidden = false;
    orbit = new Orbit(document.getElementById("orbit"), maps.depth, shader.mask, yaw, pitch);
  }
  let queued = false;
  let predicted = null;
  const prediction = document.getElementById("prediction");
  prediction.width = index.width;
  prediction.height = index.height;
  showAt(prediction, index.width, index.height, 256);
  const predictionImage = prediction.getContext("2d").createImageData(index.width, index.height);
  const predict = (light, intensity) => {
    predicted = [light, intensity];
    shader.render(predictionImage, light, intensity.map((v) => v * state.exposure));
    prediction.getContext("2d").putImageData(predictionImage, 0, 0);
  };
  const changed = () => {
    if (queued) return;
    queued = true;
    requestAnimationFrame(() => {
      queued = false;
      draw();
      if (predicted) predict(...predicted);
    });
  };
  lightDisc(document.getElementById("disc"), state, changed);
  const exposure = document.getElementById("exposure");
  exposure.value = String(Math.log2(state.exposure / index.exposure));
  exposure.addEventListener("input", () => {
    state.exposure = index.exposure * 2 ** Number(exposure.value);
    changed();
  });
  draw();
  const capture = index.capture;
  if (capture && capture.mode !== "none") {
    document.getElementById("timeline-section").hidden = false;
    const ids = ["time", "time-out", "window", "window-label", "frame", "frame-caption", "events", "events-caption", "prediction-caption"];
    const timeline = new Timeline(capture, byId(ids), predict, fetchOk);
    await timeline.start(params.get("t"));
  }
  await signalReady(renderMs);
}

main().catch((e) => {
  const status = document.getElementById("status");
  if (status) status.textContent = `failed: ${e.message}`;
  report(e.message);
});
