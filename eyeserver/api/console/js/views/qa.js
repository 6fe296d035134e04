// The daily QA (any role): the lockout of position verification and tracking and why, a QA run
// with its figures against their thresholds, the recent runs, each figure's trend as the
// daemon's plot (GET /qa/trends/{figure}.png) and the day's printable report. Physicists also
// set a calibration's QA baseline ("as baseline"), and override the lockout with a reason or
// withdraw the override; an operator is shown none of that (the daemon refuses it anyway).
//
// The lockout is the shell's (ctx.qa, GET /qa/status, renewed with the daemon's status and on
// every qa.* event); this view redraws it whenever it changes.

import {del, download, get, objectUrl, post, put, reasonOf} from "../api.js";
import {field, h, message, num, panel, replace, when} from "../dom.js";

const HISTORY_LIMIT = 20;
const QA_POSITION_MM = [0, 0, 0]; // the QA phantom's ball centre on the isocentre (docs/qa.md)

export function mount(container, ctx) {
  const physicist = ctx.may("physicist");
  let closed = false;
  let running = false;
  let runs = [];

  // --- the lockout -----------------------------------------------------------------------
  const lockWord = h("p", {class: "verdict-word", id: "qa-locked-word"}, "…");
  const lockReason = h("p", {id: "qa-reason"});
  const lockFacts = h("dl", {class: "facts", id: "qa-facts"});
  const overrideBox = h("div", {id: "qa-override-box"});
  const statusMessage = h("div", {id: "qa-status-message"});
  const statusPanel = h("section", {class: "panel", id: "qa-status", dataset: {locked: ""}},
    h("h2", {}, "Verification and tracking"), lockWord, lockReason, lockFacts, overrideBox,
    statusMessage);

  // Physicists: override the lockout with a reason (shown only while something is locked).
  const overrideReason = h("textarea", {id: "qa-override-reason", required: true, rows: 2,
    minlength: 3, maxlength: 1000, placeholder: "why: what was checked instead, who decided"});
  const overrideForm = physicist ? h("form", {id: "qa-override-form", class: "override",
    hidden: true}, h("h3", {}, "Override the lockout (until midnight, this calibration)"),
  h("label", {for: "qa-override-reason"}, "Reason (kept in the audit and the day's report)"),
  overrideReason,
  h("div", {class: "actions"}, h("button", {type: "submit", id: "qa-override",
    class: "danger"}, "Override the lockout"))) : null;
  const overridePanel = overrideForm ? h("section", {class: "panel", id: "qa-override-panel",
    hidden: true}, overrideForm) : null;
  overrideForm?.addEventListener("submit", (event) => {
    event.preventDefault();
    override();
  });

  // --- a run -----------------------------------------------------------------------------
  const baselineBox = physicist ? h("input", {type: "checkbox", id: "qa-baseline"}) : null;
  const runButton = h("button", {type: "button", id: "qa-run", class: "primary",
    onclick: run}, "Run the daily QA");
  const progress = h("p", {id: "qa-progress", class: "muted", role: "status", hidden: true});
  const result = h("div", {id: "qa-result", dataset: {passed: "none"}},
    h("p", {class: "muted"}, "No run from this page yet: the newest run is in the history."));
  const runMessage = h("div", {id: "qa-run-message"});

  // --- history, trends, report -------------------------------------------------------------
  const history = h("div", {id: "qa-history"});
  const trendDays = h("select", {id: "qa-trend-days"}, [30, 90, 365].map((d) =>
    h("option", {value: d, selected: d === 90}, `last ${d} days`)));
  const trends = h("div", {id: "qa-trends", class: "trends"});
  // The daemon host's day (its report's and its lockout's), not necessarily the browser's.
  const reportDay = h("input", {type: "date", id: "qa-report-day",
    value: ctx.qa?.day ?? localDay()});
  reportDay.addEventListener("change", () => {
    reportDay.dataset.chosen = "true";
  });
  const reportMessage = h("div", {id: "qa-report-message"});

  container.append(h("div", {class: "grid two"},
    h("div", {class: "column"},
      statusPanel,
      overridePanel,
      panel("Run the daily QA",
        h("p", {class: "small"}, "Place the QA phantom (eye phantom 1) at its QA position: the "
          + "ball's centre on the isocentre, the base plate facing +Z. The run captures it with "
          + "every unit a few times and measures it with the active calibration against its "
          + "drawing (a few seconds)."),
        ctx.simulated ? simPhantom() : null,
        h("div", {class: "actions"}, runButton,
          baselineBox ? h("label", {title: "Make this run the active calibration's QA baseline "
            + "if every other figure passes: needed once after every new calibration"},
          baselineBox, " as baseline") : null),
        progress, runMessage, result),
      h("section", {class: "panel"}, h("h2", {}, "The day's report"),
        h("p", {class: "small muted"}, "Every run of the day with its figures against their "
          + "thresholds, the lockout, the overrides and the trends: one HTML page to print, "
          + "sign and archive."),
        h("div", {class: "actions"}, h("label", {}, "Day ", reportDay),
          h("button", {type: "button", id: "qa-report", onclick: report},
            "Download the printable report")), reportMessage)),
    h("div", {class: "column"},
      panel(`Recent runs (newest ${HISTORY_LIMIT})`, history),
      h("section", {class: "panel"}, h("h2", {}, "Trends"),
        h("div", {class: "actions"}, trendDays,
          h("span", {class: "muted small"}, "threshold dashed, failures red, baselines "
            + "squared, calibration changes dotted")),
        trends))));

  // --- the lockout -----------------------------------------------------------------------
  function showStatus(status) {
    if (!status) return;
    statusPanel.dataset.locked = String(status.locked);
    lockWord.className = `verdict-word ${status.locked ? "fail" : "pass"}`;
    lockWord.textContent = status.locked ? "LOCKED" : status.override ? "OVERRIDDEN"
      : "NOT LOCKED";
    if (status.locked) {
      replace(lockReason, h("span", {class: "error"}, `Locked: ${status.reason}`));
    } else if (status.qa_reason) {
      replace(lockReason, h("span", {class: "warn"}, status.override
        ? `The physicist's override lifts the lockout; the QA still lacks: ${status.qa_reason}`
        : `Not required by the settings (qa.required = false); the QA lacks: `
          + status.qa_reason));
    } else {
      replace(lockReason, h("span", {class: "ok"}, "Today's QA passed with the active "
        + "calibration."));
    }
    replace(lockFacts,
      field("Day", status.day),
      field("Required", status.required ? "yes (qa.required)" : "no (qa.required = false)"),
      field("Calibration", status.calibration_id ?? "none active"),
      field("QA baseline", status.baseline_run_id ?? "none"),
      field("Today's last pass", status.last_pass ?? "none"),
      field("Today's last run", status.last_run ?? "none"),
      field("Failures since the pass", `${status.failures_since_pass} (locked at ${
        status.max_consecutive_failures})`));
    const current = status.override;
    replace(overrideBox, current ? h("div", {class: "override-notice", id: "qa-override-now"},
      h("strong", {}, "Override in force"), ` by ${current.actor}, ${when(current.created)}, `
        + `until ${when(current.until)}: “${current.reason}”`,
      h("div", {class: "small muted"}, `It overrode: ${current.lockout_reason ?? "–"}`),
      physicist ? h("div", {class: "actions"}, h("button", {type: "button",
        id: "qa-override-withdraw", onclick: withdraw}, "Withdraw the override")) : null)
      : null);
    if (overrideForm) overrideForm.hidden = overridePanel.hidden = !status.locked;
    if (!reportDay.dataset.chosen) reportDay.value = status.day;
    runButton.disabled = running;
  }

  async function override() {
    const reason = overrideReason.value.trim();
    if (reason.length < 3) {
      replace(statusMessage, message("error", "An override needs a reason."));
      return;
    }
    const button = document.getElementById("qa-override");
    button.disabled = true;
    try {
      await post("/qa/override", {reason});
      overrideReason.value = "";
      replace(statusMessage, message("ok", "The lockout is overridden until midnight."));
    } catch (error) {
      replace(statusMessage, message("error", reasonOf(error)));
    } finally {
      button.disabled = false;
    }
    await ctx.refreshQa().catch(() => {});
  }

  async function withdraw() {
    try {
      await del("/qa/override");
      replace(statusMessage, message("ok", "The override is withdrawn."));
    } catch (error) {
      replace(statusMessage, message("error", reasonOf(error)));
    }
    await ctx.refreshQa().catch(() => {});
  }

  // --- a run -----------------------------------------------------------------------------
  function simPhantom() {
    return h("div", {class: "sim-helper"},
      h("span", {class: "badge"}, "simulated room"),
      " The QA phantom at its QA position (PUT /sim/scene) ",
      h("button", {type: "button", id: "sim-phantom", onclick: async () => {
        try {
          await put("/sim/scene", {kind: "eye_phantom_1", position_mm: QA_POSITION_MM});
          replace(runMessage, message("ok", "QA phantom placed at its QA position."));
        } catch (error) {
          replace(runMessage, message("error", reasonOf(error)));
        }
      }}, "Place the QA phantom"));
  }

  async function run() {
    if (running) return;
    const baseline = Boolean(baselineBox?.checked);
    running = true;
    runButton.disabled = true;
    replace(runMessage);
    replace(statusMessage);
    const started = Date.now();
    const tick = () => {
      progress.textContent = `Running${baseline ? " (as baseline)" : ""}: capturing the `
        + `phantom with every unit and measuring it… ${Math.round((Date.now() - started)
          / 1000)} s`;
    };
    tick();
    progress.hidden = false;
    const ticker = setInterval(tick, 500);
    result.dataset.passed = "running";
    try {
      const done = await post("/qa/runs", baseline ? {baseline: true} : {});
      if (closed) return;
      showRun(done, "This run");
      if (baselineBox) baselineBox.checked = false;
    } catch (error) {
      if (closed) return;
      result.dataset.passed = "none";
      replace(runMessage, message("error", reasonOf(error)));
    } finally {
      clearInterval(ticker);
      running = false;
      progress.hidden = true;
      runButton.disabled = false;
    }
    await Promise.all([ctx.refreshQa().catch(() => {}), loadHistory(), loadTrends()]);
  }

  /** A run: its verdict, each figure against its threshold, why it failed. */
  function showRun(r, title) {
    result.dataset.passed = String(r.passed);
    result.dataset.run = r.id;
    replace(result,
      h("h3", {}, `${title}: ${r.id}`),
      h("p", {class: `verdict-word ${r.passed ? "pass" : "fail"}`},
        r.passed ? "PASSED" : "FAILED"),
      h("p", {class: "small"}, `${when(r.created)} by ${r.actor}; calibration `
        + `${r.calibration_id}; ${r.frames} frames; `
        + (r.baseline ? "this run is the calibration's QA baseline"
          : `drift against baseline ${r.baseline_run_id ?? "none"}`)),
      h("table", {class: "table", id: "qa-figures"},
        h("thead", {}, h("tr", {}, ["figure", "value (mm)", "threshold (mm)", ""].map(
          (name) => h("th", {}, name)))),
        h("tbody", {}, Object.entries(r.figures).map(([name, f]) => h("tr", {
          class: f.passed ? "" : "failed", dataset: {figure: name, passed: String(f.passed)}},
        h("td", {class: "mono"}, name), h("td", {class: "num"}, num(f.value, 4)),
        h("td", {class: "num"}, num(f.threshold, 3)),
        h("td", {class: f.passed ? "ok" : "error"}, f.passed ? "pass" : "FAIL"))))),
      r.reasons.length ? h("ul", {class: "reasons", id: "qa-reasons"},
        r.reasons.map((text) => h("li", {}, text))) : null);
  }

  // --- history, trends, report -------------------------------------------------------------
  async function loadHistory() {
    try {
      runs = (await get("/qa/runs", {query: {limit: HISTORY_LIMIT}})).items;
    } catch (error) {
      replace(history, message("error", reasonOf(error)));
      return;
    }
    if (closed) return;
    if (!runs.length) {
      replace(history, h("p", {class: "muted"}, "No QA run yet."));
      return;
    }
    replace(history, h("table", {class: "table small", dataset: {rows: runs.length}},
      h("thead", {}, h("tr", {}, ["time", "by", "calibration", "result", "why", ""].map(
        (name) => h("th", {}, name)))),
      h("tbody", {}, runs.map((r) => h("tr", {dataset: {run: r.id, passed: String(r.passed)}},
        h("td", {}, when(r.created)), h("td", {}, r.actor),
        h("td", {class: "mono"}, r.calibration_id),
        h("td", {class: r.passed ? "ok" : "error"}, r.passed ? "passed" : "failed",
          r.baseline ? h("span", {class: "badge"}, "baseline") : null),
        h("td", {class: "wrap"}, r.reasons.join("; ")),
        h("td", {class: "actions"}, h("button", {type: "button", class: "show-run",
          onclick: () => showRun(r, "Run")}, "Figures")))))));
  }

  async function loadTrends() {
    let data;
    try {
      data = await get("/qa/trends", {query: {days: trendDays.value}});
    } catch (error) {
      replace(trends, message("error", reasonOf(error)));
      return;
    }
    const figures = Object.entries(data.figures);
    const tiles = await Promise.all(figures.map(async ([name, series]) => {
      const caption = h("figcaption", {}, h("span", {class: "mono"}, name),
        ` — ${series.description}; threshold ${num(series.threshold, 3)} mm, `
          + `${series.points.length} run(s)`);
      try {
        const src = await objectUrl(`/qa/trends/${encodeURIComponent(name)}.png`,
          {query: {days: data.days}});
        return h("figure", {class: "trend", dataset: {figure: name}},
          image(src, `${name} over the last ${data.days} days`), caption);
      } catch (error) {
        return h("figure", {class: "trend", dataset: {figure: name}},
          message("error", reasonOf(error)), caption);
      }
    }));
    if (closed) return;
    replace(trends, tiles);
    trends.dataset.days = String(data.days);
  }

  async function report() {
    const day = reportDay.value || localDay();
    replace(reportMessage);
    try {
      await download(`/qa/report?day=${encodeURIComponent(day)}`, `eyeserver-qa-${day}.html`);
      replace(reportMessage, message("ok", `eyeserver-qa-${day}.html saved: open it to print.`));
    } catch (error) {
      replace(reportMessage, message("error", reasonOf(error)));
    }
  }

  const onQa = (event) => showStatus(event.detail);
  const onEvent = (event) => {
    const type = event.detail.type;
    if (type === "qa.run" && !running) {
      loadHistory();
      loadTrends();
    }
  };
  ctx.events.addEventListener("qa", onQa);
  ctx.events.addEventListener("event", onEvent);
  trendDays.addEventListener("change", loadTrends);
  showStatus(ctx.qa);
  ctx.refreshQa().catch((error) => replace(statusMessage, message("error", reasonOf(error))));
  loadHistory();
  loadTrends();

  return () => {
    closed = true;
    ctx.events.removeEventListener("qa", onQa);
    ctx.events.removeEventListener("event", onEvent);
  };
}

/** Today as the browser's local date (YYYY-MM-DD); the daemon's report defaults to its own. */
function localDay() {
  const now = new Date();
  const pad = (n) => String(n).padStart(2, "0");
  return `${now.getFullYear()}-${pad(now.getMonth() + 1)}-${pad(now.getDate())}`;
}

/** An <img> of a blob: URL, which it lets go once decoded (or failed). */
function image(src, alt) {
  const element = h("img", {alt});
  const release = () => URL.revokeObjectURL(src);
  element.addEventListener("load", release, {once: true});
  element.addEventListener("error", release, {once: true});
  element.src = src;
  return element;
}
