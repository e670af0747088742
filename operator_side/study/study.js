// The participant's page: training pictures, the 12-picture answer grid, feedback.
// The server decides what is on screen; the page shows it and sends one reply.
"use strict";

// ``shown`` keeps what each feedback screen said, for whoever checks the page.
const study = { hello: null, screen: null, sent: [], shown: [], connected: false };
window.study = study;
const $ = (id) => document.getElementById(id);
let socket = null;

function onMessage(msg) {
  if (msg.type === "hello") {
    study.hello = msg;
    buildGrid();
  } else {
    show(msg);
  }
}

function reply(msg) {
  study.sent.push(msg);
  socket.send(msg);
}

function only(id) {
  for (const s of document.querySelectorAll(".screen")) s.hidden = s.id !== id;
}

function picture(canvas, pattern) {
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  DXP.drawPattern(ctx, study.hello.patterns[pattern], 0, 0, canvas.width);
}

function buildGrid() {
  const grid = $("grid");
  grid.textContent = "";
  for (const p of study.hello.patterns) {
    const b = document.createElement("button");
    b.type = "button";
    b.className = "choice";
    b.id = "choice-" + p.id;
    b.dataset.pattern = p.id;
    const cv = document.createElement("canvas");
    cv.width = 120;
    cv.height = 120;
    const label = document.createElement("span");
    label.textContent = `${p.id} · ${p.name}`;
    b.append(cv, label);
    grid.append(b);
    picture(cv, p.id);
    b.addEventListener("click", () => answer(p.id, b));
  }
  if (study.screen) show(study.screen);
}

function answer(pattern, button) {
  const s = study.screen;
  if (!s || s.type !== "ask" || s.answered) return;
  s.answered = true;
  button.classList.add("chosen");
  for (const b of document.querySelectorAll(".choice")) b.disabled = true;
  reply({ type: "answer", id: s.id, pattern });
}

function show(msg) {
  study.screen = msg;
  if (!study.hello) return;
  if (msg.type === "train") {
    $("progress").textContent = `training ${msg.index + 1} of ${msg.total}`;
    picture($("train-picture"), msg.pattern);
    $("train-name").textContent = `${msg.pattern} · ${study.hello.patterns[msg.pattern].name}`;
    $("next").disabled = false;
    only("train");
  } else if (msg.type === "ask") {
    const what = msg.phase === "practice" ? "practice" : "trial";
    $("progress").textContent = `${what} ${msg.index + 1} of ${msg.total}`;
    for (const b of document.querySelectorAll(".choice")) {
      b.disabled = false;
      b.classList.remove("chosen");
    }
    only("ask");
  } else if (msg.type === "feedback") {
    const t = msg.truth;
    $("feedback-text").textContent = msg.correct
      ? "Right"
      : `It was ${t} · ${study.hello.patterns[t].name}`;
    $("feedback-text").className = "name " + (msg.correct ? "right" : "wrong");
    study.shown.push($("feedback-text").textContent);
    picture($("feedback-picture"), t);
    only("feedback");
  } else {
    $("message-text").textContent = msg.text;
    only("message");
  }
}

$("next").addEventListener("click", () => {
  const s = study.screen;
  if (!s || s.type !== "train") return;
  $("next").disabled = true;
  reply({ type: "next", id: s.id });
});

socket = DXP.openSocket(study, "connected", onMessage);
