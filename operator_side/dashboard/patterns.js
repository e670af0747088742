// Shared by the dashboard and the perception study's answer page: the colour
// scale of the tactile heatmaps, the picture of a pattern, and the page's
// socket to its node (with the run's token, see openSocket).
"use strict";

const DXP = (() => {
  // viridis at six stops: perceptually even, readable in greyscale, colour-blind safe
  const STOPS = [
    [68, 1, 84], [65, 68, 135], [42, 120, 142], [34, 168, 132], [122, 209, 81], [253, 231, 37],
  ];

  function heatColor(v, vmax = 9) {
    const t = Math.min(Math.max(v / vmax, 0), 1) * (STOPS.length - 1);
    const i = Math.min(Math.floor(t), STOPS.length - 2);
    const f = t - i;
    const c = STOPS[i].map((a, k) => Math.round(a + (STOPS[i + 1][k] - a) * f));
    return `rgb(${c[0]},${c[1]},${c[2]})`;
  }

  const ANGLES = [0, 45, 90, 135];

  // A pattern's picture: the palm's 3x3 stimulus cells (row 0 at the top,
  // nearest the fingers), the pressed cells filled, and the pipette's band
  // through them at its tilt (counter-clockwise from the rows, as in
  // docs/tactile.md).
  function drawPattern(ctx, pattern, x, y, size, opts = {}) {
    const cells = pattern.cells;
    const angle = ANGLES[Math.floor(pattern.id / 3)];
    const pitch = size / 3;
    ctx.save();
    ctx.translate(x, y);
    ctx.fillStyle = opts.background || "#f4f1ea";
    ctx.fillRect(0, 0, size, size);
    ctx.strokeStyle = "#cfc8b8";
    ctx.lineWidth = 1;
    for (let k = 1; k < 3; k++) {
      ctx.beginPath();
      ctx.moveTo(k * pitch, 0);
      ctx.lineTo(k * pitch, size);
      ctx.moveTo(0, k * pitch);
      ctx.lineTo(size, k * pitch);
      ctx.stroke();
    }
    // the band: through the centroid of the pressed cells
    let cx = 0;
    let cy = 0;
    for (const [r, c] of cells) {
      cx += (c + 0.5) * pitch;
      cy += (r + 0.5) * pitch;
    }
    cx /= cells.length;
    cy /= cells.length;
    const rad = (angle * Math.PI) / 180;
    const dx = Math.cos(rad) * size;
    const dy = -Math.sin(rad) * size; // canvas y grows downwards
    ctx.save();
    ctx.beginPath();
    ctx.rect(0, 0, size, size);
    ctx.clip();
    ctx.strokeStyle = "rgba(90, 140, 200, 0.35)";
    ctx.lineCap = "round";
    ctx.lineWidth = pitch * 0.55;
    ctx.beginPath();
    ctx.moveTo(cx - dx, cy - dy);
    ctx.lineTo(cx + dx, cy + dy);
    ctx.stroke();
    ctx.restore();
    for (let r = 0; r < 3; r++) {
      for (let c = 0; c < 3; c++) {
        const on = cells.some(([rr, cc]) => rr === r && cc === c);
        ctx.beginPath();
        ctx.arc((c + 0.5) * pitch, (r + 0.5) * pitch, pitch * (on ? 0.3 : 0.12), 0, 2 * Math.PI);
        ctx.fillStyle = on ? opts.on || "#c0392b" : "#b9b2a3";
        ctx.fill();
      }
    }
    ctx.strokeStyle = "#8a8373";
    ctx.strokeRect(0.5, 0.5, size - 1, size - 1);
    ctx.restore();
  }

  // The run's token: from the printed URL (?token=, or #token=) the first
  // time, then from this tab's sessionStorage (per origin, port included, and
  // per tab; no cookie, which the browser would send to every port of the
  // host). It leaves the address bar and the history at once, and a reload
  // finds it in the tab's storage.
  const TOKEN_KEY = "dxp-token";
  function takeToken() {
    const params = new URLSearchParams(location.search);
    let token = params.get("token");
    if (!token && location.hash.startsWith("#token=")) {
      token = decodeURIComponent(location.hash.slice("#token=".length));
    }
    if (token) {
      try {
        sessionStorage.setItem(TOKEN_KEY, token);
      } catch (e) {
        // storage refused (a private window's quota): the token lives in this page only
      }
      params.delete("token");
      const query = params.toString();
      history.replaceState(null, "", location.pathname + (query ? "?" + query : ""));
      return token;
    }
    try {
      return sessionStorage.getItem(TOKEN_KEY);
    } catch (e) {
      return null;
    }
  }
  const pageToken = takeToken(); // at once, before anything else can read the address

  // The answer to the server's challenge: HMAC-SHA256(token, context + nonce),
  // so the token itself never goes on the socket (a process squatting the
  // port while the node restarts learns nothing from our reconnects). A page
  // opened over plain HTTP under a non-loopback name has no WebCrypto; it
  // sends the token, as its URL already did.
  async function answerChallenge(nonce) {
    if (!(window.crypto && crypto.subtle)) return { type: "auth", token: pageToken };
    const enc = new TextEncoder();
    const key = await crypto.subtle.importKey(
      "raw", enc.encode(pageToken), { name: "HMAC", hash: "SHA-256" }, false, ["sign"],
    );
    const mac = await crypto.subtle.sign("HMAC", key, enc.encode("deepxpalm-page:" + nonce));
    const hex = Array.from(new Uint8Array(mac), (b) => b.toString(16).padStart(2, "0")).join("");
    return { type: "auth", mac: hex };
  }

  // A WebSocket to the node that served this page, reopened with a growing
  // back-off; the #conn element says whether it is up. Returns a sender.
  function openSocket(state, liveText, onMessage) {
    const scheme = location.protocol === "https:" ? "wss://" : "ws://";
    const conn = document.getElementById("conn");
    let ws = null;
    let proven = false;
    let retryMs = 250;
    function connect() {
      if (!pageToken) {
        conn.textContent = "no token: open the URL printed when the node started";
        conn.className = "conn";
        return;
      }
      proven = false;
      ws = new WebSocket(scheme + location.host + "/ws", ["deepxpalm.challenge"]);
      ws.onopen = () => {
        retryMs = 250;
      };
      ws.onclose = (ev) => {
        state.connected = false;
        proven = false;
        conn.textContent =
          ev.code === 4401 ? "token refused: open the URL printed at start" : "reconnecting…";
        conn.className = "conn";
        setTimeout(connect, retryMs);
        retryMs = Math.min(retryMs * 2, 4000);
      };
      ws.onmessage = (ev) => {
        const msg = JSON.parse(ev.data);
        if (!proven) {
          if (msg.type !== "auth_challenge") return;
          const socket = ws;
          answerChallenge(String(msg.nonce)).then((reply) => {
            if (socket !== ws || socket.readyState !== WebSocket.OPEN) return;
            socket.send(JSON.stringify(reply));
            proven = true;
            state.connected = true;
            conn.textContent = liveText;
            conn.className = "conn live";
          });
          return;
        }
        onMessage(msg);
      };
    }
    connect();
    return {
      isOpen: () => ws !== null && proven && ws.readyState === WebSocket.OPEN,
      send: (msg) => ws.send(JSON.stringify(msg)),
    };
  }

  return { heatColor, drawPattern, openSocket, ANGLES };
})();
