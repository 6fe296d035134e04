// A reconstruction's point cloud in the browser: the daemon's binary PLY (FORMATS.md: float32
// x y z in WCS mm, then quality and camera where known) parsed here, drawn on a <canvas> with
// a depth buffer, turned with the mouse and zoomed with the wheel.

const TYPES = {
  char: [1, "getInt8"], int8: [1, "getInt8"], uchar: [1, "getUint8"], uint8: [1, "getUint8"],
  short: [2, "getInt16"], int16: [2, "getInt16"], ushort: [2, "getUint16"],
  uint16: [2, "getUint16"], int: [4, "getInt32"], int32: [4, "getInt32"],
  uint: [4, "getUint32"], uint32: [4, "getUint32"], float: [4, "getFloat32"],
  float32: [4, "getFloat32"], double: [8, "getFloat64"], float64: [8, "getFloat64"],
};

/**
 * The vertices of a binary little-endian PLY: {count, points: Float32Array of x y z, taken}
 * keeping at most `maxPoints` of them, evenly spread over the file.
 */
export function parsePly(buffer, maxPoints = 60000) {
  const head = new TextDecoder("ascii").decode(new Uint8Array(buffer, 0,
    Math.min(buffer.byteLength, 4096)));
  const end = head.indexOf("end_header\n");
  if (!head.startsWith("ply\n") || end < 0) throw new Error("not a PLY file");
  const lines = head.slice(0, end).split("\n").map((l) => l.trim());
  if (!lines.includes("format binary_little_endian 1.0")) {
    throw new Error("not a binary little-endian PLY");
  }
  let count = 0;
  let inVertex = false;
  const properties = [];
  for (const line of lines) {
    const words = line.split(/\s+/);
    if (words[0] === "element") {
      if (inVertex) break; // the vertex element's properties end here
      inVertex = words[1] === "vertex";
      if (!inVertex && count === 0 && properties.length === 0) {
        throw new Error("the PLY's first element is not its vertices");
      }
      if (inVertex) count = Number(words[2]);
    } else if (words[0] === "property" && inVertex) {
      if (words[1] === "list") throw new Error("list properties on vertices are not read");
      const type = TYPES[words[1]];
      if (!type) throw new Error(`unknown PLY type ${words[1]}`);
      properties.push({name: words[2], size: type[0], read: type[1]});
    }
  }
  let stride = 0;
  const offsets = {};
  for (const p of properties) {
    offsets[p.name] = {offset: stride, read: p.read};
    stride += p.size;
  }
  for (const axis of ["x", "y", "z"]) {
    if (!offsets[axis]) throw new Error(`the PLY's vertices have no ${axis}`);
  }
  const start = end + "end_header\n".length;
  const view = new DataView(buffer, start);
  const available = Math.min(count, Math.floor(view.byteLength / Math.max(stride, 1)));
  const step = Math.max(1, Math.ceil(available / maxPoints));
  const taken = Math.ceil(available / step);
  const points = new Float32Array(taken * 3);
  let k = 0;
  for (let i = 0; i < available; i += step) {
    const base = i * stride;
    points[k++] = view[offsets.x.read](base + offsets.x.offset, true);
    points[k++] = view[offsets.y.read](base + offsets.y.offset, true);
    points[k++] = view[offsets.z.read](base + offsets.z.offset, true);
  }
  return {count, points: points.subarray(0, k), taken: k / 3};
}

/** Blue (low) → cyan → green → yellow → red (high), like the daemon's height map. */
function colour(t) {
  const stops = [[48, 18, 59], [40, 140, 230], [30, 210, 140], [165, 230, 50], [250, 180, 40],
    [200, 40, 20]];
  const x = Math.min(0.9999, Math.max(0, t)) * (stops.length - 1);
  const i = Math.floor(x);
  const f = x - i;
  return stops[i].map((c, j) => Math.round(c + (stops[i + 1][j] - c) * f));
}

