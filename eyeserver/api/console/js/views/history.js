// Calibration history (physicists): every stored calibration with its version, lineage and
// quality figures; activate one, download one (with its evidence), compare two for drift.

import {at, download, get, post, reasonOf} from "../api.js";
import {field, h, message, num, panel, replace, when} from "../dom.js";

export function mount(container, ctx) {
  const table = h("div", {id: "calibration-list"});
  const feedback = h("div", {id: "history-message"});
  const compareA = h("select", {id: "compare-a"});
  const compareB = h("select", {id: "compare-b"});
  const comparison = h("div", {id: "comparison"});
  container.append(panel("Calibrations, newest first", feedback, table),
    panel("Drift between two calibrations",
      h("form", {class: "inline", onsubmit: (e) => {
        e.preventDefault();
        compare();
      }}, h("label", {}, "A ", compareA), h("label", {}, "B ", compareB),
      h("button", {type: "submit", id: "compare"}, "Compare")), comparison));

  async function load() {
    let items;
    try {
      items = (await get("/calibrations")).items;
    } catch (error) {
      replace(table, message("error", reasonOf(error)));
      return;
    }
    const options = (selected) => items.map((c) => h("option", {value: c.id,
      selected: c.id === selected}, `v${c.version ?? "?"} ${c.id}`));
    replace(compareA, options(items[1]?.id));
    replace(compareB, options(items[0]?.id));
    if (!items.length) {
      replace(table, h("p", {class: "muted"}, "No calibration stored yet: run a guided "
        + "calibration or upload one (POST /api/v1/calibrations)."));
      return;
    }
    replace(table, h("table", {class: "table"},
      h("thead", {}, h("tr", {}, ["version", "id", "made", "imported", "source", "quality",
        "lineage", ""].map((name) => h("th", {}, name)))),
      h("tbody", {}, items.map((c) => h("tr", {class: c.active ? "active" : "",
        dataset: {calibration: c.id}},
      h("td", {}, c.version ?? "–", c.active ? h("span", {class: "badge state-idle"}, "active")
        : null),
      h("td", {class: "mono"}, c.id, c.status === "missing" ? h("span", {class: "error"},
        " (files missing)") : null),
      h("td", {}, when(c.created)), h("td", {}, when(c.imported)),
      h("td", {class: "small wrap"}, c.source),
      h("td", {class: "small"}, quality(c.quality)),
      h("td", {class: "small"}, c.parent_id ? `parent ${c.parent_id}` : "",
        c.session_id ? ` session ${c.session_id}` : ""),
      h("td", {class: "actions"},
        c.active ? null : h("button", {type: "button", class: "activate",
          onclick: () => activate(c.id)}, "Activate"),
        h("button", {type: "button", onclick: () => download(at("calibrations", c.id,
          "download"), `${c.id}.zip`).catch((e) => replace(feedback,
          message("error", reasonOf(e))))}, "Download")))))));
  }

  async function activate(id) {
    if (!window.confirm(`Make ${id} the active calibration? Captures, reconstructions and `
        + "tracking use it from now on.")) return;
    try {
      await post(at("calibrations", id, "activate"));
      replace(feedback, message("ok", `Calibration ${id} is active.`));
      ctx.refreshStatus().catch(() => {});
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    load();
  }

  async function compare() {
    if (!compareA.value || !compareB.value) return;
    try {
      const drift = await get("/calibrations/compare", {query: {a: compareA.value,
        b: compareB.value}});
      replace(comparison, flatTable(drift));
    } catch (error) {
      replace(comparison, message("error", reasonOf(error)));
    }
  }

  const onEvent = (event) => {
    if (event.detail.type.startsWith("calibration.")) load();
  };
  ctx.events.addEventListener("event", onEvent);
  load();
  return () => ctx.events.removeEventListener("event", onEvent);
}

/** The quality figures as short "name value" lines (nested figures joined with dots). */
function quality(figures) {
  const lines = flatten(figures).filter(([, v]) => typeof v === "number").slice(0, 8);
  return lines.length ? h("dl", {class: "facts compact"}, lines.map(([k, v]) =>
    field(k, num(v, Math.abs(v) < 0.1 ? 4 : 3)))) : "–";
}

function flatten(value, prefix = "") {
  if (value && typeof value === "object" && !Array.isArray(value)) {
    return Object.entries(value).flatMap(([k, v]) => flatten(v, prefix ? `${prefix}.${k}` : k));
  }
  return [[prefix, value]];
}

function flatTable(value) {
  return h("dl", {class: "facts"}, flatten(value).map(([k, v]) => field(k,
    typeof v === "number" ? num(v, 4) : Array.isArray(v) ? v.map((x) => (typeof x === "number"
      ? num(x, 3) : String(x))).join(", ") : String(v))));
}
