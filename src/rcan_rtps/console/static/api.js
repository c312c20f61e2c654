// The bridge's API, as the console uses it. The bearer token lives in sessionStorage only
// (this tab, until it closes; never a cookie, never localStorage) and goes in the
// Authorization header of same-origin requests. The WebSocket, which a browser cannot give
// a header, is opened with a single-use ticket from POST /api/ws-ticket.

const KEY = "rcan-rtps.token";

export function storedToken() {
  return sessionStorage.getItem(KEY);
}

export function storeToken(token) {
  sessionStorage.setItem(KEY, token);
}

export function forgetToken() {
  sessionStorage.removeItem(KEY);
}

export class ApiError extends Error {
  constructor(status, body) {
    super((body && (body.reason || body.error_code)) || "HTTP " + status);
    this.status = status;
    this.body = body;
  }
}

export class Api {
  constructor(token) {
    this.token = token;
  }

  async request(method, path, body) {
    const headers = { Authorization: "Bearer " + this.token };
    const init = { method, headers, credentials: "omit", cache: "no-store", redirect: "error" };
    if (body !== undefined) {
      headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    const response = await fetch(path, init);
    return response;
  }

  async json(method, path, body) {
    const response = await this.request(method, path, body);
    let parsed = null;
    try {
      parsed = await response.json();
    } catch (_) {
      parsed = null;
    }
    return { status: response.status, body: parsed };
  }

  async get(path) {
    const { status, body } = await this.json("GET", path);
    if (status !== 200) throw new ApiError(status, body);
    return body;
  }

  command(body) {
    return this.json("POST", "/api/command", body);
  }

  async blob(path) {
    const response = await this.request("GET", path);
    if (response.status !== 200) throw new ApiError(response.status, null);
    return response.blob();
  }

  /** A WebSocket to /api/ws (a fresh ticket each time). */
  async socket() {
    const { status, body } = await this.json("POST", "/api/ws-ticket");
    if (status !== 200) throw new ApiError(status, body);
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const url = scheme + "//" + location.host + body.ws_path + "?ticket=" +
      encodeURIComponent(body.ticket);
    return new WebSocket(url);
  }
}
