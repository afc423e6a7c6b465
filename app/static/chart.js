// A small SVG line chart with real axes (ticks, labels, legend) for the job page; no library, no build step.
// lineChart({...}) returns an <svg>; each series is a <polyline data-series=NAME data-points=N> plus its dots.
"use strict";

const CHART_SVG_NS = "http://www.w3.org/2000/svg";
const CHART_COLOURS = ["#2f6fdb", "#d9822b", "#1f8a4c", "#9b59b6", "#c23b30", "#16a2b8"];

function svgNode(tag, attrs = {}, text) {
  const node = document.createElementNS(CHART_SVG_NS, tag);
  for (const [key, value] of Object.entries(attrs)) node.setAttribute(key, String(value));
  if (text !== undefined) node.textContent = text;
  return node;
}

// About `count` round tick values (1, 2 or 5 times a power of ten apart) covering [min, max].
function niceTicks(min, max, count = 5) {
  const span = max - min || Math.abs(max) || 1;
  const raw = span / count;
  const power = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw);
  const ticks = [];
  for (let v = Math.ceil(min / step) * step; v <= max + step * 1e-9; v += step) ticks.push(Number(v.toPrecision(12)));
  return ticks;
}

// Tick values for a log axis over [min, max] (both > 0): 1, 2 and 5 times the powers of ten inside it.
function logTicks(min, max) {
  const ticks = [];
  for (let e = Math.floor(Math.log10(min)); e <= Math.ceil(Math.log10(max)); e += 1) {
    for (const m of [1, 2, 5]) {
      const v = m * 10 ** e;
      if (v >= min && v <= max) ticks.push(v);
    }
  }
  return ticks.length >= 2 ? ticks : [min, max];
}

function tickText(value) {
  const abs = Math.abs(value);
  if (abs !== 0 && (abs < 1e-3 || abs >= 1e5)) return value.toExponential(0);
  return String(Number(value.toPrecision(4)));
}

// The y range of the points, padded by a few percent (in log space on a log axis, where only positive values
// count), and by more when flat.
function yRange(values, log) {
  let lo = Math.min(...values), hi = Math.max(...values);
  if (log) return lo === hi ? [lo / 2, hi * 2] : [lo / (hi / lo) ** 0.04, hi * (hi / lo) ** 0.04];
  if (hi - lo < 1e-9) return [lo - 0.5, hi + 0.5];
  const pad = 0.05 * (hi - lo);
  return [lo - pad, hi + pad];
}

// series: [{name, points: [[x, y], ...], marks?: [[x, y, title], ...]}]; x from 0 to xMax (at least the
// largest x); log: a log10 y axis. Non-finite points are left out.
function lineChart({ width = 640, height = 220, xMax = 0, xLabel, yLabel, series, log = false, label }) {
  const left = 58, right = 12, top = 24, bottom = 40;  // the legend sits in the top margin
  const clean = series.map((s) => ({
    ...s,
    points: s.points.filter(([x, y]) => Number.isFinite(x) && Number.isFinite(y) && (!log || y > 0)),
  }));
  const root = svgNode("svg", {
    width, height, viewBox: `0 0 ${width} ${height}`, class: "chart", role: "img", "aria-label": label || yLabel,
  });
  const all = clean.flatMap((s) => s.points);
  root.dataset.points = String(all.length);
  const plotW = width - left - right, plotH = height - top - bottom;
  root.appendChild(svgNode("rect", { x: left, y: top, width: plotW, height: plotH, class: "chart-area" }));
  if (!all.length) {
    root.appendChild(svgNode("text", { x: left + 10, y: top + plotH / 2, class: "chart-empty" }, "no points yet"));
    return root;
  }
  const x1 = Math.max(xMax, ...all.map((p) => p[0]), 1);
  const [y0, y1] = yRange(all.map((p) => p[1]), log);
  const fy = log ? Math.log10 : (v) => v;
  const px = (x) => left + (x / x1) * plotW;
  const py = (y) => top + (1 - (fy(y) - fy(y0)) / (fy(y1) - fy(y0))) * plotH;
  for (const t of niceTicks(0, x1, 6)) {
    root.appendChild(svgNode("line", { x1: px(t), y1: top, x2: px(t), y2: top + plotH, class: "chart-grid" }));
    root.appendChild(svgNode("text", { x: px(t), y: top + plotH + 14, "text-anchor": "middle" }, tickText(t)));
  }
  for (const t of log ? logTicks(y0, y1) : niceTicks(y0, y1, 5)) {
    root.appendChild(svgNode("line", { x1: left, y1: py(t), x2: left + plotW, y2: py(t), class: "chart-grid" }));
    root.appendChild(svgNode("text", { x: left - 5, y: py(t) + 3, "text-anchor": "end" }, tickText(t)));
  }
  root.appendChild(svgNode("line", { x1: left, y1: top + plotH, x2: left + plotW, y2: top + plotH, class: "chart-axis" }));
  root.appendChild(svgNode("line", { x1: left, y1: top, x2: left, y2: top + plotH, class: "chart-axis" }));
  root.appendChild(svgNode("text", { x: left + plotW / 2, y: height - 6, "text-anchor": "middle", class: "chart-label" }, xLabel));
  root.appendChild(svgNode("text", {
    x: 12, y: top + plotH / 2, "text-anchor": "middle", class: "chart-label",
    transform: `rotate(-90 12 ${top + plotH / 2})`,
  }, yLabel + (log ? " (log scale)" : "")));
  clean.forEach((s, index) => {
    const colour = CHART_COLOURS[index % CHART_COLOURS.length];
    const points = [...s.points].sort((a, b) => a[0] - b[0]);
    const line = svgNode("polyline", {
      points: points.map(([x, y]) => `${px(x).toFixed(1)},${py(y).toFixed(1)}`).join(" "),
      fill: "none", stroke: colour, "stroke-width": 1.5,
    });
    line.dataset.series = s.name;
    line.dataset.points = String(points.length);
    root.appendChild(line);
    if (s.dots !== false) {
      for (const [x, y] of points) root.appendChild(svgNode("circle", { cx: px(x), cy: py(y), r: 2.5, fill: colour }));
    }
    for (const [x, y, title] of s.marks || []) {
      if (!Number.isFinite(x) || !Number.isFinite(y) || (log && y <= 0)) continue;
      const mark = svgNode("rect", { x: px(x) - 4, y: py(y) - 4, width: 8, height: 8, fill: "none", stroke: colour, "stroke-width": 1.5 });
      mark.appendChild(svgNode("title", {}, title));
      root.appendChild(mark);
    }
    const legendX = left + 120 * index;
    root.appendChild(svgNode("line", { x1: legendX, y1: 10, x2: legendX + 16, y2: 10, stroke: colour, "stroke-width": 2 }));
    root.appendChild(svgNode("text", { x: legendX + 20, y: 14, class: "chart-legend" }, s.name));
  });
  return root;
}
