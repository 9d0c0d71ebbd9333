// A small OFF reader: OFF, COFF, NOFF, CNOFF, NCOFF, STOFF headers (counts on the header line
// or the next), one vertex per line (extra columns ignored), one polygon per line (a trailing face colour
// ignored), polygons fan-triangulated, `#` comments.
import { BufferGeometry, Float32BufferAttribute } from 'three';

export function parseOff(text) {
  const lines = [];
  for (const line of text.split(/\r?\n/)) {
    const body = line.split('#')[0].trim();
    if (body) lines.push(body.split(/\s+/));
  }
  let li = 0;
  const head = lines[li++] || [];
  if (!/^(ST)?(C|N|CN|NC)?4?OFF$/.test(head[0] || '')) throw new Error('OFF: missing OFF header');
  const counts = head.length >= 3 ? head.slice(1) : lines[li++] || [];
  const nv = parseInt(counts[0], 10);
  const nf = parseInt(counts[1], 10);
  if (!(nv >= 0 && nf >= 0)) throw new Error('OFF: bad vertex/face counts');
  if (li + nv + nf > lines.length) throw new Error(`OFF: expected ${nv} vertices and ${nf} faces`);
  const pos = new Float32Array(nv * 3);
  for (let v = 0; v < nv; v++) {
    const t = lines[li++];
    for (let k = 0; k < 3; k++) pos[v * 3 + k] = parseFloat(t[k]);
  }
  const index = [];
  for (let f = 0; f < nf; f++) {
    const t = lines[li++];
    const n = parseInt(t[0], 10);
    if (!(n >= 3) || t.length < n + 1) throw new Error(`OFF: face ${f} is malformed`);
    const vs = t.slice(1, n + 1).map((x) => parseInt(x, 10));
    if (vs.some((x) => !(x >= 0 && x < nv))) throw new Error(`OFF: face ${f} indexes a missing vertex`);
    for (let k = 1; k + 1 < n; k++) index.push(vs[0], vs[k], vs[k + 1]);
  }
  const g = new BufferGeometry();
  g.setAttribute('position', new Float32BufferAttribute(pos, 3));
  g.setIndex(index);
  return g;
}