export class PointView {
  /** Draws `cloud` (parsePly's) on `canvas`; drag to turn, wheel to zoom. */
  constructor(canvas) {
    this.canvas = canvas;
    this.cloud = null;
    this.yaw = 0.5;
    this.pitch = -0.6;
    this.zoom = 1;
    this.pending = false;
    let dragging = null;
    canvas.addEventListener("pointerdown", (e) => {
      dragging = [e.clientX, e.clientY];
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!dragging) return;
      this.yaw += (e.clientX - dragging[0]) * 0.01;
      this.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2,
        this.pitch + (e.clientY - dragging[1]) * 0.01));
      dragging = [e.clientX, e.clientY];
      this.schedule();
    });
    const release = () => {
      dragging = null;
    };
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      this.zoom = Math.max(0.2, Math.min(20, this.zoom * (e.deltaY < 0 ? 1.15 : 1 / 1.15)));
      this.schedule();
    }, {passive: false});
  }

  show(cloud) {
    this.cloud = cloud;
    const p = cloud.points;
    const low = [Infinity, Infinity, Infinity];
    const high = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < p.length; i += 3) {
      for (let a = 0; a < 3; a += 1) {
        low[a] = Math.min(low[a], p[i + a]);
        high[a] = Math.max(high[a], p[i + a]);
      }
    }
    this.centre = low.map((l, a) => (l + high[a]) / 2);
    this.radius = Math.max(1e-6, ...high.map((h, a) => (h - low[a]) / 2));
    this.zRange = [low[2], high[2]];
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
    const width = canvas.clientWidth || 480;
    const height = canvas.clientHeight || 360;
    canvas.width = width;
    canvas.height = height;
    const g = canvas.getContext("2d");
    g.fillStyle = "#0b0f14";
    g.fillRect(0, 0, width, height);
    if (!this.cloud || this.cloud.taken === 0) return;
    // Drawn into a fresh image (no read back from the canvas), the background filled in.
    const image = g.createImageData(width, height);
    const pixels = image.data;
    for (let i = 0; i < pixels.length; i += 4) {
      pixels[i] = 11;
      pixels[i + 1] = 15;
      pixels[i + 2] = 20;
      pixels[i + 3] = 255;
    }
    const depth = new Float32Array(width * height).fill(Infinity);
    const [cy, sy, cp, sp] = [Math.cos(this.yaw), Math.sin(this.yaw), Math.cos(this.pitch),
      Math.sin(this.pitch)];
    const scale = (0.45 * Math.min(width, height) * this.zoom) / this.radius;
    const [zLow, zHigh] = this.zRange;
    const p = this.cloud.points;
    for (let i = 0; i < p.length; i += 3) {
      const x = p[i] - this.centre[0];
      const y = p[i + 1] - this.centre[1];
      const z = p[i + 2] - this.centre[2];
      // Turn about Z (yaw), then tilt about X (pitch); look along -Z' at the result.
      const x1 = cy * x - sy * y;
      const y1 = sy * x + cy * y;
      const y2 = cp * y1 - sp * z;
      const z2 = sp * y1 + cp * z;
      const u = Math.round(width / 2 + x1 * scale);
      const v = Math.round(height / 2 - y2 * scale);
      const c = colour((p[i + 2] - zLow) / Math.max(1e-9, zHigh - zLow));
      for (let dv = 0; dv < 2; dv += 1) {
        for (let du = 0; du < 2; du += 1) {
          const uu = u + du;
          const vv = v + dv;
          if (uu < 0 || vv < 0 || uu >= width || vv >= height) continue;
          const at = vv * width + uu;
          if (-z2 >= depth[at]) continue;
          depth[at] = -z2;
          pixels[at * 4] = c[0];
          pixels[at * 4 + 1] = c[1];
          pixels[at * 4 + 2] = c[2];
          pixels[at * 4 + 3] = 255;
        }
      }
    }
    g.putImageData(image, 0, 0);
    g.fillStyle = "#c8d1dc";
    g.font = "12px system-ui, sans-serif";
    g.fillText(`${this.cloud.taken.toLocaleString()} of ${this.cloud.count.toLocaleString()} `
      + "points · drag to turn · wheel to zoom", 8, height - 8);
  }
}
