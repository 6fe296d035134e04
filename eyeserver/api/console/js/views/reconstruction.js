// Reconstruction (physicists): pick a capture, reconstruct it with the active calibration, and
// see its surface as the daemon's height map (preview.png) and as points on a canvas (its
// cloud.ply, parsed in the browser), with the reconstruction's summary.

import {at, bytes, get, objectUrl, post, reasonOf} from "../api.js";
import {field, h, message, num, panel, replace, when} from "../dom.js";
import {PointView, parsePly} from "../points.js";

export function mount(container, ctx) {
  const list = h("div", {id: "capture-list"});
  const feedback = h("div", {id: "reconstruction-message"});
  const summary = h("div", {id: "reconstruction-summary"});
  const heightMap = h("img", {id: "height-map", class: "height-map", alt: "height map"});
  const canvas = h("canvas", {id: "point-view", class: "points", width: 560, height: 420});
  const points = new PointView(canvas);
  let selected = null;
  let closed = false;

  container.append(h("div", {class: "grid two"},
    h("div", {class: "column"}, panel("Captures", list)),
    h("div", {class: "column wide"},
      h("section", {class: "panel"}, h("h2", {id: "reconstruction-title"}, "Surface"),
        feedback, summary,
        h("div", {class: "surface"},
          h("figure", {}, heightMap, h("figcaption", {}, "Height map (Z over X, Y: blue "
            + "low, red high)")),
          h("figure", {}, canvas, h("figcaption", {}, "Points (drag to turn)")))))));

  async function load() {
    try {
      const page = await get("/captures", {query: {limit: 30}});
      replace(list, h("table", {class: "table small"},
        h("thead", {}, h("tr", {}, ["capture", "kind", "unit", "created", ""].map(
          (name) => h("th", {}, name)))),
        h("tbody", {}, page.items.map((c) => h("tr", {dataset: {capture: c.id},
          class: c.id === selected ? "active" : ""},
        h("td", {class: "mono"}, c.id), h("td", {}, c.kind), h("td", {}, c.unit),
        h("td", {}, when(c.created)),
        h("td", {class: "actions"},
          h("button", {type: "button", class: "show", onclick: () => show(c.id)}, "Show"),
          h("button", {type: "button", class: "reconstruct primary",
            disabled: !ctx.status?.active_calibration_id,
            title: ctx.status?.active_calibration_id ? "With the active calibration"
              : "No calibration is active", onclick: () => reconstruct(c.id)},
          "Reconstruct")))))),
      page.total > page.items.length ? h("p", {class: "muted small"},
        `The newest ${page.items.length} of ${page.total}.`) : null);
    } catch (error) {
      replace(list, message("error", reasonOf(error)));
    }
  }

  async function reconstruct(id) {
    selected = id;
    replace(feedback, h("p", {class: "muted"}, `Reconstructing ${id} (seconds)…`));
    try {
      const answer = await post(at("captures", id, "reconstruction"));
      await present(id, answer);
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    load();
  }

  /** A capture's stored reconstruction; 404 (said as such) before it has one. */
  async function show(id) {
    selected = id;
    replace(feedback, h("p", {class: "muted"}, `Loading ${id}…`));
    try {
      await present(id, await get(at("captures", id, "reconstruction")));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
      replace(summary);
    }
    load();
  }

  async function present(id, answer) {
    document.getElementById("reconstruction-title").textContent = `Surface of ${id}`;
    replace(feedback);
    const extent = answer.extent_mm;
    replace(summary, h("dl", {class: "facts", dataset: {points: answer.points}},
      field("Points", answer.points.toLocaleString()),
      field("Extent", extent ? `${extent.min.map((v) => num(v, 2)).join(", ")} … `
        + `${extent.max.map((v) => num(v, 2)).join(", ")} mm` : answer.empty_reason || "–"),
      field("Calibration", answer.calibration_id),
      field("Method", answer.method),
      field("Per camera", Object.entries(answer.cameras).map(([c, s]) =>
        `${c}: ${s.points.toLocaleString()}${s.method ? ` (${s.method})` : ""}`).join("; ")),
      field("Made", `${when(answer.reconstructed)}, ${num(answer.duration_s, 1)} s`)));
    if (answer.points === 0) return;
    const [href, buffer] = await Promise.all([
      objectUrl(at("captures", id, "preview.png")), bytes(at("captures", id, "cloud.ply"))]);
    if (closed) {
      URL.revokeObjectURL(href);
      return;
    }
    // Let go of the blob: URL once decoded: no URL outlives its image.
    const release = () => URL.revokeObjectURL(href);
    heightMap.addEventListener("load", release, {once: true});
    heightMap.addEventListener("error", release, {once: true});
    heightMap.src = href;
    heightMap.dataset.capture = id;
    const cloud = parsePly(buffer);
    canvas.dataset.points = String(cloud.taken);
    canvas.dataset.capture = id;
    points.show(cloud);
  }

  const onEvent = (event) => {
    if (["capture.stored", "reconstruction.done"].includes(event.detail.type)) load();
  };
  ctx.events.addEventListener("event", onEvent);
  load();
  return () => {
    closed = true;
    ctx.events.removeEventListener("event", onEvent);
  };
}
