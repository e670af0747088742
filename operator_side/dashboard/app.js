// The dashboard page: draws what the operator node pushes, sends gripper commands.
// Everything the page draws is kept on window.dxp so a test (or a curious
// engineer in the console) can read what was drawn and when.
"use strict";

const dxp = {
  hello: null,
  state: {},
  joints: null,
  connected: false,
  messages: 0,
  draws: { pads: 0, pattern: 0, stimulus: 0, linkage: 0, chart: 0 },
  acks: [],
  sendCommand: null,
};
window.dxp = dxp;

const $ = (id) => document.getElementById(id);
const LINK = {
  ok: ["FRESH", "ok", "rendering"],
  stale: ["STALE", "stale", "lifted off"],
  down: ["NO DATA", "down", "lifted off"],
};

// ------------------------------------------------------------------ socket
let socket = null;
let drawPending = false;
const changed = new Set();

function onMessage(msg) {
  dxp.messages++;
  if (msg.type === "hello") {
    dxp.hello = msg;
    changed.add("all");
  } else if (msg.type === "state") {
    for (const k of Object.keys(msg)) changed.add(k);
    Object.assign(dxp.state, msg);
  } else if (msg.type === "ack") {
    dxp.acks.push(msg);
    $("ack").textContent = msg.ok
      ? `sent ${msg.action}${msg.grip_level ? " (level " + msg.grip_level + ")" : ""}`
      : `refused: ${msg.error}`;
  }
  if (!drawPending) {
    drawPending = true;
    requestAnimationFrame(draw);
  }
}

function sendCommand(action, gripLevel) {
  if (!socket || !socket.isOpen()) {
    $("ack").textContent = "not connected";
    return false;
  }
  const msg = { type: "command", action };
  if (gripLevel !== undefined) msg.grip_level = gripLevel;
  socket.send(msg);
  return true;
}
dxp.sendCommand = sendCommand;

// ------------------------------------------------------------------ drawing
function draw() {
  drawPending = false;
  if (!dxp.hello) return;
  const all = changed.has("all");
  const s = dxp.state;
  if (all || changed.has("link_state") || changed.has("age_ms")) drawLink(s);
  if (all || changed.has("frame")) drawPads(s.frame);
  const recognised = ["pattern", "confidence", "grip_level", "stimulus"];
  if (all || recognised.some((k) => changed.has(k))) {
    drawRecognised(s);
  }
  if (all || changed.has("stimulus")) drawStimulus(s.stimulus);
  if (all || changed.has("angles")) drawLinkage(s.angles);
  if (all || changed.has("history")) drawChart(s.history);
  if (changed.has("stats")) drawCounters(s.stats);
  changed.clear();
}

function drawLink(s) {
  const [label, cls, detail] = LINK[s.link_state] || ["?", "down", ""];
  const age = s.age_ms == null ? "" : ` · age ${s.age_ms.toFixed(0)} ms`;
  $("link").className = "badge " + cls;
  $("link-label").textContent = label;
  $("link-detail").textContent = ` palm ${detail}${age}`;
}

function drawPads(frame) {
  for (let p = 0; p < 2; p++) {
    const cv = $("pad" + p);
    const ctx = cv.getContext("2d");
    const n = 10;
    const px = cv.width / n;
    if (!frame) {
      ctx.fillStyle = "#ddd";
      ctx.fillRect(0, 0, cv.width, cv.height);
      ctx.fillStyle = "#777";
      ctx.font = "14px sans-serif";
      ctx.textAlign = "center";
      ctx.fillText("no frame yet", cv.width / 2, cv.height / 2);
      continue;
    }
    for (let r = 0; r < n; r++) {
      for (let c = 0; c < n; c++) {
        ctx.fillStyle = DXP.heatColor(frame[p][r][c]);
        ctx.fillRect(c * px, r * px, px + 0.5, px + 0.5);
      }
    }
  }
  dxp.draws.pads++;
}

function drawColorbar() {
  const cv = $("colorbar");
  const ctx = cv.getContext("2d");
  const h = cv.height - 20;
  for (let y = 0; y < h; y++) {
    ctx.fillStyle = DXP.heatColor(9 * (1 - y / h));
    ctx.fillRect(0, y + 10, 12, 1);
  }
  ctx.fillStyle = "#333";
  ctx.font = "11px sans-serif";
  ctx.fillText("9", 16, 16);
  ctx.fillText("0", 16, h + 12);
}

