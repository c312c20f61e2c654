// The robot's pose on a 2-D plot: SVG in world units (1 unit = 1 m, y up, so SVG's y is the
// world's −y), the workspace polygon from the safety manifest, the trail driven so far.
import { s, put } from "./dom.js";

const TRAIL_MAX = 2000; // points kept
const TRAIL_STEP = 0.02; // m: closer points are not added
const FOLLOW_PAD = 1.5; // m around the trail and the robot
const FOLLOW_MIN = 6; // m: the smallest span shown

export class PosePlot {
  constructor(container, readout) {
    this.readout = readout;
    this.workspace = null;
    this.trail = [];
    this.robot = null;
    this.fit = false; // false: follow the robot; true: the whole workspace
    this.view = null;
    this.svg = s("svg", { viewBox: "-3 -3 6 6", preserveAspectRatio: "xMidYMid meet",
                          role: "img", "aria-label": "robot pose" });
    this.grid = s("g", { class: "gridlines" });
    this.area = s("polygon", { class: "workspace", id: "workspace" });
    this.path = s("polyline", { class: "trail", id: "trail" });
    this.marker = s("g", { id: "robot", class: "robot" },
      s("circle", { class: "robot-body", r: "0.25" }),
      s("polygon", { class: "robot-nose", points: "0.3,0 0.05,0.12 0.05,-0.12" }));
    this.marker.setAttribute("visibility", "hidden");
    this.svg.append(this.area, this.grid, this.path, this.marker);
    put(container, this.svg);
  }

  setWorkspace(polygon) {
    this.workspace = Array.isArray(polygon) && polygon.length >= 3 ? polygon : null;
    this.area.setAttribute("points", this.workspace
      ? this.workspace.map(([x, y]) => `${x},${-y}`).join(" ") : "");
    this.refit();
  }

  toggleFit() {
    this.fit = !this.fit;
    this.refit();
    return this.fit;
  }

  update(position, yaw) {
    if (!position || typeof position.x !== "number" || typeof position.y !== "number") return;
    const { x, y } = position;
    const last = this.trail[this.trail.length - 1];
    if (!last || Math.hypot(x - last[0], y - last[1]) >= TRAIL_STEP) {
      this.trail.push([x, y]);
      if (this.trail.length > TRAIL_MAX) this.trail.shift();
      this.path.setAttribute("points", this.trail.map(([px, py]) => `${px},${-py}`).join(" "));
    }
    const degrees = typeof yaw === "number" ? (-yaw * 180) / Math.PI : 0;
    this.marker.setAttribute("transform",
      `translate(${x.toFixed(3)},${(-y).toFixed(3)}) rotate(${degrees.toFixed(1)})`);
    this.marker.setAttribute("data-x", x.toFixed(3));
    this.marker.setAttribute("data-y", y.toFixed(3));
    this.marker.setAttribute("visibility", "visible");
    this.robot = [x, y];
    this.readout.textContent = `x ${x.toFixed(2)} m, y ${y.toFixed(2)} m` +
      (typeof yaw === "number" ? `, yaw ${((yaw * 180) / Math.PI).toFixed(0)}°` : "");
    this.refit();
  }

  refit() {
    const points = this.fit && this.workspace ? this.workspace
      : [...this.trail.slice(-400), ...(this.robot ? [this.robot] : [])];
    if (!points.length) return;
    const xs = points.map((p) => p[0]);
    const ys = points.map((p) => p[1]);
    const pad = this.fit ? 1 : FOLLOW_PAD;
    let [x0, x1] = [Math.min(...xs) - pad, Math.max(...xs) + pad];
    let [y0, y1] = [Math.min(...ys) - pad, Math.max(...ys) + pad];
    const span = Math.max(x1 - x0, y1 - y0, FOLLOW_MIN);
    const cx = (x0 + x1) / 2;
    const cy = (y0 + y1) / 2;
    [x0, x1, y0, y1] = [cx - span / 2, cx + span / 2, cy - span / 2, cy + span / 2];
    // Snap to whole metres so small moves do not redraw the grid at every STATUS.
    const snap = (v, down) => (down ? Math.floor(v) : Math.ceil(v));
    const view = [snap(x0, true), snap(-y1, true), snap(x1, false), snap(-y0, false)];
    const key = view.join(",");
    if (key === this.view) return;
    this.view = key;
    const [left, top, right, bottom] = view;
    const size = Math.max(right - left, bottom - top);
    this.svg.setAttribute("viewBox", `${left} ${top} ${size} ${size}`);
    this.drawGrid(left, top, size);
  }

  drawGrid(left, top, size) {
    const step = size <= 30 ? 1 : size <= 150 ? 5 : 25;
    const lines = [];
    for (let v = Math.ceil(left / step) * step; v <= left + size; v += step) {
      lines.push(s("line", { class: v === 0 ? "axis" : "grid-line", x1: v, x2: v, y1: top,
                             y2: top + size }));
    }
    for (let v = Math.ceil(top / step) * step; v <= top + size; v += step) {
      lines.push(s("line", { class: v === 0 ? "axis" : "grid-line", y1: v, y2: v, x1: left,
                             x2: left + size }));
    }
    put(this.grid, ...lines);
  }
}
