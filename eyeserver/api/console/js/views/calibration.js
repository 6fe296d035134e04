// Guided calibration (physicists): a stereo session whose board coverage grid fills in view by
// view, or a phase-height session over plate heights; what is still missing, then the solve as
// a job with its progress, and the new calibration to activate.
//
// In the simulated room a helper places the board (PUT /sim/chessboard) at the poses the
// offline calibration set uses; in a real room the physicist moves the board by hand.

import {at, del, get, post, put, reasonOf} from "../api.js";
import {field, h, message, num, panel, replace, when} from "../dom.js";

const JOB_POLL_MS = 500;
const SESSION_POLL_MS = 3000;

// eyeserver/hardware/sim/sessions.py calibration_poses(): the first is the origin board.
const SIM_BOARD_POSES = [
  [[0, 0, 0], [0, 0, 0]], [[0, 0, 5], [20, 0, 0]], [[0, 0, 5], [-20, 0, 0]],
  [[0, 0, -5], [0, 22, 0]], [[0, 0, -5], [0, -22, 0]], [[3, -2, 10], [15, 15, 10]],
  [[-3, 2, 10], [-15, -15, -10]], [[2, 3, -8], [18, -18, 25]], [[-2, -3, -8], [-18, 18, -25]],
  [[0, 0, 15], [0, 0, 90]], [[0, 0, 0], [10, -25, 180]], [[4, 0, 3], [-25, 10, 45]],
];