function drawRecognised(s) {
  const cv = $("pattern");
  const ctx = cv.getContext("2d");
  ctx.clearRect(0, 0, cv.width, cv.height);
  if (s.pattern == null) {
    const touching = s.stimulus && s.stimulus.some((row) => row.some((v) => v > 0));
    $("pattern-name").textContent = !s.stimulus ? "–" : touching ? "none (direct)" : "no contact";
    ctx.fillStyle = "#eee";
    ctx.fillRect(0, 0, cv.width, cv.height);
  } else {
    DXP.drawPattern(ctx, dxp.hello.patterns[s.pattern], 0, 0, cv.width);
    $("pattern-name").textContent = `${s.pattern} · ${s.pattern_name}`;
  }
  const conf = s.confidence;
  $("confidence-bar").style.width = conf == null ? "0" : `${Math.round(conf * 100)}%`;
  $("confidence").textContent = conf == null ? "confidence –" : `confidence ${(conf * 100).toFixed(0)}%`;
  $("grip").textContent = `grip level ${s.grip_level ?? "–"}`;
  dxp.draws.pattern++;
}

function drawStimulus(stim) {
  const cv = $("stimulus");
  const ctx = cv.getContext("2d");
  const px = cv.width / 3;
  ctx.clearRect(0, 0, cv.width, cv.height);
  ctx.font = "bold 15px sans-serif";
  ctx.textAlign = "center";
  ctx.textBaseline = "middle";
  for (let r = 0; r < 3; r++) {
    for (let c = 0; c < 3; c++) {
      const v = stim ? stim[r][c] : 0;
      ctx.fillStyle = v > 0 ? DXP.heatColor(v) : "#f2f2f2";
      ctx.fillRect(c * px + 2, r * px + 2, px - 4, px - 4);
      ctx.fillStyle = v > 5 ? "#222" : v > 0 ? "#fff" : "#aaa";
      ctx.fillText(v > 0 ? v.toFixed(2) : "·", c * px + px / 2, r * px + px / 2);
    }
  }
  dxp.draws.stimulus++;
}

// Forward kinematics, as operator_side/linkglide.py: B and D from the servo
// angles, C the intersection of circles (B, l3) and (D, l4) with the larger Y.
function forward(g, ta, te) {
  const B = [g.l2 * Math.cos(ta), g.l2 * Math.sin(ta)];
  const D = [g.l1 + g.l5 * Math.cos(te), g.l5 * Math.sin(te)];
  const vx = D[0] - B[0];
  const vy = D[1] - B[1];
  const dist = Math.hypot(vx, vy);
  const a = ((dist - g.l4) * (dist + g.l4) + g.l3 * g.l3) / (2 * dist);
  const h = Math.sqrt(Math.max((g.l3 - a) * (g.l3 + a), 0));
  const sign = vx >= 0 ? 1 : -1;
  const ux = vx / dist;
  const uy = vy / dist;
  const C = [B[0] + a * ux - sign * h * uy, B[1] + a * uy + sign * h * ux];
  return { A: [0, 0], B, C, D, E: [g.l1, 0] };
}

function drawLinkage(angles) {
  const cv = $("linkage");
  const ctx = cv.getContext("2d");
  ctx.clearRect(0, 0, cv.width, cv.height);
  if (!angles) return;
  const g = dxp.hello.geometry;
  const k = dxp.hello.contact;
  const palm = k.palm_y_mm;
  const x0 = -g.l2 - 8;
  const x1 = g.l1 + g.l5 + 8;
  const y0 = -12;
  const y1 = palm + k.max_depth_mm + 8;
  const panelW = cv.width / 3;
  const scale = Math.min((panelW - 16) / (x1 - x0), (cv.height - 30) / (y1 - y0));
  dxp.joints = angles.map(([ta, te]) => forward(g, ta, te));
  dxp.joints.forEach((j, n) => {
    const ox = n * panelW + (panelW - (x1 - x0) * scale) / 2;
    const P = ([x, y]) => [ox + (x - x0) * scale, cv.height - 8 - (y - y0) * scale];
    // the palm: everything above its surface
    const [px0, py] = P([x0, palm]);
    const [px1, pyTop] = P([x1, y1]);
    ctx.fillStyle = "#f6dcc8";
    ctx.fillRect(px0, pyTop, px1 - px0, py - pyTop);
    ctx.strokeStyle = "#d7a98a";
    ctx.beginPath();
    ctx.moveTo(px0, py);
    ctx.lineTo(px1, py);
    ctx.stroke();
    // column positions on the palm
    ctx.fillStyle = "#c99a7c";
    for (const cx of k.column_x_mm) {
      const [tx, ty] = P([cx, palm]);
      ctx.fillRect(tx - 1, ty - 4, 2, 8);
    }
    const link = (p, q, w, colour) => {
      const a = P(p);
      const b = P(q);
      ctx.strokeStyle = colour;
      ctx.lineWidth = w;
      ctx.lineCap = "round";
      ctx.beginPath();
      ctx.moveTo(a[0], a[1]);
      ctx.lineTo(b[0], b[1]);
      ctx.stroke();
    };
    link(j.A, j.E, 6, "#555");
    link(j.A, j.B, 5, "#2c6e9e");
    link(j.E, j.D, 5, "#2c6e9e");
    link(j.B, j.C, 3, "#5d9bc7");
    link(j.D, j.C, 3, "#5d9bc7");
    ctx.lineWidth = 1;
    for (const p of [j.A, j.E]) {
      const [x, y] = P(p);
      ctx.fillStyle = "#222";
      ctx.fillRect(x - 5, y - 5, 10, 10);
    }
    for (const p of [j.B, j.D]) {
      const [x, y] = P(p);
      ctx.beginPath();
      ctx.arc(x, y, 3.5, 0, 2 * Math.PI);
      ctx.fillStyle = "#fff";
      ctx.fill();
      ctx.strokeStyle = "#2c6e9e";
      ctx.stroke();
    }
    const pressing = j.C[1] > palm + 0.05;
    const [cx, cy] = P(j.C);
    ctx.beginPath();
    ctx.arc(cx, cy, pressing ? 7 : 5, 0, 2 * Math.PI);
    ctx.fillStyle = pressing ? "#c0392b" : "#999";
    ctx.fill();
    ctx.fillStyle = "#333";
    ctx.font = "12px sans-serif";
    ctx.textAlign = "left";
    const depth = pressing ? ` · ${(j.C[1] - palm).toFixed(1)} mm in` : " · lifted";
    ctx.fillText(`linkage ${n + 1} (row ${n})${depth}`, n * panelW + 8, 14);
  });
  dxp.draws.linkage++;
}

