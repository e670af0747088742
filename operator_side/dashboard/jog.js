// Jogging the arm from the page: keyboard, on-screen buttons, gamepads (Gamepad
// API) and 3Dconnexion SpaceMice (WebHID). Every source is hold-to-move: the
// arm moves only while a key, a button or the device's enable button is held,
// and the moment nothing is held one arm_jog_end goes out. Jogs go to the
// dashboard server at send_rate_hz; the server caps them again and hands them
// to the operator node's command sender; the robot clips them to its envelope
// and stops on its own deadman when they cease.
//
// STOP (the page's button, Esc, Space, the gamepad's stop button) sends
// arm_stop, which latches on the robot: it refuses every jog, from this page
// or any other, until the lease holder resumes. While the robot reports its
// latch this page sends no jog either, and after a resume it waits until
// every input is released, so a resume never restarts a held jog.
//
// The assist (a held key, the gamepad's assist button, the page's hold-to-assist
// button) is held like a jog: while held and no jog is, arm_assist goes out at
// send_rate_hz and the robot aligns its grasp to what it feels; let go, one
// arm_jog_end ends it. A jog held beside it wins (and ends it on the robot).
//
// The decoding and shaping functions are pure and exported on JOG so a test
// can run them on recorded raw input in a real browser.
"use strict";

