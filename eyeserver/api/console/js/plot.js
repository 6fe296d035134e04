// The eye's deviation from its reference over time, drawn on a <canvas>: ΔX, ΔY, ΔZ (mm) and
// the gaze angle (degrees), each in its own strip with the patient's tolerance drawn as a band,
// and the beam hold as a red bar under them.
//
// The verdict is on the length of (ΔX, ΔY, ΔZ) against tolerance_mm; the band on each axis is
// that same tolerance, so a point outside it is out of tolerance whatever the other axes say.

const STRIPS = [
  {key: 0, label: "ΔX", unit: "mm"},
  {key: 1, label: "ΔY", unit: "mm"},
  {key: 2, label: "ΔZ", unit: "mm"},
  {key: "gaze", label: "gaze", unit: "°"},
];
const COLOURS = {
  band: "rgba(46, 160, 67, 0.18)", edge: "rgba(46, 160, 67, 0.8)", line: "#4aa3ff",
  outside: "#ff5c5c", axis: "#5b6675", text: "#c8d1dc", hold: "#e5484d", clear: "#2ea043",
};

export class DeviationPlot {
  /** `canvas`: the element to draw on; `windowS`: how many seconds are shown. */
  constructor(canvas, {windowS = 30} = {}) {
    this.canvas = canvas;
    this.windowMs = windowS * 1000;
    this.samples = [];
    this.toleranceMm = null;
    this.toleranceDeg = null;
    this.pending = false;
  }

  setTolerance(mm, deg) {
    this.toleranceMm = mm;
    this.toleranceDeg = deg;
    this.schedule();
  }

  clear() {
    this.samples = [];
    this.schedule();
  }

  /** A sample at `timeMs` (Date.now()): delta_mm [x, y, z] or null, gaze_deg or null, hold. */
  push(sample) {
    this.samples.push(sample);
    const oldest = sample.timeMs - this.windowMs;
    while (this.samples.length && this.samples[0].timeMs < oldest) this.samples.shift();
    this.schedule();
  }

  schedule() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => {
      this.pending = false;
      this.draw();
    });
  }

  draw() {
    const canvas = this.canvas;
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth || 600;
    const height = canvas.clientHeight || 320;
    if (canvas.width !== Math.round(width * ratio)) canvas.width = Math.round(width * ratio);
    if (canvas.height !== Math.round(height * ratio)) canvas.height = Math.round(height * ratio);
    const g = canvas.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.clearRect(0, 0, width, height);
    g.font = "12px system-ui, sans-serif";

    const left = 58;
    const right = width - 10;
    const holdBar = 10;
    const top = 6;
    const bottom = height - 22 - holdBar;
    const stripHeight = (bottom - top) / STRIPS.length;
    const now = Date.now();
    const x = (t) => right - ((now - t) / this.windowMs) * (right - left);

    STRIPS.forEach((strip, index) => {
      const y0 = top + index * stripHeight + 4;
      const y1 = y0 + stripHeight - 8;
      const isGaze = strip.key === "gaze";
      const tolerance = isGaze ? this.toleranceDeg : this.toleranceMm;
      const values = this.samples.map((s) => (isGaze ? s.gaze_deg : s.delta_mm?.[strip.key]))
        .filter((v) => typeof v === "number" && Number.isFinite(v));
      const extreme = Math.max(tolerance ? 2 * tolerance : isGaze ? 2 : 0.5,
        ...values.map(Math.abs)) * 1.1;
      const low = isGaze ? 0 : -extreme;
      const y = (v) => y1 - ((v - low) / (extreme - low)) * (y1 - y0);

      g.strokeStyle = COLOURS.axis;
      g.lineWidth = 1;
      g.strokeRect(left, y0, right - left, y1 - y0);
      if (tolerance) {
        g.fillStyle = COLOURS.band;
        const bandTop = y(tolerance);
        const bandBottom = y(isGaze ? 0 : -tolerance);
        g.fillRect(left, bandTop, right - left, bandBottom - bandTop);
        g.strokeStyle = COLOURS.edge;
        g.setLineDash([4, 3]);
        for (const edge of isGaze ? [tolerance] : [tolerance, -tolerance]) {
          g.beginPath();
          g.moveTo(left, y(edge));
          g.lineTo(right, y(edge));
          g.stroke();
        }
        g.setLineDash([]);
      }
      if (!isGaze) {
        g.strokeStyle = COLOURS.axis;
        g.beginPath();
        g.moveTo(left, y(0));
        g.lineTo(right, y(0));
        g.stroke();
      }
      g.fillStyle = COLOURS.text;
      g.fillText(`${strip.label} ${strip.unit}`, 4, (y0 + y1) / 2 + 4);
      g.fillStyle = COLOURS.axis;
      g.fillText(`${isGaze ? "" : "±"}${extreme.toFixed(isGaze ? 1 : 2)}`, left + 4, y0 + 12);

      let previous = null;
      for (const sample of this.samples) {
        const v = isGaze ? sample.gaze_deg : sample.delta_mm?.[strip.key];
        if (typeof v !== "number" || !Number.isFinite(v)) {
          previous = null;
          continue;
        }
        const point = [x(sample.timeMs), y(v)];
        const outside = tolerance && Math.abs(v) > tolerance;
        g.strokeStyle = outside ? COLOURS.outside : COLOURS.line;
        g.fillStyle = g.strokeStyle;
        if (previous) {
          g.beginPath();
          g.moveTo(...previous);
          g.lineTo(...point);
          g.stroke();
        } else {
          g.fillRect(point[0] - 1, point[1] - 1, 2, 2);
        }
        previous = point;
      }
    });

    // The beam hold along the time axis: red while held, green while clear.
    const barTop = bottom + 2;
    for (let i = 0; i < this.samples.length; i += 1) {
      const sample = this.samples[i];
      const next = this.samples[i + 1]?.timeMs ?? now;
      g.fillStyle = sample.hold ? COLOURS.hold : COLOURS.clear;
      g.fillRect(x(sample.timeMs), barTop, Math.max(1, x(next) - x(sample.timeMs)), holdBar);
    }
    g.fillStyle = COLOURS.text;
    g.fillText("beam", 4, barTop + holdBar);
    const seconds = this.windowMs / 1000;
    for (let s = 0; s <= seconds; s += 5) {
      const tx = x(now - s * 1000);
      g.fillText(s === 0 ? "now" : `−${s} s`, tx - (s === 0 ? 24 : 14), height - 4);
    }
  }
}
