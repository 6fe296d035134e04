// The audit trail (physicists): who did what to which item, when, with what outcome; newest
// first, filtered in the browser.

import {get, reasonOf} from "../api.js";
import {h, message, panel, replace, when} from "../dom.js";

export function mount(container) {
  const filter = h("input", {type: "search", id: "audit-filter", placeholder: "filter: actor, "
    + "action, target…", size: 30});
  const limit = h("select", {id: "audit-limit"}, [100, 500, 1000].map((n) =>
    h("option", {value: n}, `newest ${n}`)));
  const table = h("div", {id: "audit-table"});
  let entries = [];
  container.append(panel("Audit trail",
    h("div", {class: "actions"}, filter, limit,
      h("button", {type: "button", id: "audit-refresh", onclick: load}, "Refresh")),
    table));

  async function load() {
    try {
      entries = (await get("/audit", {query: {limit: limit.value}})).items;
    } catch (error) {
      replace(table, message("error", reasonOf(error)));
      return;
    }
    draw();
  }

  function draw() {
    const words = filter.value.toLowerCase().split(/\s+/).filter(Boolean);
    const shown = entries.filter((e) => {
      const text = `${e.actor} ${e.role} ${e.action} ${e.target} ${e.outcome} `
        + JSON.stringify(e.detail);
      return words.every((w) => text.toLowerCase().includes(w));
    });
    replace(table, h("table", {class: "table small", dataset: {rows: shown.length}},
      h("thead", {}, h("tr", {}, ["time", "actor", "role", "action", "target", "outcome",
        "detail"].map((name) => h("th", {}, name)))),
      h("tbody", {}, shown.map((e) => h("tr", {class: `outcome-${e.outcome}`},
        h("td", {}, when(e.time)), h("td", {}, e.actor), h("td", {}, e.role),
        h("td", {}, e.action), h("td", {class: "mono"}, e.target),
        h("td", {}, e.outcome),
        h("td", {class: "mono small"}, Object.keys(e.detail).length
          ? JSON.stringify(e.detail) : ""))))),
    shown.length ? null : h("p", {class: "muted"}, "No entry matches."));
  }

  filter.addEventListener("input", draw);
  limit.addEventListener("change", load);
  load();
  return null;
}
