// Held commands (the WebSocket's approvals frames), for principals who may review them.
import { byId, fmt, h, put, when } from "./dom.js";

export class Approvals {
  constructor(api, whoami, notify) {
    this.api = api;
    this.covers = new Set(whoami.covers);
    // Under a `required` signature policy an approval must be signed, which this page
    // cannot do: it offers Deny only (a denial needs no signature) and says so.
    this.mustSign = Boolean(whoami.may && whoami.may.must_sign_approvals);
    this.notify = notify;
    this.pending = [];
    this.reasons = new Map(); // pending id → reason typed so far (kept across re-renders)
    this.busy = new Set();
    this.timer = setInterval(() => this.tick(), 1000);
  }

  stop() {
    clearInterval(this.timer);
  }

  offer(body) {
    this.pending = body.pending || [];
    this.render();
  }

  tick() {
    for (const node of document.querySelectorAll("[data-expires]")) {
      node.textContent = this.left(Number(node.dataset.expires));
    }
  }

  left(expiresMs) {
    const s = Math.round((expiresMs - Date.now()) / 1000);
    return s > 0 ? `in ${s} s (${when(expiresMs)})` : "expired";
  }

  render() {
    byId("approvals-count").textContent = String(this.pending.length);
    put(byId("approvals"), ...(this.pending.length ? this.pending.map((p) => this.item(p))
      : [h("li", { class: "empty" }, "nothing waits")]));
  }

  item(p) {
    const cmd = p.original_command || {};
    const mine = this.covers.has(p.requires_auth_from_role);
    const reason = h("input", { type: "text", placeholder: "reason (recorded in the audit)",
                                maxlength: "256", "aria-label": "reason" });
    reason.value = this.reasons.get(p.pending_id) || "";
    reason.addEventListener("input", () => this.reasons.set(p.pending_id, reason.value));
    const approvals = (p.approvals || []).filter((a) => a.decision === "approve");
    const meta = [
      ["from", p.issued_by],
      ["AI model", p.ai_model || "–"],
      ["confidence", typeof p.confidence === "number" ? fmt(p.confidence, 2) : "–"],
      ["needs", `${p.requires_auth_from_role} (${approvals.length} of ${p.approvals_required})`],
      ["message", cmd.message_id || "–"],
    ];
    const expires = h("dd", { "data-expires": String(p.expires_at_ms) },
      this.left(p.expires_at_ms));
    const approve = this.mustSign
      ? h("p", { class: "signed-only" }, "Your approvals must be signed: approve from a " +
          "signing client (a signed AUTHORIZE). Denying needs no signature.")
      : this.button("Approve", "approve", p, reason);
    const actions = mine ? h("div", { class: "actions" }, reason, approve,
      this.button("Deny", "deny", p, reason)) : h("p", {}, "another role reviews this one");
    return h("li", { class: "approval", "data-pending": p.pending_id },
      h("div", { class: "what" }, String(cmd.action || "?")),
      h("pre", { class: "params mono" }, JSON.stringify(cmd.params || {}, null, 1)),
      h("dl", { class: "meta" }, ...meta.flatMap(([k, v]) => [h("dt", {}, k), h("dd", {}, v)]),
        h("dt", {}, "expires"), expires),
      actions);
  }

  button(label, verdict, p, reason) {
    const button = h("button", { type: "button", class: verdict, "data-verdict": verdict },
      label);
    button.disabled = this.busy.has(p.pending_id);
    button.addEventListener("click", () => this.review(verdict, p.pending_id, reason.value));
    return button;
  }

  async review(verdict, pendingId, reason) {
    this.busy.add(pendingId);
    this.render();
    const path = verdict === "approve" ? "/api/hitl/authorize" : "/api/hitl/deny";
    const body = { pending_id: pendingId };
    if (reason.trim()) body.reason = reason.trim();
    try {
      const { status, body: reply } = await this.api.json("POST", path, body);
      this.notify(this.said(verdict, status, reply), status >= 400);
      if (status < 400) this.reasons.delete(pendingId);
    } catch (err) {
      this.notify(`${verdict} failed: ${err.message}`, true);
    } finally {
      this.busy.delete(pendingId);
      this.render();
    }
  }

  said(verdict, status, reply) {
    const refused = reply && reply.error_code;
    const what = refused ? `${reply.error_code} ${reply.reason || ""}` : (reply && reply.outcome);
    const line = `${verdict}: ${status} ${what || ""}`.trim();
    if (refused && String(reply.error_code).startsWith("SIGNATURE_")) {
      return `${line}: this principal's approvals must be signed; approve from a signing client`;
    }
    return line;
  }
}