export function mount(container, ctx) {
  let session = null;
  let jobTimer = null;
  let closed = false;
  let simPose = 0;
  const timers = [];

  const sessionPanel = h("section", {class: "panel", id: "calibration-session"});
  const solvePanel = h("section", {class: "panel", id: "calibration-solve", hidden: true});
  const sessionsPanel = panel("Sessions of this run", h("div", {id: "calibration-sessions"}));
  const feedback = h("div", {id: "calibration-message"});
  container.append(h("div", {class: "grid two wide-first"},
    h("div", {class: "column wide"}, feedback, sessionPanel, solvePanel),
    h("div", {class: "column"}, sessionsPanel)));

  // --- starting a session -------------------------------------------------------------------
  async function showStart() {
    session = null;
    const cols = h("input", {type: "number", id: "board-cols", value: 9, min: 2, class: "narrow"});
    const rows = h("input", {type: "number", id: "board-rows", value: 6, min: 2, class: "narrow"});
    const square = h("input", {type: "number", id: "board-square", value: 4.5, min: 0.1,
      step: 0.1, class: "narrow"});
    const parent = h("select", {id: "p2h-parent"});
    try {
      const calibrations = (await get("/calibrations")).items;
      replace(parent, calibrations.map((c) => h("option", {value: c.id, selected: c.active},
        `v${c.version ?? "?"} ${c.id}${c.active ? " (active)" : ""}`)));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    replace(sessionPanel, h("h2", {}, "Start a guided calibration"),
      h("p", {class: "muted"}, "Opening a session puts the daemon in calibrating: captures "
        + "and tracking wait until its solve starts or it is closed."),
      h("h3", {}, "Stereo (chessboard views)"),
      h("form", {class: "inline", onsubmit: (e) => {
        e.preventDefault();
        open({kind: "stereo", board: {cols: Number(cols.value), rows: Number(rows.value),
          square_mm: Number(square.value)}});
      }}, h("label", {}, "Corners ", cols, " × ", rows),
      h("label", {}, "Square ", square, " mm"),
      h("button", {type: "submit", id: "session-stereo", class: "primary"},
        "Start stereo session")),
      h("h3", {}, "Phase-to-height (plate heights)"),
      h("form", {class: "inline", onsubmit: (e) => {
        e.preventDefault();
        if (parent.value) open({kind: "phase-height", calibration_id: parent.value});
      }}, h("label", {}, "Parent calibration ", parent),
      h("button", {type: "submit", id: "session-p2h", disabled: !parent.options.length},
        "Start phase-height session")));
  }

  async function open(body) {
    replace(feedback);
    try {
      showSession(await post("/calibration-sessions", body));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    listSessions();
  }

  // --- a session acquiring --------------------------------------------------------------------
  function showSession(found) {
    session = found;
    sessionPanel.dataset.session = found.id;
    sessionPanel.dataset.state = found.state;
    // A phase-height session whose solve failed takes more plates and is solved anew.
    const extendable = found.state === "failed" && found.kind === "phase-height";
    if (found.state !== "acquiring" && !extendable) {
      if (found.job_id) followJob(found.job_id);
      showStart();
      return;
    }
    const stereo = found.kind === "stereo";
    replace(sessionPanel,
      h("h2", {}, `${stereo ? "Stereo" : "Phase-to-height"} session ${found.id}`),
      h("dl", {class: "facts"}, field("Opened", `${when(found.created)} by ${found.actor}`),
        stereo ? field("Board", `${found.board.cols} × ${found.board.rows} corners, `
          + `${found.board.square_mm} mm squares`) : field("Parent", found.parent_id)),
      extendable ? message("error", `The solve failed: ${found.error} Add the plates the plan `
        + "asks for, then solve again.") : null,
      stereo ? stereoSteps(found) : plateSteps(found),
      h("h3", {}, "Still missing"),
      missingList(found),
      h("div", {class: "actions"},
        h("button", {type: "button", id: "solve", class: "primary",
          disabled: !found.ready || found.state !== "acquiring", onclick: solve}, "Solve"),
        h("button", {type: "button", id: "session-close", onclick: closeSession},
          "Close session")));
  }

  function missingList(found) {
    const missing = found.coverage ? found.coverage.missing : found.missing;
    if (!missing?.length) {
      return h("p", {id: "missing", class: "ok", dataset: {ready: "true"}},
        "Nothing: ready to solve.");
    }
    return h("ul", {id: "missing", class: "reasons", dataset: {ready: "false"}},
      missing.map((m) => h("li", {}, m)));
  }

  function stereoSteps(found) {
    const origin = h("input", {type: "checkbox", id: "view-origin",
      checked: found.views.length === 0});
    const cameras = found.coverage.cameras;
    const grids = Object.entries(cameras).map(([camera, entry]) => coverageGrid(camera, entry));
    return [
      ctx.simulated ? simBoard() : null,
      h("div", {class: "actions"},
        h("label", {}, origin, " origin board (defines the WCS)"),
        h("button", {type: "button", id: "acquire-view", class: "primary",
          onclick: () => acquireView(origin.checked)}, "Acquire view")),
      h("h3", {}, `Board coverage (${found.views.length} view${found.views.length === 1
        ? "" : "s"})`),
      h("div", {class: "coverage", id: "coverage"}, grids),
      found.views.length ? h("table", {class: "table small", id: "views"},
        h("thead", {}, h("tr", {}, h("th", {}, "#"), h("th", {}, "capture"),
          h("th", {}, "origin"), h("th", {}, "found by"))),
        h("tbody", {}, found.views.map((v, k) => h("tr", {}, h("td", {}, k + 1),
          h("td", {}, v.capture_id), h("td", {}, v.origin ? "yes" : ""),
          h("td", {}, Object.entries(v.found).filter(([, f]) => f).map(([c]) => c)
            .join(", ") || "none"))))) : null,
    ];
  }

  /** A camera's image cut into cells: filled where the board's corners have been seen. */
  function coverageGrid(camera, entry) {
    const size = Math.round(Math.sqrt(entry.cells_total));
    const uncovered = new Set(entry.uncovered_cells.map(([r, c]) => `${r},${c}`));
    const cells = [];
    for (let r = 0; r < size; r += 1) {
      for (let c = 0; c < size; c += 1) {
        const covered = !uncovered.has(`${r},${c}`);
        cells.push(h("span", {class: `cell ${covered ? "covered" : ""}`,
          dataset: {covered: String(covered)}, title: `row ${r}, column ${c}`}));
      }
    }
    const grid = h("div", {class: "cells"}, cells);
    // Through the CSSOM: the Content-Security-Policy refuses style attributes.
    grid.style.gridTemplateColumns = `repeat(${size}, 1fr)`;
    return h("figure", {class: "coverage-camera", dataset: {camera}}, grid,
      h("figcaption", {}, h("strong", {}, camera), ` ${Math.round(entry.coverage * 100)} % — `
        + `${entry.views_found} view(s)`, entry.origin_found ? ", origin seen" : ""));
  }

  function simBoard() {
    const [position, rotation] = SIM_BOARD_POSES[simPose % SIM_BOARD_POSES.length];
    return h("div", {class: "sim-helper"},
      h("span", {class: "badge"}, "simulated room"),
      ` Board pose ${simPose % SIM_BOARD_POSES.length + 1} of ${SIM_BOARD_POSES.length}: at `
        + `(${position.join(", ")}) mm, turned (${rotation.join(", ")})° `,
      h("button", {type: "button", id: "sim-board", onclick: async () => {
        try {
          await put("/sim/chessboard", {position_mm: position, rotation_deg: rotation});
          replace(feedback, message("ok", `Board placed at pose ${simPose
            % SIM_BOARD_POSES.length + 1}.`));
        } catch (error) {
          replace(feedback, message("error", reasonOf(error)));
        }
      }}, "Place the board"));
  }

  async function acquireView(origin) {
    const button = document.getElementById("acquire-view");
    if (button) button.disabled = true;
    replace(feedback, h("p", {class: "muted"}, "Acquiring the board…"));
    try {
      const answer = await post(at("calibration-sessions", session.id, "views"), {origin});
      const found = Object.entries(answer.found).filter(([, f]) => f).map(([c]) => c);
      replace(feedback, message(found.length ? "ok" : "error", found.length
        ? `View stored (${answer.capture_id}): board found by ${found.join(", ")}.`
        : `View stored (${answer.capture_id}) but no camera found the board.`));
      simPose += 1;
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    await reload();
  }

  function plateSteps(found) {
    const z = h("input", {type: "number", id: "plate-z", value: nextPlateZ(found), step: "any",
      class: "narrow"});
    const stage = h("input", {type: "checkbox", id: "plate-stage", checked: ctx.simulated});
    const referenceZ = h("input", {type: "number", id: "reference-z", value: 10, step: 0.5,
      class: "narrow"});
    const plan = found.plan || {};
    const steepest = Math.max(...Object.values(plan.sensitivity_rad_per_mm || {}));
    return [
      h("p", {id: "plate-plan", dataset: {step: plan.max_step_mm ?? ""}},
        plan.max_step_mm ? `Fringe sensitivity ${num(steepest, 2)} rad/mm (${
          plan.sensitivity_source}): planes at most ${plan.max_step_mm} mm apart over Z ${
          plan.z_range_mm.join("…")} mm. ` : "", `Next: ${plan.next ?? "—"}`),
      h("div", {class: "actions"},
        h("label", {}, "Plate at Z ", z, " mm"),
        h("label", {}, stage, " move it with the stage"),
        h("button", {type: "button", id: "acquire-plate", class: "primary", onclick: () =>
          acquire("plates", {z_mm: Number(z.value), move_stage: stage.checked})},
        "Acquire plate")),
      h("div", {class: "actions"},
        h("label", {}, "Reference plane at Z ", referenceZ, " mm"),
        h("button", {type: "button", id: "acquire-reference", onclick: () =>
          acquire("reference", {z_mm: Number(referenceZ.value)})}, "Acquire reference")),
      h("table", {class: "table small", id: "plates"},
        h("thead", {}, h("tr", {}, h("th", {}, "Z (mm)"), h("th", {}, "capture"),
          h("th", {}, "by stage"))),
        h("tbody", {}, found.plates.map((p) => h("tr", {}, h("td", {}, num(p.z_mm, 2)),
          h("td", {}, p.capture_id), h("td", {}, p.moved_by_stage ? "yes" : "by hand"))),
        found.reference ? h("tr", {class: "reference"}, h("td", {}, `${num(
          found.reference.z_mm, 2)} (reference)`), h("td", {}, found.reference.capture_id),
        h("td", {}, "")) : null)),
    ];
  }

  /** The first height the session's plan asks for; before it knows the rig's sensitivity,
   * the probe 1 mm below the reference plane. */
  function nextPlateZ(found) {
    const needed = found.plan?.needed_heights_mm;
    if (needed?.length) return needed[0];
    return found.reference ? found.reference.z_mm - 1 : 0;
  }

  async function acquire(what, body) {
    replace(feedback, h("p", {class: "muted"}, "Acquiring…"));
    try {
      const answer = await post(at("calibration-sessions", session.id, what), body);
      replace(feedback, message("ok", `Stored ${answer.capture_id} at Z ${num(answer.z_mm,
        2)} mm.`));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    await reload();
  }

  async function closeSession() {
    try {
      await del(at("calibration-sessions", session.id));
      replace(feedback, message("ok", `Session ${session.id} closed; its captures stay.`));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    await showStart();
    listSessions();
  }

  // --- the solve ------------------------------------------------------------------------------
  async function solve() {
    try {
      const job = await post(at("calibration-sessions", session.id, "solve"));
      followJob(job.id);
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
    }
    await showStart();
    listSessions();
  }

  function followJob(jobId) {
    clearTimeout(jobTimer);
    solvePanel.hidden = false;
    const bar = h("progress", {id: "solve-progress", max: 1, value: 0});
    const text = h("p", {id: "solve-message", class: "muted"}, "queued");
    const outcome = h("div", {id: "solve-outcome"});
    replace(solvePanel, h("h2", {}, `Solve ${jobId}`), bar, text, outcome);
    const poll = async () => {
      if (closed) return;
      let job;
      try {
        job = await get(at("jobs", jobId));
      } catch (error) {
        replace(outcome, message("error", reasonOf(error)));
        return;
      }
      bar.value = job.progress;
      solvePanel.dataset.state = job.state;
      text.textContent = `${job.state}, ${Math.round(job.progress * 100)} %: ${job.message}`;
      if (job.state === "queued" || job.state === "running") {
        jobTimer = setTimeout(poll, JOB_POLL_MS);
        return;
      }
      if (job.state === "succeeded") {
        const id = job.result?.calibration_id;
        replace(outcome, message("ok", `New calibration ${id} (not active yet).`),
          id ? h("button", {type: "button", id: "activate-new", class: "primary",
            onclick: async () => {
              try {
                await post(at("calibrations", id, "activate"));
                replace(outcome, message("ok", `Calibration ${id} is active.`));
              } catch (error) {
                replace(outcome, message("error", reasonOf(error)));
              }
            }}, "Activate it") : null);
      } else {
        replace(outcome, message("error", `${job.state}: ${job.error}`));
      }
      listSessions();
    };
    poll();
  }

  // --- every session of this run -------------------------------------------------------------
  async function listSessions() {
    const target = document.getElementById("calibration-sessions");
    try {
      const items = (await get("/calibration-sessions")).items;
      if (!target) return;
      replace(target, items.length ? h("table", {class: "table small"},
        h("thead", {}, h("tr", {}, h("th", {}, "session"), h("th", {}, "kind"),
          h("th", {}, "state"), h("th", {}, "calibration"))),
        h("tbody", {}, items.map((s) => h("tr", {}, h("td", {}, s.id), h("td", {}, s.kind),
          h("td", {}, s.state + (s.error ? `: ${s.error}` : "")),
          h("td", {}, s.calibration_id || ""))))) : h("p", {class: "muted"}, "None yet."));
      return items;
    } catch (error) {
      if (target) replace(target, message("error", reasonOf(error)));
      return [];
    }
  }

  async function reload() {
    if (!session) return;
    try {
      showSession(await get(at("calibration-sessions", session.id)));
    } catch (error) {
      replace(feedback, message("error", reasonOf(error)));
      await showStart();
    }
    listSessions();
  }

  async function resume() {
    const items = await listSessions();
    const acquiring = items.find((s) => s.state === "acquiring");
    const solving = items.find((s) => s.state === "solving");
    if (acquiring) showSession(acquiring);
    else await showStart();
    if (solving?.job_id) followJob(solving.job_id);
  }

  resume();
  timers.push(setInterval(listSessions, SESSION_POLL_MS));
  return () => {
    closed = true;
    clearTimeout(jobTimer);
    timers.forEach(clearInterval);
  };
}
