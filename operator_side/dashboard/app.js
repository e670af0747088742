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
  draws: { pads: 0, pattern: 0, stimulus: 0, linkage: 0, chart: 0, arm: 0 },
  acks: [],
  sendCommand: null,
  jog: null,
  video: null,
  latched: false, // the robot's stop latch, as its newest heartbeat says
  latchChanges: [], // {latched, t: performance.now()} each time this page saw it change
  stopSentAt: null, // Date.now() of this page's latest STOP
  staleAtResume: null, // the robot's stale-command count when this page last sent RESUME
  resumeCheck: null, // the timer that says why a resume left the stop in place
  marks: [], // the server's answers to this page's episode marks
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
    startJogger(msg.jog);
    if (msg.video) startVideo();
  } else if (msg.type === "state") {
    for (const k of Object.keys(msg)) changed.add(k);
    Object.assign(dxp.state, msg);
  } else if (msg.type === "video_answer") {
    if (dxp.video) dxp.video.onAnswer(msg);
    $("video-source").textContent = `${msg.source}, ${msg.width}x${msg.height} at ${msg.fps} fps`;
    return;
  } else if (msg.type === "video_closed") {
    if (dxp.video) dxp.video.onClosed(msg);
    return;
  } else if (msg.type === "ack") {
    dxp.acks.push(msg);
    if (dxp.acks.length > 200) dxp.acks.shift();
    if (msg.action === "arm_resume") {
      onResumeAck(msg);
      return;
    }
    if (msg.action === "episode_mark") {
      onMarkAck(msg);
      return;
    }
    if (msg.action && msg.action.startsWith("arm")) {
      if (!msg.ok) $("jog-source").textContent = `refused: ${msg.error}`;
      return;
    }
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

// The arm's jog and stop messages; false when the socket is down (the robot's
// deadman stops a jog that is no longer renewed). Each carries the page's clock:
// the server drops a jog that reached it late (a busy PC queued it), so a hand
// that let go never moves the arm afterwards.
function sendArm(msg) {
  if (!socket || !socket.isOpen()) return false;
  socket.send(msg.type === "command" ? { ...msg, t_page_ms: performance.now() } : msg);
  return true;
}

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
  if (all || changed.has("arm")) {
    drawArm(s.arm);
    drawLatch(s.arm);
  }
  if (all || changed.has("control")) drawControl(s.control);
  changed.clear();
}

