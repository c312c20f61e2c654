// Building the page without ever parsing markup: every value, whoever supplied it (a
// command's parameters, a thought id, a model name, a principal), becomes a text node.
// Nothing in the console assigns innerHTML, outerHTML or insertAdjacentHTML.

const SVG_NS = "http://www.w3.org/2000/svg";

function fill(node, attrs, children) {
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on")) throw new Error("no event attributes: " + name);
    node.setAttribute(name, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** An HTML element: h("li", {class: "x"}, "text", otherNode). */
export function h(tag, attrs, ...children) {
  return fill(document.createElement(tag), attrs, children);
}

/** An SVG element. */
export function s(tag, attrs, ...children) {
  return fill(document.createElementNS(SVG_NS, tag), attrs, children);
}

/** Replace a node's children. */
export function put(node, ...children) {
  node.replaceChildren();
  return fill(node, {}, children);
}

export function byId(id) {
  const found = document.getElementById(id);
  if (!found) throw new Error("no element #" + id);
  return found;
}

export function show(node, visible) {
  node.hidden = !visible;
}

export function fmt(value, digits = 2) {
  return typeof value === "number" && Number.isFinite(value) ? value.toFixed(digits) : "–";
}

export function when(ms) {
  if (typeof ms !== "number") return "–";
  const d = new Date(ms);
  return d.toLocaleTimeString([], { hour12: false });
}
