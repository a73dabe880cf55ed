// Talking to the flylib gui server: REST for reads, one WebSocket for edits.
// Every mutating request carries the session token the server put in this page's HTML
// (another origin cannot read it): a header on POSTs, a sub-protocol on the WebSocket.

const token = new URLSearchParams(location.search).get("token");
const sessionToken = document.querySelector('meta[name="flylib-token"]')?.content ?? "";

export function apiUrl(path) {
  return token ? `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}` : path;
}

async function failure(path, response) {
  // the server answers {"detail": "<one line>"}; show that, never raw HTML
  let detail = "";
  try { detail = (await response.json()).detail; } catch { detail = response.statusText; }
  const error = new Error(`${path}: ${detail || response.status}`);
  error.status = response.status;
  error.detail = detail;
  return error;
}

export async function getJSON(path) {
  const response = await fetch(apiUrl(path));
  if (!response.ok) throw await failure(path, response);
  return response.json();
}

export async function postJSON(path, body) {
  const response = await fetch(apiUrl(path), {
    method: "POST",
    headers: { "Content-Type": "application/json", "X-Flylib-Token": sessionToken },
    body: JSON.stringify(body ?? {}),
  });
  if (!response.ok) throw await failure(path, response);
  return response.json();
}

// Edits go over a WebSocket; each send() resolves with the server's reply, in order.
// {"op": "changed"} messages (another page edited) go to onChanged instead; once the
// connection is lost every send() resolves at once with {op: "not_stored"}.
export class EditChannel {
  constructor({ onLost, onChanged } = {}) {
    this.queue = [];
    this.onLost = onLost;
    this.onChanged = onChanged;
    this.lost = false;
    this.ready = this.connect();
  }

  connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    this.socket = new WebSocket(apiUrl(`${scheme}://${location.host}/ws`),
      ["flylib.v1", `flylib.token.${sessionToken}`]);
    this.socket.onmessage = (event) => {
      const message = JSON.parse(event.data);
      if (message.op === "changed") { this.onChanged?.(message); return; }
      const waiter = this.queue.shift();
      if (waiter) waiter(message);
    };
    this.socket.onclose = () => {
      this.lost = true;
      for (const waiter of this.queue.splice(0)) {
        waiter({ op: "not_stored", error: "the connection to flylib gui was lost before it confirmed this edit" });
      }
      this.onLost?.();
    };
    return new Promise((resolve) => {
      this.socket.onopen = resolve;
      this.socket.addEventListener("close", resolve);
    });
  }

  get busy() { return this.queue.length > 0; }

  async send(message) {
    await this.ready;
    if (this.lost) return { op: "not_stored", error: "flylib gui is not running; the edit was not stored" };
    return new Promise((resolve) => {
      this.queue.push(resolve);
      this.socket.send(JSON.stringify(message));
    });
  }
}
