(function () {
  // one data block per model (the largest first); the picker chooses the one drawn
  const blocks = Array.from(document.querySelectorAll("script[type='application/json'][id^='model-data']"));
  const bytes = s => Uint8Array.from(atob(s), c => c.charCodeAt(0));
  const cv = document.getElementById('model-view'), ctx = cv.getContext('2d'), tip = document.getElementById('model-tip');
  const pick = document.getElementById('model-pick');
  let D = null, RGB = null, P = null, n = 0;
  let v = null, home = null, hover = -1, pinned = -1, drag = null, W = 0, H = 0, r = 1;
  function load(k) {  // model k's points and cameras, seen from its first view
    D = JSON.parse(blocks[k].textContent);
    const Q = new Uint16Array(bytes(D.points).buffer);
    RGB = bytes(D.colors); n = Q.length / 3; P = new Float32Array(3 * n);
    for (let i = 0; i < 3 * n; i++) P[i] = D.quant.lo[i % 3] + Q[i] * D.quant.step[i % 3];
    document.getElementById('model-legend').innerHTML = D.legend;
    document.getElementById('model-note').textContent = D.note;
    v = {yaw: D.yaw, pitch: 0.45, zoom: 1, px: 0, py: 0}; hover = -1; pinned = -1; show(-1);
    setup(); fit(); home = Object.assign({}, v); draw();
  }
  function setup() { r = window.devicePixelRatio || 1; W = cv.clientWidth * r; H = cv.clientHeight * r; cv.width = W; cv.height = H; }
  function project(p) {  // display frame (z up) -> [screen x, screen y, depth], device pixels
    const cy = Math.cos(v.yaw), sy = Math.sin(v.yaw), cp = Math.cos(v.pitch), sp = Math.sin(v.pitch);
    const x = cy * p[0] - sy * p[1], y = sy * p[0] + cy * p[1], z = p[2];
    const d = cp * y - sp * z + D.dist, F = 0.8 * Math.min(W, H) * v.zoom;
    return [W / 2 + v.px * r + F * x / d, H / 2 + v.py * r - F * (sp * y + cp * z) / d, d];
  }
  function fit() {  // zoom and pan so that all cameras and 96 % of the points fill the canvas
    const xs = [], ys = [], cx = [], cy = [];
    for (let i = 0; i < n; i += Math.ceil(n / 3000)) { const q = project([P[3 * i], P[3 * i + 1], P[3 * i + 2]]); if (q[2] > 0.05) { xs.push(q[0]); ys.push(q[1]); } }
    D.cameras.forEach(c => { const q = project(c.c); if (q[2] > 0.05) { cx.push(q[0]); cy.push(q[1]); } });
    xs.sort((a, b) => a - b); ys.sort((a, b) => a - b);
    const k = Math.floor(0.02 * xs.length), m = xs.length - 1 - k;
    const x0 = Math.min(...cx, xs.length ? xs[k] : Infinity), x1 = Math.max(...cx, xs.length ? xs[m] : -Infinity);
    const y0 = Math.min(...cy, ys.length ? ys[k] : Infinity), y1 = Math.max(...cy, ys.length ? ys[m] : -Infinity);
    if (!(x1 > x0 && y1 > y0)) return;
    const f = Math.min(0.85 * W / (x1 - x0), 0.8 * H / (y1 - y0));  // screen offsets scale with zoom: exact in one step
    v.zoom *= f; v.px = (v.px * r - ((x0 + x1) / 2 - W / 2)) * f / r; v.py = (v.py * r - ((y0 + y1) / 2 - H / 2)) * f / r;
  }
  function draw() {
    const img = ctx.createImageData(W, H), px = img.data, zb = new Float32Array(W * H).fill(Infinity);
    for (let i = 0; i < W * H; i++) { px[4 * i] = 29; px[4 * i + 1] = 31; px[4 * i + 2] = 36; px[4 * i + 3] = 255; }
    const s = Math.max(1, Math.round((n < 3000 ? 3 : n < 30000 ? 2 : 1.5) * r)), p = [0, 0, 0];
    for (let i = 0; i < n; i++) {
      p[0] = P[3 * i]; p[1] = P[3 * i + 1]; p[2] = P[3 * i + 2];
      const q = project(p);
      if (q[2] < 0.05) continue;
      const x0 = Math.round(q[0]), y0 = Math.round(q[1]);
      for (let dy = 0; dy < s; dy++) for (let dx = 0; dx < s; dx++) {
        const x = x0 + dx, y = y0 + dy;
        if (x < 0 || y < 0 || x >= W || y >= H || zb[y * W + x] <= q[2]) continue;
        zb[y * W + x] = q[2]; const k = 4 * (y * W + x);
        px[k] = RGB[3 * i]; px[k + 1] = RGB[3 * i + 1]; px[k + 2] = RGB[3 * i + 2];
      }
    }
    ctx.putImageData(img, 0, 0);
    ctx.font = (11 * r) + 'px sans-serif'; ctx.lineJoin = 'round';
    D.cameras.forEach((c, i) => {
      const o = project(c.c), f = c.f.map(project);
      if (o[2] < 0.05 || f.some(q => q[2] < 0.05)) return;
      ctx.strokeStyle = D.colors_by_era[c.era]; ctx.lineWidth = (i === hover || i === pinned ? 3 : 1.3) * r;
      ctx.beginPath();
      f.forEach(q => { ctx.moveTo(o[0], o[1]); ctx.lineTo(q[0], q[1]); });
      ctx.moveTo(f[3][0], f[3][1]); f.forEach(q => ctx.lineTo(q[0], q[1]));
      ctx.stroke();
      if (D.cameras.length <= 40 || i === hover || i === pinned) {
        ctx.fillStyle = '#eee'; ctx.fillText(c.name, o[0] + 5 * r, o[1] - 5 * r);
      }
    });
  }
  function nearest(e) {
    const b = cv.getBoundingClientRect(), mx = (e.clientX - b.left) * r, my = (e.clientY - b.top) * r;
    let best = -1, bd = 14 * r;
    D.cameras.forEach((c, i) => { const q = project(c.c); const d = Math.hypot(q[0] - mx, q[1] - my); if (q[2] > 0.05 && d < bd) { bd = d; best = i; } });
    return best;
  }
  function show(i, e) {
    if (i < 0) { tip.style.display = 'none'; return; }
    const c = D.cameras[i], b = cv.getBoundingClientRect();
    tip.replaceChildren();
    if (c.thumb) { const im = document.createElement('img'); im.src = c.thumb; tip.appendChild(im); }
    tip.appendChild(document.createTextNode(c.name + (c.era !== 'photo' ? ' (' + c.era + ')' : '')));
    tip.style.left = Math.min(e.clientX - b.left + 14, b.width - 180) + 'px'; tip.style.top = (e.clientY - b.top + 14) + 'px';
    tip.style.display = 'block';
  }
  let queued = false;
  function redraw() { if (!queued) { queued = true; requestAnimationFrame(() => { queued = false; draw(); }); } }
  cv.addEventListener('mousedown', e => { drag = {x: e.clientX, y: e.clientY, moved: false, pan: e.shiftKey || e.button !== 0}; e.preventDefault(); });
  cv.addEventListener('contextmenu', e => e.preventDefault());
  window.addEventListener('mouseup', e => {
    if (drag && !drag.moved && e.target === cv) { const i = nearest(e); pinned = i === pinned ? -1 : i; show(pinned, e); redraw(); }
    drag = null;
  });
  window.addEventListener('mousemove', e => {
    if (drag) {
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      if (Math.abs(dx) + Math.abs(dy) > 2) drag.moved = true;
      if (drag.pan) { v.px += dx; v.py += dy; } else { v.yaw -= 0.008 * dx; v.pitch = Math.max(-1.55, Math.min(1.55, v.pitch + 0.008 * dy)); }
      drag.x = e.clientX; drag.y = e.clientY; redraw(); return;
    }
    if (e.target !== cv || pinned >= 0) return;
    const i = nearest(e);
    if (i !== hover) { hover = i; redraw(); }
    show(i, e);
  });
  cv.addEventListener('wheel', e => { const f = Math.exp(-0.0015 * e.deltaY); v.zoom *= f; v.px *= f; v.py *= f; e.preventDefault(); redraw(); }, {passive: false});
  cv.addEventListener('dblclick', () => { v = Object.assign({}, home); redraw(); });
  document.getElementById('model-home').onclick = () => { v = Object.assign({}, home); redraw(); };
  document.getElementById('model-top').onclick = () => { v = Object.assign({}, home, {pitch: 1.55, yaw: 0}); fit(); redraw(); };
  window.addEventListener('resize', () => { setup(); draw(); });
  if (pick) pick.addEventListener('change', () => load(+pick.value));
  let wanted = null; try { wanted = decodeURIComponent(location.hash.replace(/^#photo=/, '')); } catch (err) { /* a malformed link: no photo */ }
  const holds = k => JSON.parse(blocks[k].textContent).cameras.some(c => c.name === wanted);
  const first = location.hash.startsWith('#photo=') && pick ? Math.max(0, blocks.findIndex((b, k) => holds(k))) : 0;
  if (pick) pick.value = String(first);
  load(first);
  const linked = location.hash.startsWith('#photo=') ? D.cameras.findIndex(c => c.name === wanted) : -1;
  if (linked >= 0) {  // report.html#photo=NAME opens with that photo shown, in the model that holds it
    const q = project(D.cameras[linked].c), b = cv.getBoundingClientRect();
    pinned = linked; draw(); show(linked, {clientX: b.left + q[0] / r, clientY: b.top + q[1] / r});
  }
})();
