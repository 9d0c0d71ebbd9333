// The format of a mesh file, found as the server finds it (src/mesh/read/mod.rs, `sniff`):
// the content first (GLB magic, a `ply` line, an OFF header, `solid` … `facet`, a JSON object
// with "asset", a binary STL of exactly 84 + 50·n bytes, OBJ statements), then the extension.
// A file the server reads is then read here too, whatever its name says.
const OFF_HEADERS = ['OFF', 'COFF', 'NOFF', 'CNOFF', 'NCOFF'];
// ASCII whitespace, as Rust's `split_ascii_whitespace` (not a no-break space).
const ASCII_SPACE = /[ \t\n\f\r]+/;

export function formatOf(name, bytes) {
  let start = 0;
  if (bytes[0] === 0xef && bytes[1] === 0xbb && bytes[2] === 0xbf && !binaryStlSize(bytes)) start = 3;
  const b = bytes.subarray(start);
  const head = new TextDecoder('utf-8', { fatal: false }).decode(b.subarray(0, 4096));
  if (head.startsWith('glTF')) return 'glb';
  if (head.startsWith('ply\n') || head.startsWith('ply\r\n')) return 'ply';
  const firstToken = head
    .split(/\r?\n/)
    .map((l) => l.split('#')[0].trim())
    .find((l) => l.length > 0);
  if (firstToken && OFF_HEADERS.includes(firstToken.split(ASCII_SPACE)[0])) return 'off';
  const trimmed = head.trimStart();
  if (trimmed.slice(0, 5).toLowerCase() === 'solid' && head.includes('facet')) return 'stl';
  if (trimmed.startsWith('{') && new TextDecoder().decode(b).includes('"asset"')) return 'gltf';
  if (binaryStlSize(b)) return 'stl';
  if (looksLikeObj(head)) return 'obj';
  const ext = (name.split('.').pop() || '').toLowerCase();
  if (ext === 'stla' || ext === 'stlb') return 'stl';
  return ['obj', 'gltf', 'glb', 'ply', 'off', 'stl'].includes(ext) ? ext : 'obj';
}

// The first statement that is not blank or a comment is an OBJ keyword with something after it.
const OBJ_KEYWORDS = ['v', 'vt', 'vn', 'vp', 'f', 'o', 'g', 's', 'l', 'p', 'mtllib', 'usemtl'];
function looksLikeObj(head) {
  for (const line of head.split(/\r?\n/)) {
    const t = line.trim();
    if (!t || t.startsWith('#')) continue;
    const kw = t.split(ASCII_SPACE)[0];
    return OBJ_KEYWORDS.includes(kw) && t.length > kw.length;
  }
  return false;
}

function binaryStlSize(b) {
  if (b.length < 84) return false;
  const n = new DataView(b.buffer, b.byteOffset + 80, 4).getUint32(0, true);
  return b.length === 84 + 50 * n;
}
