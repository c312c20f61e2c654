// The console: sign in, follow the role, keep one WebSocket open, keep the e-stop in reach.
import { Api, forgetToken, storeToken, storedToken } from "./api.js";
import { Approvals } from "./approvals.js";
import { AuditTail } from "./audit.js";
import { byId, show } from "./dom.js";
import { PosePlot } from "./plot.js";
import { Goals, renderStatus } from "./status.js";

const RECONNECT_MS = [500, 1000, 2000, 5000];

class Console {
  constructor() {
    this.api = null;
    this.whoami = null;
    this.ws = null;
    this.retries = 0;
    this.latched = false;
    this.signedIn = false;
    this.plot = new PosePlot(byId("plot"), byId("pose-text"));
    this.goals = new Goals();
    this.goals.render();
    this.approvals = null;
    this.audit = null;
    byId("sign-in-form").addEventListener("submit", (event) => {
      event.preventDefault();
      const token = byId("token").value.trim();
      byId("token").value = "";
      if (token) this.signIn(token);
    });
    byId("sign-out").addEventListener("click", () => this.signOut());
    byId("estop").addEventListener("click", () => this.estop());
    byId("clear-estop").addEventListener("click", () => this.clearEstop());
    byId("plot-fit").addEventListener("click", () => {
      byId("plot-fit").textContent = this.plot.toggleFit() ? "Follow robot" : "Whole workspace";
    });
    const token = storedToken();
    if (token) this.signIn(token);
    else this.showSignIn("");
  }

  showSignIn(error) {
    show(byId("sign-in"), true);
    show(byId("console"), false);
    byId("sign-in-error").textContent = error;
    byId("token").focus();
  }

  async signIn(token) {
    const api = new Api(token);
    let reply;
    try {
      reply = await api.json("GET", "/api/whoami");
    } catch (err) {
      this.showSignIn(`the bridge did not answer: ${err.message}`);
      return;
    }
    if (reply.status !== 200) {
      forgetToken();
      this.showSignIn(reply.status === 401 ? "token refused" : `sign-in failed (${reply.status})`);
      return;
    }
    storeToken(token);
    this.api = api;
    this.whoami = reply.body;
    this.signedIn = true;
    this.followRole();
    show(byId("sign-in"), false);
    show(byId("console"), true);
    this.loadManifest();
    this.connect();
  }

  followRole() {
    const me = this.whoami;
    byId("principal").textContent = `${me.principal} (${me.role})`;
    document.body.dataset.role = me.role;
    show(byId("estop"), true); // every principal may stop the robot
    show(byId("sign-out"), true);
    show(byId("approvals-card"), me.may.approve);
    show(byId("audit-card"), me.may.read_audit);
    const readOnly = !me.may.command && !me.may.approve;
    show(byId("guest-note"), readOnly);
    if (readOnly) {
      byId("guest-text").textContent = `Signed in as ${me.role}: you see the robot and may ` +
        "raise the e-stop. Approvals, clearing the e-stop and the audit need a higher role.";
    }
    if (me.may.approve) this.approvals = new Approvals(this.api, me, (m, bad) => this.notice(m, bad));
    if (me.may.read_audit) this.audit = new AuditTail(this.api, (m, bad) => this.notice(m, bad));
  }

  async loadManifest() {
    try {
      const manifest = await this.api.get("/api/safety/manifest");
      byId("robot-name").textContent = manifest.ruri;
      this.plot.setWorkspace(manifest.workspace ? manifest.workspace.polygon : null);
    } catch (err) {
      this.notice(`safety manifest: ${err.message}`, true);
    }
  }

  async connect() {
    if (!this.signedIn) return;
    let ws;
    try {
      ws = await this.api.socket();
    } catch (err) {
      if (err.status === 401) {
        this.signOut();
        return;
      }
      this.retry();
      return;
    }
    this.ws = ws;
    ws.addEventListener("open", () => {
      this.retries = 0;
      this.link(true);
    });
    ws.addEventListener("message", (event) => this.frame(event.data));
    ws.addEventListener("close", () => {
      this.link(false);
      if (this.ws === ws) this.retry();
    });
  }

  retry() {
    if (!this.signedIn) return;
    const wait = RECONNECT_MS[Math.min(this.retries, RECONNECT_MS.length - 1)];
    this.retries += 1;
    setTimeout(() => this.connect(), wait);
  }

  link(on) {
    const badge = byId("link");
    badge.dataset.state = on ? "on" : "off";
    badge.textContent = on ? "live" : "offline";
  }

  frame(data) {
    let frame;
    try {
      frame = JSON.parse(data);
    } catch (_) {
      return;
    }
    if (frame.type === "status") this.status(frame.body);
    else if (frame.type === "goal") this.goals.offer(frame.body);
    else if (frame.type === "approvals" && this.approvals) this.approvals.offer(frame.body);
  }

  status(status) {
    renderStatus(status);
    const t = status.telemetry || {};
    this.plot.update(t.position, t.yaw);
    this.showLatched(status.estop);
  }

  showLatched(latched) {
    this.latched = latched;
    document.body.dataset.estop = latched ? "latched" : "released";
    const banner = byId("banner");
    banner.textContent = latched ? "E-STOP LATCHED: the robot is stopped" : "";
    show(banner, latched);
    show(byId("clear-estop"), latched && this.whoami.may.clear_estop);
  }

  async estop() {
    // One touch, no confirmation: said at once, over REST (it works with the socket down).
    const button = byId("estop");
    button.textContent = "STOPPING…";
    try {
      const { status, body } = await this.api.command({ action: "estop" });
      if (status === 200) this.showLatched(true);
      else this.notice(`e-stop: ${status} ${(body && body.reason) || ""}`, true);
    } catch (err) {
      this.notice(`e-stop not sent: ${err.message}`, true);
    } finally {
      button.textContent = "E-STOP";
    }
  }

  async clearEstop() {
    const { status, body } = await this.api.command({ action: "clear_estop" });
    if (status === 200) this.showLatched(false);
    else this.notice(`clear: ${status} ${(body && (body.reason || body.outcome)) || ""}`, true);
  }

  notice(message, bad) {
    const box = byId("notice");
    box.textContent = message;
    box.dataset.tone = bad ? "bad" : "ok";
    show(box, true);
    clearTimeout(this.noticeTimer);
    this.noticeTimer = setTimeout(() => show(box, false), 8000);
  }

  signOut() {
    this.signedIn = false;
    forgetToken();
    if (this.ws) {
      const ws = this.ws;
      this.ws = null;
      ws.close();
    }
    location.reload(); // a fresh page: nothing of this principal's view is left

  }
}

new Console();
