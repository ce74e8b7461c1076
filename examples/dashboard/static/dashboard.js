// evclock live dashboard: polls the JSON API, renders the state, plots the history with uPlot
// and sends the controls. No build step, no dependencies but the vendored uPlot.
"use strict";

const STATE_PERIOD_MS = 250;
const HISTORY_PERIOD_MS = 1000;
const SCENE_PERIOD_MS = 200; // the server renders at most its scene_fps whatever we ask
const COLORS = ["#2563eb", "#d92d20", "#039855", "#dc6803", "#7a5af8", "#0e9384"];

const $ = (id) => document.getElementById(id);
const controls = () => document.querySelectorAll(".controls button, .controls input");

let busy = 0; // control requests in flight (a pause may be sent while a step is)
let renders = 0; // counted in <body data-renders>: lets tests wait for fresh data
let lastState = null;
let generation = 0; // bumped by each control: polls sent before it are stale
const plots = { rtf: null, lateness: null, latenessNames: "" };

// ------------------------------------------------------------------ API

async function api(method, path, body) {
  const init = { method, headers: {} };
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  let data = null;
  try {
    data = await response.json();
  } catch (_) {
    data = null;
  }
  if (!response.ok) {
    const message = data && data.error ? data.error : `${response.status} ${response.statusText}`;
    const error = new Error(message);
    error.data = data;
    throw error;
  }
  return data;
}

function showError(message) {
  const box = $("error");
  box.textContent = message;
  box.hidden = !message;
}

// ------------------------------------------------------------ rendering

const seconds = (value) => (value == null ? "-" : `${value.toFixed(3)} s`);
const ms = (value) => (value == null ? "-" : `${(value * 1e3).toFixed(3)} ms`);
const factor = (value) => (value == null ? "-" : `${value.toFixed(value < 10 ? 3 : 1)}\u00d7`);

function tableRow(cells) {
  const row = document.createElement("tr");
  for (const value of cells) {
    const cell = document.createElement("td");
    cell.textContent = String(value);
    row.append(cell);
  }
  return row;
}

function renderLoops(loops) {
  const body = $("loops").tBodies[0];
  body.replaceChildren(
    ...loops.map((loop) => {
      const row = tableRow([
        loop.name, loop.hz, loop.policy, loop.ticks, loop.missed,
        ms(loop.mean_lateness_s), ms(loop.p50_lateness_s), ms(loop.p99_lateness_s),
        ms(loop.max_lateness_s), loop.run.ticks, loop.run.missed,
        ms(loop.run.mean_lateness_s), ms(loop.run.max_lateness_s),
      ]);
      row.dataset.loop = loop.name;
      return row;
    }),
  );
}

function renderEpisodes(episodes) {
  const body = $("episodes").tBodies[0];
  body.replaceChildren(
    ...episodes.map((episode) => tableRow([
      episode.number, episode.seed, episode.error || episode.outcome,
      seconds(episode.started_at_s), seconds(episode.ended_at_s), seconds(episode.duration_s),
    ])),
  );
}

function render(state) {
  $("scenario").textContent = `${state.scenario.name}: ${state.scenario.description}`;
  $("sim-time").textContent = `${state.sim_time_s.toFixed(6)} s`;
  $("physics-steps").textContent = String(state.physics_steps);
  const runState = $("run-state");
  const stepping = state.stepping;
  runState.textContent = stepping
    ? `stepping ${stepping.taken}/${stepping.count}`
    : state.paused ? "paused" : "running";
  runState.classList.toggle("paused", state.paused && !stepping);
  $("lockstep-overruns").textContent = String(state.lockstep_overruns);
  $("achieved-rtf").textContent = factor(state.achieved_rtf);
  $("requested-rtf").textContent = state.rtf == null ? "max" : factor(state.rtf);
  const episode = state.episode;
  $("episode").textContent = episode ? `#${episode.number} (seed ${episode.seed}) ${episode.outcome}` : "-";
  renderLoops(state.loops);
  renderEpisodes(state.finished_episodes);
  lastState = state;
  if (!busy) updateButtons(state);
  document.body.dataset.renders = String(++renders);
}

function updateButtons(state) {
  controls().forEach((element) => { element.disabled = false; });
  $("pause").disabled = state.paused;
  $("resume").disabled = !state.paused;
  $("step").disabled = !state.paused;
}

// ---------------------------------------------------------------- plots