// The control lease (through a relay, several operators; the robot obeys one).
function drawControl(c) {
  $("control").hidden = !c;
  if (!c) return;
  let text;
  if (c.ours) text = "you have control";
  else if (c.holder) text = `control: ${c.holder}…` + (c.asked ? " (you asked)" : "");
  else text = "nobody has control";
  if (c.pending && c.ours) text += ` · ${c.pending}… asks for it`;
  $("control-text").textContent = text;
  $("lease-request").hidden = c.ours;
  $("lease-grant").hidden = !(c.ours && c.pending);
  $("lease-release").hidden = !c.ours;
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
      ctx.fillText("no raw frames", cv.width / 2, cv.height / 2 - 8);
      ctx.font = "11px sans-serif"; // the fabric sends none unless the robot's config asks
      ctx.fillText("(fabric: off by default)", cv.width / 2, cv.height / 2 + 10);
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

// Forward kinematics, as operator_side/palm/linkglide.py: B and D from the servo
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

// ---------------------------------------------------------------------- arm
const fmt = (v, d = 1) => (v == null ? "–" : v.toFixed(d));

function drawArm(arm) {
  const cv = $("workspace");
  const ctx = cv.getContext("2d");
  ctx.clearRect(0, 0, cv.width, cv.height);
  dxp.draws.arm++;
  if (!arm) {
    ctx.fillStyle = "#777";
    ctx.font = "13px sans-serif";
    ctx.fillText("no arm reported by the robot", 20, cv.height / 2);
    return;
  }
  const [lo, hi] = arm.workspace_mm;
  const p = arm.pose;
  // top view (x right, y up) on the left, z as a bar on the right
  const W = cv.width - 80;
  const H = cv.height - 30;
  const k = Math.min(W / (hi[0] - lo[0]), H / (hi[1] - lo[1]));
  const ox = 10 + (W - (hi[0] - lo[0]) * k) / 2;
  const oy = 10 + (H - (hi[1] - lo[1]) * k) / 2;
  const X = (x) => ox + (x - lo[0]) * k;
  const Y = (y) => oy + (hi[1] - y) * k;
  ctx.fillStyle = "#f4f7fa";
  ctx.fillRect(X(lo[0]), Y(hi[1]), (hi[0] - lo[0]) * k, (hi[1] - lo[1]) * k);
  ctx.strokeStyle = "#2c6e9e";
  ctx.lineWidth = 1.5;
  ctx.strokeRect(X(lo[0]), Y(hi[1]), (hi[0] - lo[0]) * k, (hi[1] - lo[1]) * k);
  ctx.fillStyle = "#555";
  ctx.font = "11px sans-serif";
  ctx.textAlign = "left";
  ctx.fillText(`x ${lo[0]}..${hi[0]} mm →`, X(lo[0]), Y(lo[1]) + 13);
  ctx.save();
  ctx.translate(X(lo[0]) - 3, Y(lo[1]));
  ctx.rotate(-Math.PI / 2);
  ctx.fillText(`y ${lo[1]}..${hi[1]} →`, 0, 0);
  ctx.restore();
  const zx = cv.width - 55;
  const ZY = (z) => 10 + (hi[2] - z) / (hi[2] - lo[2]) * H;
  ctx.strokeRect(zx, ZY(hi[2]), 14, H);
  ctx.fillText(`${hi[2]}`, zx + 17, ZY(hi[2]) + 9);
  ctx.fillText(`${lo[2]}`, zx + 17, ZY(lo[2]));
  ctx.fillText("z mm", zx - 4, H + 24);
  if (p) {
    const inside = p[0] >= lo[0] && p[0] <= hi[0] && p[1] >= lo[1] && p[1] <= hi[1] && p[2] >= lo[2] && p[2] <= hi[2];
    const colour = inside ? "#c0392b" : "#7d3c98";
    // the tool: a dot, with a tick showing its rotation about z
    const rz = (p[5] * Math.PI) / 180;
    const [tx, ty] = [X(p[0]), Y(p[1])];
    ctx.strokeStyle = colour;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(tx, ty);
    ctx.lineTo(tx + 14 * Math.cos(rz), ty - 14 * Math.sin(rz));
    ctx.stroke();
    ctx.beginPath();
    ctx.arc(tx, ty, 6, 0, 2 * Math.PI);
    ctx.fillStyle = colour;
    ctx.fill();
    ctx.fillRect(zx - 3, ZY(Math.max(lo[2], Math.min(hi[2], p[2]))) - 2, 20, 4);
    dxp.tcpPixel = [tx, ty];
  }
  $("arm-pose").textContent = p ? `x ${fmt(p[0])}  y ${fmt(p[1])}  z ${fmt(p[2])} mm` : "–";
  $("arm-rot").textContent = p ? `rx ${fmt(p[3])}  ry ${fmt(p[4])}  rz ${fmt(p[5])}°` : "–";
  $("arm-speed").textContent =
    `${fmt(arm.speed_mm_s)} mm/s · ${fmt(arm.angular_deg_s)}°/s (caps ${arm.max_linear_mm_s}, ${arm.max_angular_deg_s})`;
  const safety = $("arm-safety");
  safety.textContent = arm.available ? arm.safety ?? "–" : "reconnecting";
  safety.className = arm.safety === "normal" || arm.safety === "reduced" ? "" : "bad";
  $("arm-program").textContent = arm.program_running == null ? "–" : arm.program_running ? "running" : "stopped";
  $("arm-deadman").textContent =
    `${arm.jogging ? "jogging" : "still"} · deadman stops ${arm.deadman_stops} · link trips ${arm.link_deadman_trips}`;
  const a = arm.assist;
  $("assist-phase").textContent = !a ? "–" : `${a.phase} · re-grasps ${a.regrasps} · steps ${a.steps}`;
}

// The robot's stop latch (its heartbeat): the same on every page of every operator.
function drawLatch(arm) {
  const latched = !!(arm && arm.stop_latched);
  if (latched !== dxp.latched) {
    dxp.latched = latched;
    dxp.latchChanges.push({ latched, t: performance.now() });
    // a resume's verdict belongs to the latch it was sent against, never to the next one
    clearTimeout(dxp.resumeCheck);
    if (!latched) $("latch-note").textContent = "";
  }
  $("latch").hidden = !latched;
  document.body.classList.toggle("stopped", latched);
  $("arm-latch").textContent = !arm ? "–" : latched ? "STOPPED (latched on the robot)" : "free";
  $("arm-latch").className = latched ? "bad" : "";
  if (dxp.jog) dxp.jog.setRobotLatched(latched);
}

// RESUME: the robot obeys it from the lease holder only; the server says so at
// once when it knows we are not, and a resume the robot ignored shows here too.
function resumeArm() {
  $("latch-note").textContent = "resume sent…";
  dxp.staleAtResume = staleCommands();
  sendCommand("arm_resume");
}

// Commands the robot refused as too old (its max_command_age_ms), by its heartbeat.
function staleCommands() {
  const arm = dxp.state && dxp.state.arm;
  return arm ? arm.commands_stale : null;
}

function onResumeAck(msg) {
  if (!msg.ok) {
    $("latch-note").textContent = `resume refused: ${msg.error}`;
    return;
  }
  const staleBefore = dxp.staleAtResume;
  clearTimeout(dxp.resumeCheck);
  dxp.resumeCheck = setTimeout(() => {
    if (!dxp.latched) return;
    const stale = staleCommands();
    $("latch-note").textContent =
      staleBefore != null && stale != null && stale > staleBefore
        ? "the robot refused the resume as stale (the link or a machine is slow): press RESUME again"
        : "the robot kept its stop: a resume counts only from the lease holder, fresh (is the link up?)";
  }, 1500);
}

// The video's badge, as the palm's: FRESH while the picture on screen is recent,
// STALE (and the picture greyed) once it is older than video_stale_ms.
const VIDEO_FRESH = {
  fresh: ["FRESH", "ok"],
  stale: ["STALE", "stale"],
  none: ["NO VIDEO", "down"],
};

function drawVideoFreshness(f) {
  const [label, cls] = VIDEO_FRESH[f.state];
  $("video-fresh").className = "badge " + cls;
  $("video-fresh-label").textContent = label;
  $("video-fresh-detail").textContent = f.age_ms == null ? "" : ` · ${f.age_ms.toFixed(0)} ms old`;
  $("video").classList.toggle("stale", f.state !== "fresh");
}

function startVideo() {
  $("video-panel").hidden = false;
  const status = (text) => ($("video-status").textContent = text);
  if (!dxp.video) {
    dxp.video = new VIDEO.Receiver($("video"), sendArm, status, dxp.hello.ice_servers || [],
      dxp.hello.ice_transport_policy || "all");
    dxp.video.watchFreshness(dxp.hello.video_stale_ms || 500, drawVideoFreshness);
    setInterval(() => {
      const v = dxp.video;
      if (v.source !== "test_pattern" || !v.latencies.length) return;
      const s = v.summary();
      status(`glass-to-glass p50 ${s.p50} ms, p99 ${s.p99} ms over ${s.stamped} frames`);
    }, 1000);
  }
  dxp.video.start();
}

function startJogger(cfg) {
  if (dxp.jog || !cfg) return;
  dxp.jog = new JOG.Jogger(cfg, sendArm, stopArm);
  dxp.jog.setRobotLatched(!!dxp.latched);
  const pct = Math.round(cfg.default_speed_scale * 100);
  $("speed").value = pct;
  $("speed-out").textContent = `${pct}%`;
  const keys = Object.entries(cfg.keyboard).map(([k, t]) => `${k} ${t}`).join(" · ");
  $("key-help").textContent =
    `keys (hold): ${keys}; ${cfg.assist_key}: assist; Esc or Space: STOP (held until RESUME)`;
  setInterval(showJogState, 200);
}

function showJogState() {
  const j = dxp.jog;
  const pads = (navigator.getGamepads ? [...navigator.getGamepads()] : []).filter((p) => p);
  $("devices").textContent =
    (pads.length ? pads.map((p) => `gamepad: ${p.id.slice(0, 24)}`).join(", ") : "no gamepad") +
    (j.hidDevice ? ` · SpaceMouse: ${j.hidDevice.productName}` : "");
  const v = j.last.velocity;
  $("jog-source").textContent = j.robotLatched
    ? "STOPPED on the robot: RESUME, then release and hold again"
    : j.latched
      ? "stopped: release all inputs"
      : j.last.assist
        ? `${j.last.source}: assist held`
        : j.last.enabled
          ? `${j.last.source}: ${(Math.hypot(v[0], v[1], v[2]) * 1000).toFixed(0)} mm/s`
          : "none (hold to move)";
  for (const b of document.querySelectorAll(".jog-pad button[data-twist]")) {
    b.classList.toggle("held", j.buttons.has(b.dataset.twist));
  }
}

function stopArm() {
  dxp.stopSentAt = Date.now(); // wall clock: a test compares it with the arm's own timeline
  if (dxp.jog) {
    dxp.jog.releaseAll();
    dxp.jog.stop(true);
  } else {
    sendArm({ type: "command", action: "arm_stop" });
  }
}

$("arm-stop").addEventListener("click", stopArm);
$("arm-resume").addEventListener("click", resumeArm);
$("speed").addEventListener("input", () => {
  $("speed-out").textContent = `${$("speed").value}%`;
  if (dxp.jog) dxp.jog.speedScale = Number($("speed").value) / 100;
});
for (const b of document.querySelectorAll(".jog-pad button[data-twist]")) {
  const release = () => {
    if (!dxp.jog) return;
    dxp.jog.buttons.delete(b.dataset.twist);
    dxp.jog.released();
  };
  b.addEventListener("pointerdown", (e) => {
    if (!dxp.jog) return;
    b.setPointerCapture(e.pointerId);
    dxp.jog.buttons.add(b.dataset.twist);
  });
  for (const ev of ["pointerup", "pointercancel", "lostpointercapture"]) b.addEventListener(ev, release);
}
window.addEventListener("keydown", (e) => {
  if (!dxp.jog || e.target.tagName === "INPUT") return;
  if (e.key === "Escape" || e.key === " ") {
    e.preventDefault();
    stopArm();
    return;
  }
  const key = e.key.toLowerCase();
  const held = key in dxp.jog.cfg.keyboard || key === dxp.jog.cfg.assist_key;
  if (held && !e.ctrlKey && !e.metaKey && !e.altKey) dxp.jog.keys.add(key);
});
window.addEventListener("keyup", (e) => {
  if (!dxp.jog) return;
  dxp.jog.keys.delete(e.key.toLowerCase());
  dxp.jog.released();
});
// a key released while the window was not focused never sends keyup: release everything
window.addEventListener("blur", () => dxp.jog && dxp.jog.releaseAll());
document.addEventListener("visibilitychange", () => dxp.jog && dxp.jog.setAway(document.hidden));
window.addEventListener("pagehide", () => dxp.jog && dxp.jog.setAway(true));
window.addEventListener("pageshow", () => dxp.jog && dxp.jog.setAway(document.hidden));
window.addEventListener("gamepaddisconnected", () => dxp.jog && dxp.jog.tick());
$("connect-spacemouse").addEventListener("click", async () => {
  if (!navigator.hid) {
    $("devices").textContent = "this browser has no WebHID (use Chromium, Chrome or Edge)";
    return;
  }
  const [device] = await navigator.hid.requestDevice({ filters: JOG.HID_FILTERS });
  if (device) await dxp.jog.connectSpaceMouse(device);
});
if (navigator.hid) {
  // a SpaceMouse allowed once is reconnected without asking again
  navigator.hid.getDevices().then((devices) => {
    const known = devices.find((d) => JOG.HID_FILTERS.some((f) => f.vendorId === d.vendorId));
    const attach = () => (dxp.jog ? dxp.jog.connectSpaceMouse(known) : setTimeout(attach, 200));
    if (known) attach();
  });
  navigator.hid.addEventListener("disconnect", (e) => {
    if (dxp.jog && e.device === dxp.jog.hidDevice) dxp.jog.spaceMouseLost();
  });
}

// ------------------------------------------------------------------ episode marks
// The operator's word on the grasp in progress (or the one that just ended): the
// node records it and `deepxpalm export` applies it (docs/datasets.md). A key the
// jog uses stays the jog's.
const MARK_KEYS = { v: "success", x: "failed", Delete: "discard" };

function markEpisode(kind) {
  if (!socket || !socket.isOpen()) {
    $("mark-status").textContent = `not connected: the episode was not marked ${kind}`;
    return false;
  }
  const msg = { type: "command", action: "episode_mark", kind };
  const task = $("mark-task").value.trim();
  if (task) msg.task = task;
  socket.send(msg);
  return true;
}
dxp.markEpisode = markEpisode;

function onMarkAck(msg) {
  dxp.marks.push(msg);
  if (dxp.marks.length > 200) dxp.marks.shift();
  const at = new Date().toLocaleTimeString();
  $("mark-status").textContent = msg.ok
    ? `${at}: episode marked ${msg.kind}${msg.task ? ` (task: ${msg.task})` : ""}`
    : `${at}: not marked: ${msg.error}`;
  $("mark-status").classList.toggle("refused", !msg.ok);
}

for (const kind of ["success", "failed", "discard"]) {
  $(`mark-${kind}`).addEventListener("click", () => markEpisode(kind));
}
window.addEventListener("keydown", (e) => {
  if (e.repeat || e.ctrlKey || e.metaKey || e.altKey || e.target.tagName === "INPUT") return;
  const kind = MARK_KEYS[e.key] || MARK_KEYS[e.key.toLowerCase()];
  if (!kind) return;
  const jog = dxp.jog && dxp.jog.cfg;
  const key = e.key.toLowerCase();
  if (jog && (key in jog.keyboard || key === jog.assist_key)) return;
  e.preventDefault();
  markEpisode(kind);
});

// ------------------------------------------------------------------ controls
$("level").addEventListener("input", () => {
  $("level-out").textContent = $("level").value;
});
$("open").addEventListener("click", () => sendCommand("gripper_open"));
for (const action of ["lease_request", "lease_grant", "lease_release"]) {
  $(action.replace("_", "-")).addEventListener("click", () => sendCommand(action));
}
$("close").addEventListener("click", () => sendCommand("gripper_close", Number($("level").value)));

drawColorbar();
socket = DXP.openSocket(dxp, "live", onMessage);
