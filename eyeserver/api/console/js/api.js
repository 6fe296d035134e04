// The daemon's API from the browser: the token, requests, images and streams.
//
// The token lives in this tab's sessionStorage only: never localStorage (it would outlive the
// tab) and never a cookie (the browser would send it by itself, to requests this page did not
// make). Every request carries it as "Authorization: Bearer"; a stream, whose browser API
// cannot set headers, as ?token= (the daemon's log redacts it).

export const API = "/api/v1";
const TOKEN_KEY = "eyeserver.token";

/** An answer other than 2xx: its status and the daemon's reason ({"detail": …}). */
export class ApiError extends Error {
  constructor(status, detail, path) {
    super(detail);
    this.status = status;
    this.detail = detail;
    this.path = path;
  }
}

let unauthorised = () => {};

/** Call `handler(reason)` whenever the daemon answers 401 (the token is no longer valid). */
export function onUnauthorised(handler) {
  unauthorised = handler;
}

export function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function setToken(value) {
  sessionStorage.setItem(TOKEN_KEY, value);
}

export function forgetToken() {
  sessionStorage.removeItem(TOKEN_KEY);
}

function url(path, query) {
  const target = new URL(API + path, location.origin);
  for (const [name, value] of Object.entries(query || {})) {
    if (value !== null && value !== undefined && value !== "") {
      target.searchParams.set(name, String(value));
    }
  }
  return target;
}

async function reason(response) {
  try {
    const body = await response.json();
    if (body && typeof body.detail === "string") return body.detail;
  } catch {
    // not JSON: the status text says what there is
  }
  return `${response.status} ${response.statusText}`.trim();
}

/**
 * A request to the API (`path` under /api/v1). `body` is sent as JSON; the answer's JSON is
 * returned (null for 204), or the Response itself with `raw`. Throws ApiError for any other
 * status, with the daemon's reason; a TypeError when the daemon cannot be reached.
 */
export async function request(method, path, {body, query, raw = false, signal} = {}) {
  const headers = {Accept: "application/json"};
  const current = token();
  if (current) headers.Authorization = `Bearer ${current}`;
  const options = {method, headers, signal, cache: "no-store", credentials: "omit"};
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  const response = await fetch(url(path, query), options);
  if (!response.ok) {
    const detail = await reason(response);
    if (response.status === 401) unauthorised(detail);
    throw new ApiError(response.status, detail, path);
  }
  if (raw) return response;
  if (response.status === 204) return null;
  const text = await response.text();
  return text ? JSON.parse(text) : null;
}

export const get = (path, options) => request("GET", path, options);
export const post = (path, body, options = {}) => request("POST", path, {...options, body});
export const put = (path, body, options = {}) => request("PUT", path, {...options, body});
export const patch = (path, body, options = {}) => request("PATCH", path, {...options, body});
export const del = (path, options) => request("DELETE", path, options);

/** An image (or any file) of the API as a blob: URL for <img>, which cannot send the token. */
export async function objectUrl(path, options = {}) {
  const response = await request("GET", path, {...options, raw: true});
  return URL.createObjectURL(await response.blob());
}

/** The bytes of a file of the API. */
export async function bytes(path, options = {}) {
  const response = await request("GET", path, {...options, raw: true});
  return response.arrayBuffer();
}

/** A WebSocket to one of the daemon's streams (/ws/events, /ws/pose). */
export function socket(path) {
  const target = url(path);
  target.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  target.searchParams.set("token", token() || "");
  return new WebSocket(target);
}

/** The path with each segment URL-encoded: ids from people (a patient id) stay one segment. */
export function at(...segments) {
  return "/" + segments.map((s) => encodeURIComponent(String(s))).join("/");
}

/** Save a file of the API (a calibration zip) through a temporary link. */
export async function download(path, filename) {
  const href = await objectUrl(path);
  const link = document.createElement("a");
  link.href = href;
  link.download = filename;
  document.body.appendChild(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(href), 10_000);
}

/** What to tell the user about a failed request: the daemon's reason and the status. */
export function reasonOf(error) {
  if (error instanceof ApiError) return `${error.detail} (HTTP ${error.status})`;
  return `Cannot reach the daemon: ${error.message}`;
}

/** Close a stream without a browser warning when it is still connecting: once it is open. */
export function hangUp(ws) {
  ws.onclose = null;
  ws.onmessage = null;
  if (ws.readyState === WebSocket.CONNECTING) ws.onopen = () => ws.close();
  else ws.close();
}
