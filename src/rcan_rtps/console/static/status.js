// Live STATUS (the WebSocket's status frames) and the goals (its goal frames).
import { byId, fmt, h, put } from "./dom.js";

const TERMINAL = new Set(["succeeded", "aborted", "canceled", "lost", "rejected"]);
const KEEP_FINISHED = 5;

function fact(name, value, tone) {
  return [h("dt", {}, name), h("dd", { "data-fact": name, "data-tone": tone }, value)];
}

export function renderStatus(status) {
  const t = status.telemetry || {};
  const v = t.velocity;
  const nav = status.navigation;
  const battery = status.battery_pct;
  put(byId("facts"),
    ...fact("state", status.state, status.state === "estop" || status.state === "fault" ||
      status.state === "safe_stop" || status.state === "offline" ? "bad" : "ok"),
    ...fact("e-stop", status.estop ? "LATCHED" : "released", status.estop ? "bad" : "ok"),
    ...fact("battery", typeof battery === "number" ? fmt(battery, 0) + " %" : "–",
      typeof battery === "number" && battery < 20 ? "warn" : null),
    ...fact("velocity", v ? `${fmt(v.linear_x)} m/s, ${fmt(v.angular_z)} rad/s` : "–"),
    ...fact("ROS", status.ros && status.ros.connected ? "connected" : "not connected",
      status.ros && status.ros.connected ? "ok" : "bad"),
    ...fact("telemetry age", status.ros ? fmt(status.ros.last_telemetry_age_s, 1) + " s" : "–"),
    ...fact("waiting for approval", String(status.pending_auth)),
    ...(nav ? fact("navigation", `${nav.state}, ${fmt(nav.distance_remaining)} m left` +
      (typeof nav.eta_s === "number" ? `, ~${fmt(nav.eta_s, 0)} s` : "")) : []));
  const faults = status.faults || [];
  put(byId("faults"), ...(faults.length ? faults.map((f) =>
    h("li", { "data-tone": f.level === "WARN" ? "warn" : "bad" },
      `${f.level} ${f.name}: ${f.message}`)) : [h("li", { class: "empty" }, "none")]));
  renderForeign(status.foreign_publishers || [], status.foreign_publishers_count || 0);
  const joints = t.joints;
  const rows = joints ? joints.names.map((name, i) => h("tr", {},
    h("td", {}, name), h("td", {}, fmt(joints.positions[i], 3)),
    h("td", {}, fmt((joints.velocities || [])[i], 3)))) : [];
  put(byId("joints").tBodies[0], ...rows);
  document.body.dataset.estop = status.estop ? "latched" : "released";
}

/** Other nodes publishing where the bridge commands the robot: the robot obeys them too.
 *  Those the config declares (`expected`) are the robot's design; the others are a warning. */
function renderForeign(listed, count) {
  const items = listed.map((p) => h("li", {
    "data-foreign": `${p.topic} ${p.participant}`, "data-expected": String(!!p.expected),
    "data-tone": p.expected ? null : "warn" },
  h("strong", {}, p.node || `unnamed node (participant ${p.participant})`),
  ` on ${p.topic}`, h("span", { class: "mono" }, ` ${p.type}, ${p.writers} writer(s)`), " ",
  h("span", { "data-tone": p.expected ? "ok" : "warn" },
    p.expected ? "expected" : "not expected")));
  if (count > listed.length) items.push(h("li", {}, `and ${count - listed.length} more`));
  put(byId("foreign"), ...(items.length ? items : [h("li", { class: "empty" }, "none")]));
}

/** Goals as their frames tell them; the active ones first, then the last few finished. */
export class Goals {
  constructor() {
    this.goals = new Map();
    this.longest = new Map(); // goal id → the largest distance left seen (progress' 0 %)
  }

  offer(view) {
    this.goals.set(view.goal_id, view);
    const left = view.feedback && view.feedback.distance_remaining;
    if (typeof left === "number") {
      this.longest.set(view.goal_id, Math.max(left, this.longest.get(view.goal_id) || 0));
    }
    const finished = [...this.goals.values()].filter((g) => TERMINAL.has(g.state));
    for (const old of finished.slice(0, Math.max(0, finished.length - KEEP_FINISHED))) {
      this.goals.delete(old.goal_id);
      this.longest.delete(old.goal_id);
    }
    this.render();
  }

  render() {
    const views = [...this.goals.values()].sort((a, b) =>
      Number(TERMINAL.has(a.state)) - Number(TERMINAL.has(b.state)) || b.created_ms - a.created_ms);
    put(byId("goals"), ...(views.length ? views.map((g) => this.item(g))
      : [h("li", { class: "empty" }, "no goals")]));
  }

  item(g) {
    const left = g.feedback && g.feedback.distance_remaining;
    const longest = this.longest.get(g.goal_id);
    const progress = h("progress", { max: "1" });
    if (g.state === "succeeded") progress.value = 1;
    else if (typeof left === "number" && longest > 0) progress.value = 1 - left / longest;
    else progress.removeAttribute("value"); // indeterminate
    return h("li", { "data-goal": g.goal_id },
      h("div", {}, h("strong", {}, g.command || g.action), " ",
        h("span", { "data-tone": g.state === "succeeded" ? "ok" :
          TERMINAL.has(g.state) ? "bad" : null }, g.state)),
      progress,
      h("div", { class: "mono" }, typeof left === "number" ? `${fmt(left)} m left` : "",
        g.detail ? ` ${g.detail}` : ""));
  }
}
