// The audit tail (GET /api/audit, polled from the last seq seen), its filters, the chain and
// tree-head verification (GET /api/audit/verify) and the §20 export (GET /api/v1/audit).
import { byId, h, put, when } from "./dom.js";

const TAIL = 200; // entries shown at most
const POLL_MS = 2000;

function detail(e) {
  const parts = [];
  if (e.deny_reason) parts.push(e.deny_reason);
  if (e.ai) {
    if (e.ai.model) parts.push(`model ${e.ai.model}`);
    if (e.ai.thought_id) parts.push(`thought ${e.ai.thought_id}`);
    if (typeof e.ai.confidence === "number") parts.push(`confidence ${e.ai.confidence}`);
  }
  if (e.params && Object.keys(e.params).length) parts.push(JSON.stringify(e.params));
  if (e.pending_id) parts.push(`pending ${e.pending_id}`);
  return parts.join(" · ");
}

export class AuditTail {
  constructor(api, notify) {
    this.api = api;
    this.notify = notify;
    this.entries = [];
    this.since = null;
    this.events = new Set();
    this.outcomes = new Set();
    this.stopped = false;
    for (const id of ["f-event", "f-outcome", "f-principal", "f-text"]) {
      byId(id).addEventListener("input", () => this.render());
    }
    byId("verify-run").addEventListener("click", () => this.verify());
    byId("export-jsonl").addEventListener("click", () => this.download("jsonl"));
    byId("export-csv").addEventListener("click", () => this.download("csv"));
    this.poll();
    this.verify();
  }

  stop() {
    this.stopped = true;
    clearTimeout(this.timer);
  }

  async poll() {
    try {
      if (this.since === null) {
        const head = await this.api.get("/api/audit?since=0&limit=1");
        this.since = Math.max(0, head.head_seq - TAIL);
      }
      const page = await this.api.get(`/api/audit?since=${this.since}`);
      if (page.entries.length) {
        this.entries.push(...page.entries);
        this.entries = this.entries.slice(-TAIL);
        this.since = page.next_since;
        this.render();
      }
    } catch (err) {
      if (err.status === 401) return; // signed out
    }
    if (!this.stopped) this.timer = setTimeout(() => this.poll(), POLL_MS);
  }

  options(select, values, seen) {
    let added = false;
    for (const v of values) {
      if (v && !seen.has(v)) {
        seen.add(v);
        added = true;
      }
    }
    if (!added) return;
    const chosen = select.value;
    put(select, h("option", { value: "" }, "any"),
      ...[...seen].sort().map((v) => h("option", { value: v }, v)));
    select.value = chosen;
  }

  render() {
    this.options(byId("f-event"), this.entries.map((e) => e.event), this.events);
    this.options(byId("f-outcome"), this.entries.map((e) => e.outcome), this.outcomes);
    const event = byId("f-event").value;
    const outcome = byId("f-outcome").value;
    const who = byId("f-principal").value.trim().toLowerCase();
    const text = byId("f-text").value.trim().toLowerCase();
    const shown = this.entries.filter((e) => (!event || e.event === event) &&
      (!outcome || e.outcome === outcome) &&
      (!who || String(e.principal || "").toLowerCase().includes(who)) &&
      (!text || JSON.stringify(e).toLowerCase().includes(text))).reverse();
    put(byId("audit").tBodies[0], ...shown.map((e) => h("tr", { "data-seq": String(e.seq) },
      h("td", {}, String(e.seq)), h("td", {}, when(e.timestamp_ms)), h("td", {}, e.event),
      h("td", {}, e.principal || ""), h("td", {}, e.action_type || ""),
      h("td", {}, e.outcome || ""), h("td", { class: "mono" }, detail(e)))));
  }

  async verify() {
    const box = byId("verify");
    box.dataset.state = "running";
    byId("verify-text").textContent = "verifying…";
    try {
      const r = await this.api.get("/api/audit/verify");
      box.dataset.state = r.ok ? "ok" : "bad";
      byId("verify-text").textContent = r.ok
        ? `chain verified: ${r.count} entries, signed tree heads ${r.tree_heads ?? 0}` +
          ` (size ${r.tree_size ?? "–"}), at ${when(Date.now())}`
        : `VERIFICATION FAILED at seq ${r.bad_seq ?? "?"}: ${r.detail || ""}`;
    } catch (err) {
      box.dataset.state = "bad";
      byId("verify-text").textContent = `could not verify: ${err.message}`;
    }
  }

  async download(format) {
    try {
      const blob = await this.api.blob(`/api/v1/audit?format=${format}`);
      const url = URL.createObjectURL(blob);
      const link = h("a", { href: url, download: `audit.${format}` });
      document.body.append(link);
      link.click();
      link.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
    } catch (err) {
      this.notify(`export failed: ${err.message}`, true);
    }
  }
}