// x: sim seconds (the history's sim_time_s: it never goes back, episode resets included).
function makePlot(element, labels, yLabel) {
  const series = [{ label: "sim time (s)", value: (_u, v) => (v == null ? "-" : v.toFixed(3)) }];
  labels.forEach((label, i) => {
    series.push({
      label,
      stroke: COLORS[i % COLORS.length],
      width: 2,
      value: (_u, v) => (v == null ? "-" : v.toFixed(3)),
    });
  });
  const options = {
    width: Math.max(element.clientWidth, 320),
    height: 240,
    scales: { x: { time: false } },
    axes: [{ label: "sim time (s)" }, { label: yLabel }],
    series,
  };
  element.replaceChildren();
  return new uPlot(options, [[], ...labels.map(() => [])], element);
}

function updatePlots(history) {
  const rtfElement = $("rtf-plot");
  if (!plots.rtf) plots.rtf = makePlot(rtfElement, ["achieved", "requested"], "sim s / wall s");
  plots.rtf.setData([history.sim_time_s, history.achieved_rtf, history.requested_rtf]);
  rtfElement.dataset.samples = String(history.wall_s.length);

  const names = Object.keys(history.lateness_ms);
  const latenessElement = $("lateness-plot");
  if (!plots.lateness || plots.latenessNames !== names.join("\u0000")) {
    if (plots.lateness) plots.lateness.destroy();
    plots.lateness = makePlot(latenessElement, names, "ms");
    plots.latenessNames = names.join("\u0000");
  }
  plots.lateness.setData([history.sim_time_s, ...names.map((name) => history.lateness_ms[name])]);
  latenessElement.dataset.samples = String(history.wall_s.length);
}

window.addEventListener("resize", () => {
  for (const [plot, id] of [[plots.rtf, "rtf-plot"], [plots.lateness, "lateness-plot"]]) {
    if (plot) plot.setSize({ width: Math.max($(id).clientWidth, 320), height: 240 });
  }
});

// -------------------------------------------------------------- polling

function poll(path, period, apply) {
  const tick = async () => {
    const sent = generation;
    try {
      const data = await api("GET", path);
      if (sent === generation) apply(data);
    } catch (error) {
      showError(`${path}: ${error.message}`);
    }
    setTimeout(tick, period);
  };
  tick();
}

// ---------------------------------------------------------------- scene

// Fetch the next frame once the previous one is shown; <img data-frame> counts frames.
async function refreshScene() {
  try {
    const response = await fetch("/api/scene.jpg", { cache: "no-store" });
    if (!response.ok) throw new Error(`${response.status} ${response.statusText}`);
    const frame = response.headers.get("X-Frame");
    const image = $("scene");
    if (frame !== image.dataset.frame) {
      const url = URL.createObjectURL(await response.blob());
      await new Promise((resolve, reject) => {
        image.onload = resolve;
        image.onerror = () => reject(new Error("the scene frame could not be decoded"));
        image.src = url;
      });
      if (image.dataset.url) URL.revokeObjectURL(image.dataset.url);
      image.dataset.url = url;
      image.dataset.frame = frame;
      image.dataset.steps = response.headers.get("X-Physics-Steps");
      const simTime = Number(response.headers.get("X-Sim-Time-Ns")) / 1e9;
      $("scene-time").textContent = `${simTime.toFixed(3)} s`;
    }
  } catch (error) {
    showError(`scene: ${error.message}`);
  }
  setTimeout(refreshScene, SCENE_PERIOD_MS);
}

// ------------------------------------------------------------- controls

async function control(path, body) {
  busy += 1;
  controls().forEach((element) => { element.disabled = true; });
  if (path === "/api/step") $("pause").disabled = false; // a pause cancels a long step
  try {
    const state = await api("POST", path, body);
    generation += 1;
    showError("");
    render(state);
  } catch (error) {
    const step = error.data && error.data.step;
    // A step the user interrupted (Pause) is no error: the state shows where it stopped.
    showError(step && step.reason === "interrupted" ? "" : error.message);
  } finally {
    busy -= 1;
    if (busy === 0) {
      if (lastState) updateButtons(lastState);
      else controls().forEach((element) => { element.disabled = false; });
    }
  }
}

function setRtf(text) {
  const value = text === "max" ? null : Number(text);
  control("/api/rtf", { rtf: value });
}

$("pause").addEventListener("click", () => control("/api/pause"));
$("resume").addEventListener("click", () => control("/api/resume"));
$("step").addEventListener("click", () => control("/api/step", { count: Number($("step-count").value) }));
$("rtf-set").addEventListener("click", () => setRtf($("rtf-input").value));
for (const button of document.querySelectorAll(".rtf-preset")) {
  button.addEventListener("click", () => {
    if (button.dataset.rtf !== "max") $("rtf-input").value = button.dataset.rtf;
    setRtf(button.dataset.rtf);
  });
}

// The page arrives with the state embedded: show it at once, then keep it fresh.
render(JSON.parse($("initial-state").textContent));
poll("/api/state", STATE_PERIOD_MS, render);
refreshScene();
poll("/api/history", HISTORY_PERIOD_MS, updatePlots);
