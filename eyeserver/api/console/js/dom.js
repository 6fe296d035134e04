// Small DOM helpers. Text from the daemon always goes in as text nodes, never as markup.

/**
 * Create an element: h("button", {class: "primary", onclick: f, disabled: true}, "Start").
 * Attributes: `class`, `dataset` (object), `on<event>` (listener), booleans (set when true),
 * anything else with setAttribute. Children: strings, numbers, nodes, arrays; null and false
 * are skipped.
 */
export function h(tag, attrs = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name === "class") element.className = value;
    else if (name === "dataset") Object.assign(element.dataset, value);
    else if (name.startsWith("on") && typeof value === "function") {
      element.addEventListener(name.slice(2), value);
    } else if (value === true) element.setAttribute(name, "");
    else element.setAttribute(name, String(value));
  }
  append(element, children);
  return element;
}

function append(element, children) {
  for (const child of children) {
    if (child === null || child === undefined || child === false) continue;
    if (Array.isArray(child)) append(element, child);
    else if (child instanceof Node) element.appendChild(child);
    else element.appendChild(document.createTextNode(String(child)));
  }
}

/** Replace an element's children. */
export function replace(element, ...children) {
  element.replaceChildren();
  append(element, children);
  return element;
}

/** A number with `digits` decimals, or an en dash for none. */
export function num(value, digits = 2) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

/** A signed number (+0.012) for deviations. */
export function signed(value, digits = 3) {
  if (typeof value !== "number" || !Number.isFinite(value)) return "–";
  return (value >= 0 ? "+" : "") + value.toFixed(digits);
}

/** An ISO time from the daemon as local date and time, to the second. */
export function when(iso) {
  if (!iso) return "–";
  const date = new Date(iso);
  return Number.isNaN(date.getTime()) ? String(iso) : date.toLocaleString();
}

/** A labelled value for definition lists: [dt, dd]. */
export function field(label, value) {
  return [h("dt", {}, label), h("dd", {}, value)];
}

/** A panel with a heading. */
export function panel(title, ...children) {
  return h("section", {class: "panel"}, h("h2", {}, title), ...children);
}

/** A message line that says what went wrong (class "error") or how it went. */
export function message(kind, text) {
  return h("p", {class: kind, role: kind === "error" ? "alert" : "status"}, text);
}
