// Talking to the flylib gui server: REST for reads, one WebSocket for edits.

const token = new URLSearchParams(location.search).get("token");

export function apiUrl(path) {
  return token ? `${path}${path.includes("?") ? "&" : "?"}token=${encodeURIComponent(token)}` : path;
}

export async function getJSON(path) {
  const response = await fetch(apiUrl(path));
  if (!response.ok) throw new Error(`${path}: ${response.status} ${await response.text()}`);
  return response.json();
}

export async function postJSON(path, body) {
  const response = await fetch(apiUrl(path), {
    method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body ?? {}),
  });
  if (!response.ok) throw new Error(`${path}: ${response.status} ${await response.text()}`);
  return response.json();
}

// Edits go over a WebSocket; each send() resolves with the server's reply, in order.
export class EditChannel {
  constructor(onStatus) {
    this.queue = [];
    this.onStatus = onStatus;
    this.ready = this.connect();
  }

  connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    this.socket = new WebSocket(apiUrl(`${scheme}://${location.host}/ws`));
    this.socket.onmessage = (event) => {
      const waiter = this.queue.shift();
      if (waiter) waiter(JSON.parse(event.data));
    };
    this.socket.onclose = () => {
      this.onStatus?.("connection to the server lost; reload the page after restarting `flylib gui`");
      for (const waiter of this.queue.splice(0)) waiter({ error: "connection lost" });
    };
    return new Promise((resolve) => { this.socket.onopen = resolve; });
  }

  get busy() { return this.queue.length > 0; }

  async send(message) {
    await this.ready;
    return new Promise((resolve) => {
      this.queue.push(resolve);
      this.socket.send(JSON.stringify(message));
    });
  }
}
