// Distance distributions from the signature's quantile sketches, drawn as SVG.
//
// A sketch stores quantiles q[0..Q] of the distance distribution: F(q[j]) = j / Q, linear
// between knots. The density is drawn as a histogram of that piecewise-linear CDF on shared bins.

export function distributionFromSketch(sketch) {
  const q = sketch.quantiles.filter((x) => Number.isFinite(x));
  return { q, mass: sketch.mass };
}

/** The piecewise-linear CDF of a sketch at x. */
export function cdfAt(q, x) {
  const Q = q.length - 1;
  if (Q < 1) return x >= (q[0] ?? 0) ? 1 : 0;
  if (x < q[0]) return 0;
  if (x >= q[Q]) return 1;
  let lo = 0, hi = Q;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (q[mid] <= x) lo = mid; else hi = mid;
  }
  const span = q[hi] - q[lo];
  return (lo + (span > 0 ? (x - q[lo]) / span : 1)) / Q;
}

const esc = (s) => String(s).replace(/[&<>"]/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;' }[c]));

function niceTicks(max, n = 5) {
  const raw = max / n;
  const p = 10 ** Math.floor(Math.log10(raw || 1));
  const step = [1, 2, 2.5, 5, 10].map((m) => m * p).find((s) => s >= raw) || raw;
  const out = [];
  for (let v = 0; v <= max + 1e-12; v += step) out.push(+v.toPrecision(6));
  return out;
}

/** SVG of the distributions; `series`: [{label, color, dist}], opts: {kind: 'density'|'cdf', channel}. */
export function plotDistributions(series, { kind = 'density', channel = '' } = {}) {
  const W = 720, H = 300, L = 56, R = 16, T = 28, B = 42;
  const pw = W - L - R, ph = H - T - B;
  const xmax = Math.max(...series.map((s) => s.dist.q[s.dist.q.length - 1] || 0)) * 1.02 || 1;
  const bins = 60;
  const curves = series.map((s) => {
    const pts = [];
    if (kind === 'cdf') {
      for (let i = 0; i <= 200; i++) {
        const x = (xmax * i) / 200;
        pts.push([x, cdfAt(s.dist.q, x)]);
      }
    } else {
      const w = xmax / bins;
      for (let b = 0; b < bins; b++) {
        const d = (cdfAt(s.dist.q, (b + 1) * w) - cdfAt(s.dist.q, b * w)) / w;
        pts.push([b * w, d], [(b + 1) * w, d]);
      }
    }
    return { ...s, pts };
  });
  const ymax = kind === 'cdf' ? 1 : Math.max(...curves.flatMap((c) => c.pts.map((p) => p[1]))) * 1.08 || 1;
  const sx = (x) => L + (x / xmax) * pw;
  const sy = (y) => T + (1 - y / ymax) * ph;
  let s = `<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 ${W} ${H}" font-family="sans-serif" font-size="12" data-kind="${kind}">`;
  s += `<rect width="${W}" height="${H}" fill="white"/>`;
  for (const v of niceTicks(xmax)) {
    if (v > xmax) continue;
    s += `<line x1="${sx(v)}" y1="${T}" x2="${sx(v)}" y2="${T + ph}" stroke="#eee"/><text x="${sx(v)}" y="${T + ph + 16}" text-anchor="middle">${v}</text>`;
  }
  for (const v of niceTicks(ymax, 4)) {
    if (v > ymax) continue;
    s += `<line x1="${L}" y1="${sy(v)}" x2="${L + pw}" y2="${sy(v)}" stroke="#eee"/><text x="${L - 6}" y="${sy(v) + 4}" text-anchor="end">${v}</text>`;
  }
  s += `<rect x="${L}" y="${T}" width="${pw}" height="${ph}" fill="none" stroke="#555"/>`;
  s += `<text x="${L + pw / 2}" y="${H - 8}" text-anchor="middle">distance (unit-area shapes) — channel ${esc(channel)}</text>`;
  s += `<text x="14" y="${T + ph / 2}" text-anchor="middle" transform="rotate(-90 14 ${T + ph / 2})">${kind === 'cdf' ? 'fraction of pairs ≤ d' : 'density'}</text>`;
  curves.forEach((c, i) => {
    const d = c.pts.map((p, k) => `${k ? 'L' : 'M'}${sx(p[0]).toFixed(1)},${sy(p[1]).toFixed(1)}`).join('');
    s += `<path d="${d}" fill="none" stroke="${c.color}" stroke-width="2" data-series="${i}"/>`;
    s += `<line x1="${L + 10}" y1="${T + 12 + 16 * i}" x2="${L + 30}" y2="${T + 12 + 16 * i}" stroke="${c.color}" stroke-width="3"/>`;
    s += `<text x="${L + 36}" y="${T + 16 + 16 * i}">${esc(c.label)}</text>`;
  });
  return s + '</svg>';
}
