// The console's shell: login, the caller's role, the views it may see, the daemon's state and
// the daily QA's lockout (GET /qa/status: a badge in the top bar, ctx.qa for the views).
//
// The role comes from GET /api/v1/whoami; a view (and every action in a view) needing a role
// the caller lacks is not shown at all. The daemon refuses such requests anyway (403): hiding
// them only spares the user a button that cannot work.

import {
  ApiError, forgetToken, get, hangUp, onUnauthorised, setToken, socket, token,
} from "./api.js";
import {h, replace} from "./dom.js";
import * as audit from "./views/audit.js";
import * as calibration from "./views/calibration.js";
import * as devices from "./views/devices.js";
import * as history from "./views/history.js";
import * as qa from "./views/qa.js";
import * as reconstruction from "./views/reconstruction.js";
import * as therapist from "./views/therapist.js";

const VIEWS = [
  {id: "therapist", title: "Therapist", role: "operator", view: therapist},
  {id: "qa", title: "Daily QA", role: "operator", view: qa},
  {id: "calibration", title: "Guided calibration", role: "physicist", view: calibration},
  {id: "calibrations", title: "Calibration history", role: "physicist", view: history},
  {id: "devices", title: "Devices", role: "physicist", view: devices},
  {id: "reconstruction", title: "Reconstruction", role: "physicist", view: reconstruction},
  {id: "audit", title: "Audit trail", role: "physicist", view: audit},
];

const STATUS_POLL_MS = 5000;
const $ = (id) => document.getElementById(id);

/** What every view is given: the caller, the daemon's status and its events. */
class Context {
  constructor(me) {
    this.me = me;
    this.status = null;
    this.qa = null; // GET /qa/status: whether the daily QA locks verification and tracking
    this.events = new EventTarget();
  }

  /** Whether the caller has `role` (or a higher one). */
  may(role) {
    return this.me.roles.includes(role);
  }

  /** Whether the daemon drives the simulated room (every device a simulated one). */
  get simulated() {
    const devices = this.status?.devices || [];
    return devices.length > 0 && devices.every((d) => d.driver.startsWith("Sim"));
  }

  async refreshStatus() {
    this.status = await get("/status");
    this.events.dispatchEvent(new CustomEvent("status", {detail: this.status}));
    showStatus(this.status);
    return this.status;
  }

  /** Ask the daemon whether the daily QA locks verification and tracking (a "qa" event). */
  async refreshQa() {
    this.qa = await get("/qa/status");
    this.events.dispatchEvent(new CustomEvent("qa", {detail: this.qa}));
    showQa(this.qa);
    return this.qa;
  }

  /** Show `text` in the banner under the top bar (null hides it). */
  banner(text) {
    const element = $("banner");
    element.hidden = !text;
    element.textContent = text || "";
  }
}

let context = null;
let current = null; // {id, cleanup}
let eventSocket = null;
let reconnect = null;
let statusTimer = null;

function showLogin(reason) {
  $("app").hidden = true;
  $("login").hidden = false;
  const error = $("login-error");
  error.hidden = !reason;
  error.textContent = reason || "";
  $("login-token").value = "";
  $("login-token").focus();
}

async function login(event) {
  event.preventDefault();
  const value = $("login-token").value.trim();
  if (!value) return;
  $("login-submit").disabled = true;
  setToken(value);
  try {
    await start();
  } catch (error) {
    forgetToken();
    showLogin(loginFailure(error));
  } finally {
    $("login-submit").disabled = false;
  }
}

function loginFailure(error) {
  if (error instanceof ApiError) {
    return error.status === 401 ? `The daemon refused the token: ${error.detail}`
      : `The daemon answered ${error.status}: ${error.detail}`;
  }
  return `Cannot reach the daemon: ${error.message}`;
}

function logout(reason) {
  stop();
  forgetToken();
  showLogin(reason);
}

/** Ask the daemon who the token belongs to, then show the views its role may see. */
async function start() {
  const me = await get("/whoami");
  context = new Context(me);
  $("login").hidden = true;
  $("app").hidden = false;
  replace($("whoami"), h("span", {class: "name"}, me.name), " ",
    h("span", {class: `role role-${me.role}`, id: "role"}, me.role));
  replace($("nav"), VIEWS.filter((v) => context.may(v.role)).map(
    (v) => h("a", {href: `#/${v.id}`, id: `nav-${v.id}`, dataset: {view: v.id}}, v.title)));
  await context.refreshStatus().catch((error) => context.banner(`Status: ${error.message}`));
  await context.refreshQa().catch(() => showQa(null));
  statusTimer = setInterval(() => {
    context?.refreshStatus().catch(() => {});
    context?.refreshQa().catch(() => {});
  }, STATUS_POLL_MS);
  openEvents(0);
  route();
}

