// Devices (physicists): every device's health and the reason of a fault, the units, and the
// settings a physicist may change (PATCH /devices/{id}: a projector's enabled and intensity, a
// camera's exposure and gain). The daemon checks each value against the device's range and
// answers 422 with the reason, shown next to the device.

import {at, get, patch, reasonOf} from "../api.js";
import {h, message, num, panel, replace} from "../dom.js";

const POLL_MS = 3000;

export function mount(container, ctx) {
  const units = h("div", {id: "units"});
  const list = h("div", {id: "device-list", class: "devices"});
  container.append(panel("Units", units), panel("Devices", list));
  const editing = new Set(); // forms being edited are not redrawn under the user's hands

  function showUnits(status) {
    replace(units, h("table", {class: "table"},
      h("thead", {}, h("tr", {}, ["unit", "projector", "cameras", "health"].map(
        (name) => h("th", {}, name)))),
      h("tbody", {}, status.units.map((u) => h("tr", {dataset: {unit: u.id}},
        h("td", {}, u.id), h("td", {}, u.projector), h("td", {}, u.cameras.join(", ")),
        h("td", {}, health(u.health, u.reason)))))));
  }

  async function load() {
    let devices;
    try {
      devices = await get("/devices");
    } catch (error) {
      replace(list, message("error", reasonOf(error)));
      return;
    }
    for (const device of devices) {
      if (editing.has(device.id)) continue;
      const card = list.querySelector(`[data-device="${CSS.escape(device.id)}"]`);
      const fresh = deviceCard(device);
      if (card) card.replaceWith(fresh);
      else list.appendChild(fresh);
    }
  }

  function deviceCard(device) {
    const details = device.details || {};
    const feedback = h("div", {class: "device-message"});
    const inputs = {};
    let settings = [];
    if (device.kind === "projector") {
      inputs.enabled = h("input", {type: "checkbox", checked: Boolean(details.enabled)});
      inputs.intensity = h("input", {type: "number", step: "any",
        value: details.intensity ?? "", class: "narrow"});
      settings = [h("label", {}, inputs.enabled, " enabled"),
        h("label", {}, "intensity ", inputs.intensity)];
    } else if (device.kind === "camera") {
      inputs.exposure_us = h("input", {type: "number", step: "any",
        value: details.exposure_us ?? "", class: "narrow"});
      inputs.gain_db = h("input", {type: "number", step: "any", value: details.gain_db ?? "",
        class: "narrow"});
      settings = [h("label", {}, "exposure ", inputs.exposure_us, " µs"),
        h("label", {}, "gain ", inputs.gain_db, " dB")];
    }
    async function apply(event) {
      event.preventDefault();
      const changes = {};
      if (inputs.enabled) changes.enabled = inputs.enabled.checked;
      for (const name of ["intensity", "exposure_us", "gain_db"]) {
        if (inputs[name] && inputs[name].value !== "") changes[name] = Number(inputs[name].value);
      }
      try {
        const updated = await patch(at("devices", device.id), changes);
        editing.delete(device.id);
        const fresh = deviceCard(updated);
        card.replaceWith(fresh);
        fresh.querySelector(".device-message").replaceChildren(message("ok", "Applied."));
      } catch (error) {
        replace(feedback, message("error", reasonOf(error)));
      }
    }

    // No range in the form: the daemon checks each value against the device (one place) and
    // its 422 says why.
    const form = settings.length ? h("form", {class: "inline", novalidate: true,
      onsubmit: apply, oninput: () => editing.add(device.id)}, settings,
    h("button", {type: "submit", class: "apply"}, "Apply"),
    h("button", {type: "button", onclick: () => {
      editing.delete(device.id);
      load();
    }}, "Revert")) : null;
    const shown = Object.entries(details).filter(([k]) => !["id", "kind", "driver", "open"]
      .includes(k));
    const card = h("article", {class: `device health-${device.health}`,
      dataset: {device: device.id, health: device.health}},
    h("header", {}, h("strong", {}, device.id), ` ${device.kind} · ${device.driver}`
      + (device.unit ? ` · unit ${device.unit}` : " · every unit"), " ",
    health(device.health, device.reason)),
    h("dl", {class: "facts compact"}, shown.map(([k, v]) => [h("dt", {}, k),
      h("dd", {}, typeof v === "number" ? num(v, Number.isInteger(v) ? 0 : 2)
        : v !== null && typeof v === "object" ? JSON.stringify(v) : String(v))])),
    form, feedback);
    return card;
  }

  const onStatus = (event) => showUnits(event.detail);
  const onEvent = (event) => {
    if (event.detail.type.startsWith("device.")) load();
  };
  ctx.events.addEventListener("status", onStatus);
  ctx.events.addEventListener("event", onEvent);
  if (ctx.status) showUnits(ctx.status);
  load();
  const timer = setInterval(load, POLL_MS);
  return () => {
    clearInterval(timer);
    ctx.events.removeEventListener("status", onStatus);
    ctx.events.removeEventListener("event", onEvent);
  };
}

function health(value, reason) {
  return h("span", {class: `badge health-${value}`, title: reason || ""},
    value === "ok" ? "ok" : `fault: ${reason}`);
}
