// The lab's video: a WebRTC receiver whose offer and answer travel over the
// dashboard's own WebSocket (the server relays them to the robot's video
// server). When the source is the stamped test pattern, each presented
// frame's capture time is read back from its pixels and glass-to-glass
// latency is kept on dxp.video (robot/stamp.py describes the stamp).
//
// The receiver reconnects by itself, with backoff, when its peer connection
// fails, the robot closes the session (its video server restarted, say) or
// no frame is decoded for a while: the first retries come fast, since a
// restarted video server is back within seconds, later ones slower.
"use strict";

const VIDEO = (() => {
  const STAMP_BITS = 40;
  const MS_MODULO = 2 ** 32;
  const MARGIN = 60;
  const RETRY_FIRST_MS = 250; // then doubled per failed attempt, up to:
  const RETRY_MAX_MS = 1000; // while the outage is young (a restart: seconds)
  const RETRY_SLOW_MS = 5000; // after RETRY_FAST_TRIES attempts without a frame
  const RETRY_FAST_TRIES = 8;
  const FIRST_FRAME_MS = 6000; // after the answer: ICE, DTLS, the first keyframe
  const STALL_MS = 3000; // no frame decoded for this long: reconnect
  const WATCH_MS = 500;
  const FRESHNESS_MS = 100; // how often the picture's age is looked at, frames or not

  // (capture ms modulo 2^32, counter) from the stamp rows of an RGBA band, or null
  function readStamp(data, width) {
    const c = Math.max(4, Math.floor(width / STAMP_BITS));
    const q = Math.max(1, Math.floor(c / 4));
    const cell = (row, bit) => {
      let sum = 0;
      let n = 0;
      for (let y = row * c + q; y < row * c + c - q; y++) {
        for (let x = bit * c + q; x < bit * c + c - q; x++) {
          const i = 4 * (y * width + x);
          sum += (data[i] + data[i + 1] + data[i + 2]) / 3;
          n++;
        }
      }
      return sum / n;
    };
    let hi = 0; // the top 32 bits: milliseconds
    let counter = 0;
    for (let b = 0; b < STAMP_BITS; b++) {
      const diff = cell(0, b) - cell(1, b);
      if (Math.abs(diff) < MARGIN) return null;
      const bit = diff > 0 ? 1 : 0;
      if (b < 32) hi = hi * 2 + bit;
      else counter = counter * 2 + bit;
    }
    return { ms: hi, counter };
  }

  class Receiver {
    constructor(videoEl, send, status, iceServers, iceTransportPolicy) {
      this.video = videoEl;
      this.iceServers = iceServers || []; // the dashboard's: none = host candidates only
      this.iceTransportPolicy = iceTransportPolicy || "all"; // "relay": through TURN only
      this.send = send;
      this.status = status;
      this.pc = null;
      this.source = null;
      this.latencies = []; // glass-to-glass, ms, one per presented stamped frame
      this.timeline = []; // [presented at, captured at] wall-clock ms, per stamped frame
      this.presented = []; // wall-clock ms of each presented frame
      this.unreadable = 0;
      this.unreadableAt = []; // the index (in presented) of each frame whose stamp was unreadable
      this.lastCounter = null;
      this.skipped = 0; // frames that never reached the screen (counter gaps)
      this.canvas = document.createElement("canvas");
      this.ctx = null;
      this.retry = null;
      this.failures = 0; // attempts since frames last flowed
      this.reconnects = 0; // sessions started again after a failure, a close or a stall
      this.lastReason = null;
      this.lastStamp = null; // the last stamped frame's capture time (ms modulo 2^32)
      this.answeredAt = null; // when this session's answer was applied (ms)
      this.decodedAt = null; // when framesDecoded last grew (ms)
      this.framesDecoded = 0;
      this.presentedAt = null; // Date.now() when the latest frame reached the screen
      this.stampedAt = null; // Date.now() when lastStamp was read
      this.freshness = { state: "none", age_ms: null };
      this.freshnessChanges = []; // {state, t: Date.now()} each time the state changed
      this.watch = setInterval(() => this.checkFlow(), WATCH_MS);
    }

    async start() {
      clearTimeout(this.retry);
      this.retry = null;
      const old = this.pc;
      this.pc = null; // its state changes from here on are not ours to act on
      if (old) old.close();
      this.answeredAt = this.decodedAt = null;
      this.framesDecoded = 0;
      this.lastCounter = null; // a restarted server counts its frames from 0
      const pc = new RTCPeerConnection({
        iceServers: this.iceServers,
        iceTransportPolicy: this.iceTransportPolicy,
      });
      this.pc = pc;
      pc.addTransceiver("video", { direction: "recvonly" });
      pc.ontrack = (e) => {
        this.video.srcObject = e.streams[0] || new MediaStream([e.track]);
        this.video.play().catch(() => {});
      };
      pc.onconnectionstatechange = () => {
        if (pc !== this.pc) return;
        this.status(`video ${pc.connectionState}`);
        if (pc.connectionState === "failed" || pc.connectionState === "closed") {
          this.reconnect(`video ${pc.connectionState}`);
        }
      };
      await pc.setLocalDescription(await pc.createOffer());
      await new Promise((resolve) => {
        // the whole offer at once (no trickle): on a LAN or loopback gathering takes milliseconds
        if (pc.iceGatheringState === "complete") return resolve();
        const done = () => pc.iceGatheringState === "complete" && resolve();
        pc.addEventListener("icegatheringstatechange", done);
        setTimeout(resolve, 2000);
      });
      if (pc !== this.pc) return; // started again meanwhile
      this.send({ type: "video_offer", sdp: pc.localDescription.sdp });
      this.status("video: waiting for the robot");
    }

    // Start again after a delay that grows with each attempt that brought no frame.
    reconnect(reason) {
      this.lastReason = reason;
      if (this.retry) return; // one attempt pending is enough
      const cap = this.failures < RETRY_FAST_TRIES ? RETRY_MAX_MS : RETRY_SLOW_MS;
      const delay = Math.min(cap, RETRY_FIRST_MS * 2 ** this.failures);
      this.failures++;
      this.status(`${reason}; video again in ${(delay / 1000).toFixed(1)} s`);
      this.retry = setTimeout(() => {
        this.retry = null;
        this.reconnects++;
        this.start().catch((e) => this.reconnect(`video: ${e}`));
      }, delay);
    }

    // Frames decoded, from the statistics (they count in a hidden tab too, where
    // requestVideoFrameCallback does not run); none for too long: reconnect.
    async checkFlow() {
      const pc = this.pc;
      if (!pc || this.answeredAt === null || this.retry) return;
      let decoded = 0;
      try {
        (await pc.getStats()).forEach((r) => {
          if (r.type === "inbound-rtp" && r.kind === "video") decoded += r.framesDecoded || 0;
        });
      } catch (e) {
        return; // closed meanwhile
      }
      if (pc !== this.pc || this.answeredAt === null) return;
      const now = Date.now();
      if (decoded > this.framesDecoded) {
        this.framesDecoded = decoded;
        this.decodedAt = now;
        this.failures = 0; // flowing: the next outage starts with fast retries again
        return;
      }
      if (this.decodedAt === null ? now - this.answeredAt > FIRST_FRAME_MS : now - this.decodedAt > STALL_MS) {
        this.reconnect(this.decodedAt === null ? "video: no picture came" : "video stalled");
      }
    }

    async onAnswer(msg) {
      const pc = this.pc;
      if (!pc || pc.signalingState !== "have-local-offer") return; // an older offer's answer
      this.source = msg.source;
      try {
        await pc.setRemoteDescription({ type: "answer", sdp: msg.sdp });
      } catch (e) {
        this.reconnect(`video: ${e}`);
        return;
      }
      this.answeredAt = Date.now();
      if (this.video.requestVideoFrameCallback && !this.frameCallback) {
        this.frameCallback = true; // one chain of callbacks for the element, whatever the session
        this.video.requestVideoFrameCallback((t, m) => this.onFrame(m));
      }
    }

    async path() {
      // the candidate types of the pair in use: "relay" on either end means through TURN
      if (!this.pc) return null;
      const stats = await this.pc.getStats();
      let out = null;
      stats.forEach((r) => {
        if (r.type !== "transport" || !r.selectedCandidatePairId) return;
        const pair = stats.get(r.selectedCandidatePairId);
        const local = pair && stats.get(pair.localCandidateId);
        const remote = pair && stats.get(pair.remoteCandidateId);
        if (local && remote) out = { local: local.candidateType, remote: remote.candidateType };
      });
      return out;
    }

    // The age of the picture on screen, checked on a timer: a frozen picture has no
    // frame callback to say so. Stamped: now minus its capture time (the robot's clock);
    // otherwise the time since a frame last reached the screen.
    watchFreshness(staleMs, draw) {
      this.staleMs = staleMs;
      const look = () => {
        const f = this.ageNow();
        if (f.state !== this.freshness.state) {
          this.freshnessChanges.push({ state: f.state, t: Date.now() });
          if (this.freshnessChanges.length > 1000) this.freshnessChanges.splice(0, 500);
        }
        this.freshness = f;
        draw(f);
      };
      look();
      this.freshnessTimer = setInterval(look, FRESHNESS_MS);
    }

    ageNow() {
      const now = Date.now();
      let age = null;
      if (this.presentedAt === null) return { state: "none", age_ms: null };
      if (this.stampedAt !== null && this.stampedAt >= this.presentedAt - 1) {
        age = (now - this.lastStamp + MS_MODULO) % MS_MODULO;
      } else {
        age = now - this.presentedAt; // an unstamped source, or this frame's stamp unreadable
      }
      return { state: age > this.staleMs ? "stale" : "fresh", age_ms: age };
    }

    onClosed(msg) {
      this.reconnect(msg.reason || "video closed");
    }

    onFrame(meta) {
      const now = Date.now();
      this.presentedAt = now;
      this.presented.push(now);
      if (this.source === "test_pattern") this.measure(now, meta);
      if (this.presented.length > 20000) this.presented.splice(0, 10000);
      this.video.requestVideoFrameCallback((t, m) => this.onFrame(m));
    }

    measure(now, meta) {
      const w = meta.width || this.video.videoWidth;
      const band = 2 * Math.max(4, Math.floor(w / STAMP_BITS));
      if (!w) return;
      if (this.canvas.width !== w) {
        this.canvas.width = w;
        this.canvas.height = band;
        this.ctx = this.canvas.getContext("2d", { willReadFrequently: true });
      }
      this.ctx.drawImage(this.video, 0, 0, w, band, 0, 0, w, band);
      const stamp = readStamp(this.ctx.getImageData(0, 0, w, band).data, w);
      if (!stamp) {
        this.unreadable++;
        this.unreadableAt.push(this.presented.length); // which frames: the first few, or any
        return;
      }
      if (this.lastCounter !== null) {
        const step = (stamp.counter - this.lastCounter + 256) % 256;
        if (step > 1 && step < 128) this.skipped += step - 1; // 0: shown twice; >= 128: stale
      }
      this.lastCounter = stamp.counter;
      this.lastStamp = stamp.ms;
      this.stampedAt = now;
      const latency = (now - stamp.ms + MS_MODULO) % MS_MODULO;
      this.latencies.push(latency);
      if (this.latencies.length > 20000) this.latencies.splice(0, 10000);
      this.timeline.push([now, now - latency]);
      if (this.timeline.length > 20000) this.timeline.splice(0, 10000);
    }

    summary() {
      const lat = [...this.latencies].sort((a, b) => a - b);
      const pct = (p) => (lat.length ? lat[Math.min(lat.length - 1, Math.floor((p / 100) * lat.length))] : null);
      let stall = 0;
      for (let i = 1; i < this.presented.length; i++) stall = Math.max(stall, this.presented[i] - this.presented[i - 1]);
      return { frames: this.presented.length, stamped: lat.length, p50: pct(50), p99: pct(99), max_gap_ms: stall, unreadable: this.unreadable, unreadable_at: this.unreadableAt.slice(0, 20), skipped: this.skipped, reconnects: this.reconnects, last_reason: this.lastReason };
    }
  }

  return { readStamp, Receiver };
})();
