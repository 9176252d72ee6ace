// e3dpsm serve page: one WebSocket, a 3D skeleton on a 2D canvas, the event frame, readouts.
// Plain JS, no library and no network beyond this server. Protocol: docs/serve.md.
"use strict";
(function () {
  const COLORS = { pose: "#f2c230", compare: "#38c6f4", gt: "#4cd964" };
  const REPORT_PERIOD_MS = 1000;
  const MAX_REPORT_SAMPLES = 500; // the server accepts at most 512 per message
  // A background tab's timers are throttled (down to once a minute): the samples kept for the
  // next report are capped, so that the report stays a few messages under the server's rate limit.
  const MAX_PENDING_SAMPLES = 8 * MAX_REPORT_SAMPLES;
  const MAX_KEPT_SAMPLES = 100000;
  const $ = (id) => document.getElementById(id);
  const nowMs = () => performance.timeOrigin + performance.now(); // same clock as the server's time.time()

  // Counters the readouts show; window.e3dpsm exposes them to tests and benchmarks.
  const state = {
    poseCount: 0, received: 0, gaps: 0, outOfOrder: 0, lastSeq: null, latencies: [], pending: [],
    drawTimes: [], hello: null, pose: null, compare: null, gt: null, connected: false, closes: [],
  };
  window.e3dpsm = state;

  // ---- 3D view: orbit (drag), zoom (wheel), reset (double-click) ----
  const view = { yaw: 0.6, pitch: -0.35, distance: 2500, center: null };
  const canvas = $("skeleton");
  const ctx = canvas.getContext("2d");
  let drag = null;
  canvas.addEventListener("mousedown", (e) => { drag = { x: e.clientX, y: e.clientY }; });
  window.addEventListener("mouseup", () => { drag = null; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    view.yaw += (e.clientX - drag.x) * 0.01;
    view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + (e.clientY - drag.y) * 0.01));
    drag = { x: e.clientX, y: e.clientY };
    draw();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    view.distance = Math.max(500, Math.min(20000, view.distance * Math.exp(e.deltaY * 0.001)));
    draw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { view.yaw = 0.6; view.pitch = -0.35; view.distance = 2500; draw(); });

  // Camera frame (x right, y down, z forward, mm) -> screen, orbiting around the pose's centre.
  function project(p) {
    const c = view.center;
    let x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
    const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw);
    [x, z] = [cy * x + sy * z, -sy * x + cy * z];
    const cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    [y, z] = [cp * y - sp * z, sp * y + cp * z];
    const depth = Math.max(z + view.distance, 50);
    const f = canvas.height * 1.4;
    return [canvas.width / 2 + (f * x) / depth, canvas.height / 2 + (f * y) / depth];
  }

  function drawSkeleton(pose, color, width) {
    if (!pose || !state.hello) return;
    const pts = pose.map(project);
    ctx.strokeStyle = color; ctx.lineWidth = width; ctx.lineCap = "round";
    ctx.beginPath();
    for (const [a, b] of state.hello.bones) { ctx.moveTo(pts[a][0], pts[a][1]); ctx.lineTo(pts[b][0], pts[b][1]); }
    ctx.stroke();
    ctx.fillStyle = color;
    for (const [x, y] of pts) { ctx.fillRect(x - 2.5, y - 2.5, 5, 5); }
  }

  function drawAxes() {
    const c = view.center, len = 300;
    const o = project(c);
    [[[len, 0, 0], "#a44", "x"], [[0, len, 0], "#4a4", "y"], [[0, 0, len], "#44a", "z"]].forEach(([d, col, name]) => {
      const e = project([c[0] + d[0], c[1] + d[1], c[2] + d[2]]);
      ctx.strokeStyle = col; ctx.lineWidth = 1; ctx.beginPath(); ctx.moveTo(o[0], o[1]); ctx.lineTo(e[0], e[1]); ctx.stroke();
      ctx.fillStyle = col; ctx.fillText(name, e[0] + 3, e[1] + 3);
    });
  }

  function draw() {
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!state.pose) return;
    if (!view.center) view.center = mean(state.pose);
    drawAxes();
    if (state.gt) drawSkeleton(state.gt, COLORS.gt, 3);
    if (state.compare) drawSkeleton(state.compare, COLORS.compare, 2);
    drawSkeleton(state.pose, COLORS.pose, 3);
  }

  function mean(pose) {
    const m = [0, 0, 0];
    for (const p of pose) { m[0] += p[0] / pose.length; m[1] += p[1] / pose.length; m[2] += p[2] / pose.length; }
    return m;
  }

  // ---- event frame: two uint8 planes (positive, negative) interleaved per pixel ----
  const frameCanvas = $("frame");
  const frameCtx = frameCanvas.getContext("2d");
  function drawFrame(m) {
    if (frameCanvas.width !== m.width || frameCanvas.height !== m.height) {
      frameCanvas.width = m.width; frameCanvas.height = m.height;
    }
    const bytes = atob(m.data);
    const img = frameCtx.createImageData(m.width, m.height);
    const px = img.data;
    for (let i = 0, j = 0; i < m.width * m.height; i++, j += m.channels) {
      const pos = bytes.charCodeAt(j), neg = m.channels > 1 ? bytes.charCodeAt(j + 1) : 0;
      px[4 * i] = pos ? 80 + (pos * 175) / 255 : 12;
      px[4 * i + 1] = 13;
      px[4 * i + 2] = neg ? 80 + (neg * 175) / 255 : 16;
      px[4 * i + 3] = 255;
    }
    frameCtx.putImageData(img, 0, 0);
  }

  // ---- messages ----
  function onHello(m) {
    state.hello = m;
    view.center = null;
    $("models").textContent = m.models.join(" vs ");
    $("source").textContent = `${m.source} (${m.sensor_hw[1]}×${m.sensor_hw[0]}, ${m.window_ms} ms windows${m.live ? ", live" : ""})`;
    const items = [[COLORS.pose, m.models[0]]];
    if (m.models.length > 1) items.push([COLORS.compare, m.models[1]]);
    if (m.ground_truth) items.push([COLORS.gt, "ground truth"]);
    $("legend").innerHTML = "";
    for (const [color, label] of items) {
      const span = document.createElement("span");
      const swatch = document.createElement("i");
      swatch.style.background = color;
      span.append(swatch, document.createTextNode(label));
      $("legend").append(span);
    }
  }

  function onPose(m) {
    state.received += 1;
    if (state.lastSeq !== null) {
      if (m.seq <= state.lastSeq) state.outOfOrder += 1;
      else state.gaps += m.seq - state.lastSeq - 1;
    }
    state.lastSeq = m.seq;
    state.pose = m.pose; state.compare = m.compare; state.gt = m.gt;
    draw();
    const drawn = nowMs();
    state.poseCount += 1;
    $("pose-count").textContent = String(state.poseCount);
    const latency = drawn - m.window_end_wall_ms;
    state.pending.push(Math.round(latency * 1000) / 1000);
    if (state.latencies.length < MAX_KEPT_SAMPLES) state.latencies.push(latency);
    state.drawTimes.push(drawn);
    $("stream-time").textContent = (m.t_us / 1e6).toFixed(2);
    $("step").textContent = m.step_ms.toFixed(2) + (m.compare_step_ms != null ? " / " + m.compare_step_ms.toFixed(2) : "");
  }

  function onStatus(m) { setStatus(m.message, m.state === "source stopped"); }

  function onStats(m) {
    $("dropped").textContent = String(m.poses_dropped);
    $("frames-dropped").textContent = String(m.frames_dropped);
  }

  function setStatus(text, bad) { const s = $("status"); s.textContent = text; s.className = bad ? "bad" : ""; }

  // ---- readouts and the latency report, once a second ----
  function percentile(values, q) {
    if (!values.length) return null;
    const sorted = values.slice().sort((a, b) => a - b);
    return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  }

  function tick() {
    const now = nowMs();
    state.drawTimes = state.drawTimes.filter((t) => now - t <= 1000);
    $("hz").textContent = state.received ? String(state.drawTimes.length) : "–";
    const recent = state.latencies.slice(-250);
    if (recent.length) $("latency").textContent = `${percentile(recent, 0.5).toFixed(1)} / ${percentile(recent, 0.99).toFixed(1)}`;
    $("gaps").textContent = String(state.gaps);
    $("out-of-order").textContent = String(state.outOfOrder);
    if (state.pending.length > MAX_PENDING_SAMPLES) state.pending.splice(0, state.pending.length - MAX_PENDING_SAMPLES);
    if (socket && socket.readyState === WebSocket.OPEN && (state.pending.length || state.received)) {
      while (true) {
        const samples = state.pending.splice(0, MAX_REPORT_SAMPLES);
        socket.send(JSON.stringify({ type: "latency", samples_ms: samples, received: state.received,
                                     drawn: state.poseCount, gaps: state.gaps, out_of_order: state.outOfOrder }));
        if (!state.pending.length) break;
      }
    }
  }
  setInterval(tick, REPORT_PERIOD_MS);

  // ---- connection, reconnecting after any close; the token travels in the page's cookie ----
  let socket = null;
  let retryMs = 500;
  function connect() {
    const url = `${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`;
    socket = new WebSocket(url);
    socket.onopen = () => {
      state.connected = true; state.lastSeq = null; retryMs = 500;
      setStatus("connected", false);
      socket.send(JSON.stringify({ type: "hello", agent: navigator.userAgent }));
    };
    socket.onmessage = (event) => {
      const m = JSON.parse(event.data);
      if (m.type === "pose") onPose(m);
      else if (m.type === "frame") drawFrame(m);
      else if (m.type === "stats") onStats(m);
      else if (m.type === "status") onStatus(m);
      else if (m.type === "hello") onHello(m);
    };
    socket.onclose = (event) => {
      state.connected = false;
      state.closes.push({ code: event.code, reason: event.reason });
      const why = event.reason ? `${event.reason} (${event.code})` : `code ${event.code}`;
      const keep = $("status").className === "bad" ? $("status").textContent + "; " : "";
      setStatus(`${keep}disconnected: ${why}; reconnecting…`, true);
      setTimeout(connect, retryMs);
      retryMs = Math.min(retryMs * 2, 5000);
    };
  }
  connect();
})();
