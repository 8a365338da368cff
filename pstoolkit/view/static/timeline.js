// Scrubbing the capture: a slider over its time span (or its frames, when each frame has its own
// light); at each position the frame whose exposure covers t, the events of a window around t and
// the result rendered under the light at t, which the server computes from the capture's light
// model. Requests are coalesced: while one position loads, moves only remember the latest.

import { drawRGB, showAt } from "./maps.js";

function ms(us) {
  return `${(us / 1000).toFixed(1)} ms`;
}

function vector(v) {
  return `(${v.map((x) => x.toFixed(2)).join(", ")})`;
}

export class Timeline {
  // info: index.capture; els: the section's elements by id; predict(light, intensity): draws the
  // prediction; fetchOk(url): a fetch that throws unless the answer is 200.
  constructor(info, els, predict, fetchOk) {
    this.info = info;
    this.els = els;
    this.predict = predict;
    this.fetchOk = fetchOk;
    this.byFrame = info.mode === "frames";
    this.frameShown = null;
    this.busy = null;
    this.pending = false;
    const slider = els.time;
    if (this.byFrame) {
      slider.min = "0";
      slider.max = String(info.frames.count - 1);
      slider.step = "1";
    } else {
      const [t0, t1] = info.span_us;
      slider.min = String(t0);
      slider.max = String(t1 - 1);
      slider.step = String(Math.max(1, Math.round((t1 - t0) / 4000)));
    }
    els.window.value = String(info.window_us / 1000);
    els["window-label"].hidden = !info.events;
    slider.addEventListener("input", () => this.update());
    els.window.addEventListener("change", () => this.update());
  }

  // Move to t (µs, or a frame index) given by the page's URL, else to the middle of the first
  // exposure (or of the span).
  start(position) {
    const slider = this.els.time;
    let value = position === null || position === "" ? NaN : Number(position);
    if (!Number.isFinite(value)) {
      const windows = this.info.frames && this.info.frames.windows;
      if (this.byFrame) value = 0;
      else if (windows && windows.length) value = Math.floor((windows[0][0] + windows[0][1]) / 2);
      else value = Math.floor((this.info.span_us[0] + this.info.span_us[1]) / 2);
    }
    slider.value = String(value);
    return this.update();
  }

  // Load and draw the slider's position; resolves once the latest position is drawn.
  update() {
    if (this.busy) {
      this.pending = true;
      return this.busy;
    }
    this.busy = (async () => {
      try {
        do {
          this.pending = false;
          await this._show(Math.round(Number(this.els.time.value)));
        } while (this.pending);
      } finally {
        this.busy = null;
      }
    })();
    return this.busy;
  }

  async _show(position) {
    const els = this.els;
    const query = this.byFrame ? `frame=${position}` : `t=${position}`;
    const at = await (await this.fetchOk(`/capture/at?${query}`)).json();
    els["time-out"].textContent = this.byFrame ? `frame ${position + 1} of ${this.info.frames.count}` : ms(position - this.info.span_us[0]);
    const frames = this.info.frames;
    if (frames && at.frame !== null && at.frame !== this.frameShown) {
      const bytes = new Uint8Array(await (await this.fetchOk(`/capture/frame/${at.frame}.rgb`)).arrayBuffer());
      drawRGB(els.frame, bytes, frames.width, frames.height);
      showAt(els.frame, frames.width, frames.height, 256);
      this.frameShown = at.frame;
    }
    if (frames && at.frame === null) {
      els["frame-caption"].textContent = "no exposure covers this time";
    } else if (frames) {
      const win = frames.windows ? frames.windows[at.frame] : null;
      const span = win ? ` · exposure ${ms(win[0] - this.info.span_us[0])}–${ms(win[1] - this.info.span_us[0])}` : "";
      els["frame-caption"].textContent = `frame ${at.frame + 1} of ${frames.count}${span}`;
    } else {
      els["frame-caption"].textContent = "the capture has no frames";
    }
    const events = this.info.events;
    if (events && !this.byFrame) {
      const width = Math.max(100, Math.round(Number(els.window.value) * 1000) || this.info.window_us);
      const t0 = position - Math.floor(width / 2);
      const url = `/capture/events.rgb?t0=${t0}&t1=${t0 + width}`;
      const bytes = new Uint8Array(await (await this.fetchOk(url)).arrayBuffer());
      drawRGB(els.events, bytes, events.width, events.height);
      showAt(els.events, events.width, events.height, 256);
      els["events-caption"].textContent = `events ${ms(t0 - this.info.span_us[0])}–${ms(t0 + width - this.info.span_us[0])} · red positive, blue negative`;
    } else {
      els["events-caption"].textContent = "no events";
    }
    if (at.light) {
      this.predict(at.light, at.intensity || [1, 1, 1]);
      els["prediction-caption"].textContent = `result under the capture's light ${vector(at.light)}`;
    } else {
      els["prediction-caption"].textContent = "no light known at this time: no prediction";
    }
  }
}