function stop() {
  clearInterval(statusTimer);
  clearTimeout(reconnect);
  statusTimer = reconnect = null;
  if (eventSocket) {
    hangUp(eventSocket);
    eventSocket = null;
  }
  unmount();
  context = null;
}

function showStatus(status) {
  const state = $("daemon-state");
  state.textContent = status.state;
  state.className = `badge state-${status.state}`;
  state.dataset.state = status.state;
  $("version").textContent = `eyeserver ${status.version}`;
  const faults = status.units.filter((u) => u.health !== "ok");
  const devices = status.devices.filter((d) => d.health !== "ok" && !d.unit);
  const reasons = [...faults.map((u) => `${u.id}: ${u.reason}`),
    ...devices.map((d) => `${d.id}: ${d.reason}`)];
  context?.banner(reasons.length ? `Fault — ${reasons.join("; ")}` : null);
}

/** The daily QA's lockout in the top bar: locked (red), overridden, passed or not required. */
function showQa(status) {
  const badge = $("qa-state");
  badge.hidden = !status;
  if (!status) return;
  const [text, kind] = status.locked ? ["QA locked", "locked"]
    : status.override ? ["QA overridden", "override"]
      : status.qa_reason ? ["QA not required", "off"] : ["QA passed", "passed"];
  badge.textContent = text;
  badge.className = `badge qa-${kind}`;
  badge.dataset.locked = String(status.locked);
  badge.title = status.locked ? `Verification and tracking are locked: ${status.reason}`
    : status.qa_reason ? `The daily QA lacks: ${status.qa_reason}` : "Today's QA passed";
}

/** The daemon's event stream: state changes and stored captures reach the views at once. */
function openEvents(attempt) {
  const link = $("daemon-link");
  const ws = socket("/ws/events");
  eventSocket = ws;
  ws.onopen = () => {
    link.textContent = "live";
    link.className = "badge link-up";
    attempt = 0;
  };
  ws.onmessage = (message) => {
    const event = JSON.parse(message.data);
    if (event.type === "state" || event.type === "hello" || event.type.startsWith("device.")
        || event.type === "calibration.activated") {
      context?.refreshStatus().catch(() => {});
    }
    if (event.type === "hello" || event.type.startsWith("qa.")
        || event.type === "calibration.activated") {
      context?.refreshQa().catch(() => {});
    }
    context?.events.dispatchEvent(new CustomEvent("event", {detail: event}));
  };
  ws.onclose = (close) => {
    if (eventSocket !== ws || !context) return;
    if (close.code === 1008) {
      logout(`The daemon closed the event stream: ${close.reason}`);
      return;
    }
    link.textContent = "reconnecting";
    link.className = "badge link-down";
    const delay = Math.min(10_000, 500 * 2 ** attempt);
    reconnect = setTimeout(() => openEvents(attempt + 1), delay);
  };
}

function unmount() {
  if (current?.cleanup) {
    try {
      current.cleanup();
    } catch (error) {
      console.warn("leaving the view:", error);
    }
  }
  current = null;
}

function route() {
  if (!context) return;
  const id = (location.hash.match(/^#\/([\w-]+)/) || [])[1] || "therapist";
  const entry = VIEWS.find((v) => v.id === id) || VIEWS[0];
  // The view shown already (the first view, shown without a hash, then its own link clicked):
  // left as it is, not mounted anew over what was typed into it.
  if (current?.id === entry.id) return;
  unmount();
  for (const link of $("nav").querySelectorAll("a")) {
    link.classList.toggle("active", link.dataset.view === entry.id);
  }
  const container = replace($("view"));
  container.dataset.view = entry.id;
  if (!context.may(entry.role)) {
    // Nothing is asked of the daemon for a view the role may not see.
    container.appendChild(h("section", {class: "panel"}, h("h2", {}, entry.title),
      h("p", {class: "error", id: "view-refused"}, `This view needs the ${entry.role} role; `
        + `${context.me.name} is ${context.me.role}.`)));
    current = {id: entry.id, cleanup: null};
    return;
  }
  current = {id: entry.id, cleanup: entry.view.mount(container, context)};
}

onUnauthorised((reason) => {
  if (context) logout(`The daemon no longer accepts the token: ${reason}`);
});
window.addEventListener("hashchange", route);
$("login-form").addEventListener("submit", login);
$("logout").addEventListener("click", () => logout(null));

if (token()) {
  start().catch((error) => {
    forgetToken();
    showLogin(loginFailure(error));
  });
} else {
  showLogin(null);
}
