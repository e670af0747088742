// The lab's video: a WebRTC receiver whose offer and answer travel over the
// dashboard's own WebSocket (the server relays them to the robot's video
// server). When the source is the stamped test pattern, each presented
// frame's capture time is read back from its pixels and glass-to-glass
// latency is kept on dxp.video (robot/stamp.py describes the stamp).
"use strict";

const VIDEO = (() => {
  const STAMP_BITS = 40;
  const MS_MODULO = 2 ** 32;
  const MARGIN = 60;

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
      this.presented = []; // wall-clock ms of each presented frame
      this.unreadable = 0;
      this.lastCounter = null;
      this.skipped = 0; // frames that never reached the screen (counter gaps)
      this.canvas = document.createElement("canvas");
      this.ctx = null;
      this.retry = null;
    }

    async start() {
      clearTimeout(this.retry);
      if (this.pc) this.pc.close();
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
        this.status(`video ${pc.connectionState}`);
        if (pc === this.pc && (pc.connectionState === "failed" || pc.connectionState === "closed")) {
          this.retry = setTimeout(() => this.start(), 2000);
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
      this.send({ type: "video_offer", sdp: pc.localDescription.sdp });
      this.status("video: waiting for the robot");
    }

    async onAnswer(msg) {
      this.source = msg.source;
      await this.pc.setRemoteDescription({ type: "answer", sdp: msg.sdp });
      if (this.video.requestVideoFrameCallback) this.video.requestVideoFrameCallback((t, m) => this.onFrame(m));
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

    onClosed(msg) {
      this.status(msg.reason);
      this.retry = setTimeout(() => this.start(), 2000);
    }

    onFrame(meta) {
      const now = Date.now();
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
        return;
      }
      if (this.lastCounter !== null) {
        const step = (stamp.counter - this.lastCounter + 256) % 256;
        if (step > 1 && step < 128) this.skipped += step - 1; // 0: shown twice; >= 128: stale
      }
      this.lastCounter = stamp.counter;
      const latency = (now - stamp.ms + MS_MODULO) % MS_MODULO;
      this.latencies.push(latency);
      if (this.latencies.length > 20000) this.latencies.splice(0, 10000);
    }

    summary() {
      const lat = [...this.latencies].sort((a, b) => a - b);
      const pct = (p) => (lat.length ? lat[Math.min(lat.length - 1, Math.floor((p / 100) * lat.length))] : null);
      let stall = 0;
      for (let i = 1; i < this.presented.length; i++) stall = Math.max(stall, this.presented[i] - this.presented[i - 1]);
      return { frames: this.presented.length, stamped: lat.length, p50: pct(50), p99: pct(99), max_gap_ms: stall, unreadable: this.unreadable, skipped: this.skipped };
    }
  }

  return { readStamp, Receiver };
})();