const JOG = (() => {
  const TWIST = ["vx", "vy", "vz", "wx", "wy", "wz"];
  const TERM = /([+-]?)(axis|button|tx|ty|tz|rx|ry|rz)(\d*)/y;

  // "button7-button6" -> [{sign: 1, name: "button", index: 7}, {sign: -1, ...}]
  function parseMapping(expr) {
    const text = expr.replace(/\s+/g, "");
    const out = [];
    TERM.lastIndex = 0;
    while (TERM.lastIndex < text.length) {
      const start = TERM.lastIndex;
      const m = TERM.exec(text);
      if (!m || TERM.lastIndex === start) throw new Error(`cannot read mapping ${expr}`);
      out.push({ sign: m[1] === "-" ? -1 : 1, name: m[2], index: m[3] ? Number(m[3]) : 0 });
    }
    return out;
  }

  // Dead zone, then the response curve, on one axis in [-1, 1]: the output
  // starts from 0 at the dead zone's edge (no jump) and reaches 1 at full travel.
  function shape(x, deadZone, exponent) {
    const a = Math.min(Math.abs(x), 1);
    if (!(a > deadZone)) return 0;
    return Math.sign(x) * Math.pow((a - deadZone) / (1 - deadZone), exponent);
  }

  // --------------------------------------------------------------- SpaceMouse
  // 3Dconnexion HID input reports (the report id is not part of `bytes`):
  //   id 1, 6 bytes: translation x, y, z as int16 little-endian (older models)
  //   id 1, 12 bytes: translation then rotation, 6 x int16 (newer models, one report)
  //   id 2, 6 bytes: rotation x, y, z (older models)
  //   id 3: buttons, one bit each, little-endian (bit 0: left, bit 1: right)
  function decodeSpaceMouse(reportId, bytes, state) {
    const s = state || { t: [0, 0, 0], r: [0, 0, 0], buttons: 0 };
    const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    const i16 = (k) => dv.getInt16(2 * k, true);
    if (reportId === 1 && bytes.byteLength >= 12) {
      s.t = [i16(0), i16(1), i16(2)];
      s.r = [i16(3), i16(4), i16(5)];
    } else if (reportId === 1 && bytes.byteLength >= 6) {
      s.t = [i16(0), i16(1), i16(2)];
    } else if (reportId === 2 && bytes.byteLength >= 6) {
      s.r = [i16(0), i16(1), i16(2)];
    } else if (reportId === 3) {
      let b = 0;
      for (let k = 0; k < Math.min(bytes.byteLength, 4); k++) b |= bytes[k] << (8 * k);
      s.buttons = b >>> 0;
    }
    return s;
  }

  // A unit twist (each component in [-1, 1]) from a device's inputs.
  function mapTwist(mapping, read, deadZone, exponent) {
    return mapping.map((expr) => {
      let v = 0;
      for (const term of parseMapping(expr)) v += term.sign * read(term);
      return shape(Math.max(-1, Math.min(1, v)), deadZone, exponent);
    });
  }

  function spaceMouseTwist(state, cfg) {
    const enabled = ((state.buttons >>> cfg.enable_button) & 1) === 1;
    const names = { tx: state.t[0], ty: state.t[1], tz: state.t[2], rx: state.r[0], ry: state.r[1], rz: state.r[2] };
    const twist = mapTwist(cfg.mapping, (t) => names[t.name] / cfg.full_scale, cfg.dead_zone, cfg.curve_exponent);
    return { enabled, twist: enabled ? twist : [0, 0, 0, 0, 0, 0] };
  }

  // ------------------------------------------------------------------ gamepad
  function gamepadTwist(pad, cfg) {
    const btn = (i) => {
      const b = pad.buttons[i];
      if (b == null) return 0;
      return typeof b === "object" ? (b.value ?? (b.pressed ? 1 : 0)) : Number(b);
    };
    const enabled = btn(cfg.enable_button) > 0.5;
    const read = (t) => (t.name === "axis" ? pad.axes[t.index] ?? 0 : btn(t.index));
    const twist = mapTwist(cfg.mapping, read, cfg.dead_zone, cfg.curve_exponent);
    const stop = cfg.stop_button >= 0 && btn(cfg.stop_button) > 0.5;
    const assist = cfg.assist_button >= 0 && btn(cfg.assist_button) > 0.5;
    return { enabled, stop, assist, twist: enabled ? twist : [0, 0, 0, 0, 0, 0] };
  }

  // ----------------------------------------------------------------- keyboard
  function keyboardTwist(held, keymap) {
    const twist = [0, 0, 0, 0, 0, 0];
    for (const key of held) {
      const target = keymap[key];
      if (!target) continue;
      twist[TWIST.indexOf(target.slice(1))] += target[0] === "-" ? -1 : 1;
    }
    return twist.map((v) => Math.max(-1, Math.min(1, v)));
  }

  // Unit twist -> m/s and rad/s at the speed scale; each part's norm capped at
  // the scaled cap (direction kept), so a diagonal is no faster than an axis.
  function scaleTwist(unit, jog, speedScale) {
    const lin = speedScale * jog.max_linear_speed_m_s;
    const ang = speedScale * jog.max_angular_speed_rad_s;
    const v = unit.map((u, i) => u * (i < 3 ? lin : ang));
    for (const [a, cap] of [[0, lin], [3, ang]]) {
      const n = Math.hypot(v[a], v[a + 1], v[a + 2]);
      if (n > cap) for (let i = a; i < a + 3; i++) v[i] *= cap / n;
    }
    return v;
  }

  // -------------------------------------------------------------- the jogger
  // Polls every source at send_rate_hz, sends arm_jog while anything is held
  // and one arm_jog_end when it stops. `send(msg)` returns false when not
  // connected; `onStop()` is called when a gamepad's stop button goes down.
  class Jogger {
    constructor(cfg, send, onStop) {
      this.cfg = cfg;
      this.send = send;
      this.onStop = onStop || (() => this.stop(true));
      this.speedScale = cfg.default_speed_scale;
      this.keys = new Set();
      this.buttons = new Set(); // on-screen buttons held, as "+vx" etc., and "assist"
      this.spacemouse = null; // decoded state of the connected SpaceMouse, if any
      this.hidDevice = null;
      this.moving = false;
      this.latched = false; // after STOP: nothing moves until every input is released
      this.robotLatched = false; // the robot's own latch, from its heartbeat: nothing moves
      this.padStops = new Set(); // gamepads whose stop button is down (a press stops once)
      // the page is hidden or being left: no input moves the arm, however it is held (a
      // gamepad's enable still reads as pressed on the ticks between pagehide and the end)
      this.away = false;
      this.last = { source: "none", velocity: [0, 0, 0, 0, 0, 0], enabled: false };
      this.sent = { jogs: 0, stops: 0, assists: 0 };
      this.timer = setInterval(() => this.tick(), 1000 / cfg.send_rate_hz);
    }

    // What each source asks for now: a unit twist and whether its enable is held.
    sources() {
      const out = [];
      const pads = navigator.getGamepads ? navigator.getGamepads() : [];
      for (const pad of pads) {
        if (pad && pad.connected !== false) out.push({ source: `gamepad ${pad.index}`, ...gamepadTwist(pad, this.cfg.gamepad) });
      }
      if (this.spacemouse) out.push({ source: "spacemouse", ...spaceMouseTwist(this.spacemouse, this.cfg.spacemouse) });
      const held = keyboardTwist(this.keys, this.cfg.keyboard);
      const twists = [...this.buttons].filter((b) => b !== "assist");
      const onScreen = keyboardTwist(twists, Object.fromEntries(twists.map((b) => [b, b])));
      const assistKey = this.keys.has(this.cfg.assist_key);
      out.push({ source: "keyboard", enabled: this.keys.size > 0, assist: assistKey, twist: held });
      out.push({ source: "screen", enabled: twists.length > 0, assist: this.buttons.has("assist"), twist: onScreen });
      return out;
    }

    // An input was let go (keyup, pointerup): with nothing left held, the page's own
    // latch clears now rather than at the next tick, so a quick release-and-press moves.
    released() {
      const wants = this.sources().some((x) => x.assist || (x.enabled && x.twist.some((v) => v !== 0)));
      if (!wants && !this.robotLatched) this.latched = false;
    }

    tick() {
      if (this.away) {
        if (this.moving) this.stop();
        return;
      }
      const sources = this.sources();
      for (const s of sources) {
        if (!s.source.startsWith("gamepad")) continue;
        if (s.stop && !this.padStops.has(s.source)) this.onStop();
        if (s.stop) this.padStops.add(s.source);
        else this.padStops.delete(s.source);
      }
      const active = sources.filter((s) => s.enabled && s.twist.some((v) => v !== 0));
      const unit = [0, 0, 0, 0, 0, 0];
      for (const s of active) s.twist.forEach((v, i) => (unit[i] += v));
      const clipped = unit.map((v) => Math.max(-1, Math.min(1, v)));
      const velocity = scaleTwist(clipped, this.cfg, this.speedScale);
      const wants = velocity.some((v) => v !== 0);
      const assisting = sources.filter((s) => s.assist);
      const assist = !wants && assisting.length > 0;
      if (!wants && !assist && !this.robotLatched) this.latched = false;
      const by = (assist ? assisting : active).map((s) => s.source).join("+") || "none";
      this.last = { source: by, velocity, enabled: active.length > 0, assist };
      if (wants && !this.latched) {
        if (this.send({ type: "command", action: "arm_jog", velocity })) {
          this.moving = true;
          this.sent.jogs++;
        }
      } else if (assist && !this.latched) {
        if (this.send({ type: "command", action: "arm_assist" })) {
          this.moving = true;
          this.sent.assists++;
        }
      } else if (this.moving) {
        this.stop();
      }
    }

    // latch: STOP (arm_stop, latched on the robot); otherwise the end of a jog
    stop(latch = false) {
      this.latched = this.latched || latch;
      this.moving = false;
      this.sent.stops++;
      this.send({ type: "command", action: latch ? "arm_stop" : "arm_jog_end" });
    }

    // The robot's latch as its heartbeat reports it: while set, this page jogs nothing,
    // and once released it still waits for every input to be let go.
    setRobotLatched(latched) {
      this.robotLatched = latched;
      if (latched) this.latched = true;
    }

    // The page is hidden or left (true), or shown again (false).
    setAway(away) {
      this.away = away;
      if (away) this.releaseAll();
    }

    releaseAll() {
      this.keys.clear();
      this.buttons.clear();
      if (this.spacemouse) this.spacemouse.buttons = 0;
      if (this.moving) this.stop();
    }

    // One raw HID input report, from the device or from a test.
    hidReport(reportId, bytes) {
      this.spacemouse = decodeSpaceMouse(reportId, bytes, this.spacemouse);
    }

    async connectSpaceMouse(device) {
      if (!device.opened) await device.open();
      this.hidDevice = device;
      this.spacemouse = decodeSpaceMouse(0, new Uint8Array(0), null);
      device.addEventListener("inputreport", (e) =>
        this.hidReport(e.reportId, new Uint8Array(e.data.buffer, e.data.byteOffset, e.data.byteLength)),
      );
    }

    spaceMouseLost() {
      this.spacemouse = null;
      this.hidDevice = null;
      if (this.moving) this.stop();
    }
  }

  // 3Dconnexion's current vendor id and Logitech's (older SpaceMice, SpaceNavigator)
  const HID_FILTERS = [{ vendorId: 0x256f }, { vendorId: 0x046d, usagePage: 0x01, usage: 0x08 }];

  return { TWIST, parseMapping, shape, decodeSpaceMouse, spaceMouseTwist, gamepadTwist, keyboardTwist, scaleTwist, Jogger, HID_FILTERS };
})();