function drawChart(h) {
  const cv = $("chart");
  const ctx = cv.getContext("2d");
  ctx.clearRect(0, 0, cv.width, cv.height);
  if (!h) return;
  const L = 46;
  const R = cv.width - 36;
  const T = 10;
  const B = cv.height - 18;
  const span = dxp.hello.history_s;
  const X = (t) => R + (t / span) * (R - L);
  const lat = h.latency_ms.filter((v) => v != null);
  const top = Math.max(50, ...lat.map((v) => v * 1.2));
  const lossTop = Math.max(0.05, ...h.loss.filter((v) => v != null).map((v) => v * 1.2));
  ctx.strokeStyle = "#ddd";
  ctx.strokeRect(L, T, R - L, B - T);
  // loss: bars against the right axis
  const barW = Math.max(2, (R - L) / span - 1);
  h.loss.forEach((v, i) => {
    if (v == null || v <= 0) return;
    const y = B - (v / lossTop) * (B - T);
    ctx.fillStyle = "rgba(192, 57, 43, 0.55)";
    ctx.fillRect(X(h.t[i]) - barW, y, barW, B - y);
  });
  // latency: a line against the left axis
  ctx.strokeStyle = "#2c6e9e";
  ctx.lineWidth = 2;
  ctx.beginPath();
  let pen = false;
  h.latency_ms.forEach((v, i) => {
    if (v == null) {
      pen = false;
      return;
    }
    const x = X(h.t[i]);
    const y = B - (Math.min(v, top) / top) * (B - T);
    if (pen) ctx.lineTo(x, y);
    else ctx.moveTo(x, y);
    pen = true;
  });
  ctx.stroke();
  ctx.lineWidth = 1;
  ctx.font = "11px sans-serif";
  ctx.fillStyle = "#2c6e9e";
  ctx.textAlign = "right";
  ctx.fillText(`${top.toFixed(0)} ms`, L - 3, T + 8);
  ctx.fillText("0", L - 3, B);
  ctx.fillStyle = "#c0392b";
  ctx.textAlign = "left";
  ctx.fillText(`${(lossTop * 100).toFixed(0)}%`, R + 3, T + 8);
  ctx.fillText("0", R + 3, B);
  ctx.fillStyle = "#666";
  ctx.textAlign = "center";
  ctx.fillText(`−${span} s`, L, B + 13);
  ctx.fillText("now", R, B + 13);
  ctx.fillText("latency (line) · loss (bars)", (L + R) / 2, B + 13);
  const s = h.summary;
  const med = s.latency_median_ms == null ? "–" : `${s.latency_median_ms.toFixed(1)} ms`;
  const mx = s.latency_max_ms == null ? "–" : `${s.latency_max_ms.toFixed(1)} ms`;
  const loss = s.loss == null ? "–" : `${(s.loss * 100).toFixed(1)}% (${s.lost} of ${s.sent})`;
  $("net-summary").textContent = `latency median ${med}, max ${mx} · loss ${loss}`;
  dxp.draws.chart++;
}

function drawCounters(st) {
  if (!st) return;
  const f = (k) => (st[k] == null ? "–" : Math.round(st[k]));
  $("counters").textContent =
    `received ${f("stimuli_received")} · servo writes ${f("servo_writes")} · ` +
    `lift-offs ${f("lift_offs")} · commands ${f("commands_sent")} · rejected ${f("decode_errors")}`;
}

// ------------------------------------------------------------------ controls
$("level").addEventListener("input", () => {
  $("level-out").textContent = $("level").value;
});
$("open").addEventListener("click", () => sendCommand("gripper_open"));
$("close").addEventListener("click", () => sendCommand("gripper_close", Number($("level").value)));

drawColorbar();
socket = DXP.openSocket(dxp, "live", onMessage);
