// Mesh parsing, run in a worker (parse-worker.js) so that a large file never freezes the page:
// a file of any format the loaders read, turned into one welded, normalised triangle mesh
// (positions, normals, indices) ready to draw. Stored shapes come from the server as binary PLY
// (`/v1/shapes/{id}/mesh?format=ply`, the mesh as the server read it), so every format the
// server accepts is drawn; an upload is parsed from its own bytes.
import * as THREE from 'three';
import { OBJLoader } from 'three/addons/loaders/OBJLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { STLLoader } from 'three/addons/loaders/STLLoader.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { mergeVertices } from 'three/addons/utils/BufferGeometryUtils.js';
import { parseOff } from './off.js';


function geometriesOf(object) {
  const out = [];
  object.updateMatrixWorld(true);
  object.traverse((o) => {
    if (o.isMesh && o.geometry && o.geometry.attributes.position) {
      // Positions as f32 before the node's transform: quantized ones (KHR_mesh_quantization,
      // e.g. normalized u16, often interleaved) would be clamped back into their integer range
      // when transformed in place (a quantized figure was drawn as a box).
      const p = o.geometry.attributes.position;
      const f = new Float32Array(p.count * 3);
      for (let i = 0; i < p.count; i++) {
        f[3 * i] = p.getX(i); f[3 * i + 1] = p.getY(i); f[3 * i + 2] = p.getZ(i);
      }
      const g = new THREE.BufferGeometry();
      g.setAttribute('position', new THREE.BufferAttribute(f, 3));
      if (o.geometry.index) g.setIndex(o.geometry.index.clone());
      g.applyMatrix4(o.matrixWorld);
      out.push(g);
    }
  });
  return out;
}

function mergeAll(geoms) {
  // Positions only, non-indexed, then welded: enough to render the surface.
  let n = 0;
  const parts = geoms.map((g) => (g.index ? g.toNonIndexed() : g));
  for (const g of parts) n += g.attributes.position.count;
  const pos = new Float32Array(n * 3);
  let off = 0;
  for (const g of parts) {
    const a = g.attributes.position;
    for (let i = 0; i < a.count; i++) {
      pos[off++] = a.getX(i); pos[off++] = a.getY(i); pos[off++] = a.getZ(i);
    }
  }
  const out = new THREE.BufferGeometry();
  out.setAttribute('position', new THREE.BufferAttribute(pos, 3));
  return out;
}

// Only positions are drawn: a glTF's images, textures and materials are dropped before the
// loader sees them, so a file that names an image elsewhere makes no request for it.
function geometryOnly(bytes, format) {
  const strip = (json) => {
    for (const k of ['images', 'textures', 'samplers', 'materials']) delete json[k];
    for (const m of json.meshes || []) for (const p of m.primitives || []) delete p.material;
    return json;
  };
  if (format === 'gltf') return JSON.stringify(strip(JSON.parse(new TextDecoder().decode(bytes))));
  // GLB: a 12-byte header, the JSON chunk (length, "JSON", text), then the rest, kept as is.
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const JSON_CHUNK = 0x4e4f534a;
  if (bytes.length < 20 || dv.getUint32(16, true) !== JSON_CHUNK) {
    return bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  }
  const jsonLen = dv.getUint32(12, true);
  const json = strip(JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLen))));
  const text = new TextEncoder().encode(JSON.stringify(json));
  const padded = (text.length + 3) & ~3;
  const rest = bytes.subarray(20 + jsonLen);
  const out = new Uint8Array(20 + padded + rest.length);
  const o = new DataView(out.buffer);
  out.set(bytes.subarray(0, 8)); // magic and version
  o.setUint32(8, out.length, true);
  o.setUint32(12, padded, true);
  o.setUint32(16, JSON_CHUNK, true);
  out.set(text, 20);
  out.fill(0x20, 20 + text.length, 20 + padded);
  out.set(rest, 20 + padded);
  return out.buffer;
}

async function parseMesh(bytes, format) {
  const buf = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
  let geoms;
  switch (format) {
    case 'obj':
      geoms = geometriesOf(new OBJLoader().parse(new TextDecoder().decode(bytes)));
      break;
    case 'ply':
      geoms = [new PLYLoader().parse(buf)];
      break;
    case 'stl':
      geoms = [new STLLoader().parse(buf)];
      break;
    case 'off':
      geoms = [parseOff(new TextDecoder().decode(bytes))];
      break;
    case 'gltf':
    case 'glb': {
      // meshopt-compressed buffers (gltfpack -c/-cc), which the server reads too: meshoptimizer's
      // decoder is WebAssembly, which the worker's Content-Security-Policy allows for this.
      const loader = new GLTFLoader().setMeshoptDecoder(MeshoptDecoder);
      const gltf = await loader.parseAsync(geometryOnly(bytes, format), '');
      let scene = gltf.scene;
      if (!scene) {
        // A file without `scenes` is valid glTF: like the server, draw every root node (a node
        // that is no other node's child) with its transforms, as the scene it would have been.
        const json = gltf.parser.json;
        const nodes = json.nodes || [];
        const children = new Set(nodes.flatMap((n) => n.children || []));
        json.scenes = [{ nodes: nodes.map((_, i) => i).filter((i) => !children.has(i)) }];
        scene = await gltf.parser.getDependency('scene', 0);
      }
      geoms = geometriesOf(scene);
      break;
    }
    default:
      throw new Error(`unknown format ${format}`);
  }
  geoms = geoms.filter((g) => g.attributes.position && g.attributes.position.count >= 3);
  if (!geoms.length) throw new Error('no triangles to display');
  let g = mergeAll(geoms);
  g.deleteAttribute('normal');
  g = mergeVertices(g, 1e-6);
  g.computeVertexNormals();
  return g;
}

/** Centres on the area-free vertex mean, optionally rotates to principal axes, scales to the unit sphere. */
function normalizeGeometry(g, align) {
  const p = g.attributes.position;
  const n = p.count;
  const c = new THREE.Vector3();
  for (let i = 0; i < n; i++) c.add(new THREE.Vector3(p.getX(i), p.getY(i), p.getZ(i)));
  c.divideScalar(n);
  g.translate(-c.x, -c.y, -c.z);
  if (align) {
    const cov = [[0, 0, 0], [0, 0, 0], [0, 0, 0]];
    for (let i = 0; i < n; i++) {
      const v = [p.getX(i), p.getY(i), p.getZ(i)];
      for (let a = 0; a < 3; a++) for (let b = 0; b < 3; b++) cov[a][b] += v[a] * v[b];
    }
    const axes = jacobiEigenvectors(cov); // columns sorted by decreasing variance
    // Sign convention: the third moment along each axis is positive (a stable, pose-free choice).
    const m = new THREE.Matrix4();
    const cols = axes.map((ax) => {
      let s3 = 0;
      for (let i = 0; i < n; i++) {
        const d = p.getX(i) * ax[0] + p.getY(i) * ax[1] + p.getZ(i) * ax[2];
        s3 += d * d * d;
      }
      return s3 < 0 ? ax.map((x) => -x) : ax;
    });
    // Right-handed: third = first × second.
    const a0 = new THREE.Vector3(...cols[0]);
    const a1 = new THREE.Vector3(...cols[1]);
    const a2 = new THREE.Vector3().crossVectors(a0, a1);
    // Longest axis along x, second along y (the view looks down -z from +z-ish).
    m.set(a0.x, a0.y, a0.z, 0, a1.x, a1.y, a1.z, 0, a2.x, a2.y, a2.z, 0, 0, 0, 0, 1);
    g.applyMatrix4(m);
  }
  g.computeBoundingSphere();
  const r = g.boundingSphere.radius || 1;
  g.scale(1 / r, 1 / r, 1 / r);
  g.computeVertexNormals();
  return g;
}

function jacobiEigenvectors(a0) {
  const a = a0.map((r) => r.slice());
  const v = [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  for (let sweep = 0; sweep < 50; sweep++) {
    let off = 0;
    for (let p = 0; p < 3; p++) for (let q = p + 1; q < 3; q++) off += a[p][q] * a[p][q];
    if (off < 1e-20) break;
    for (let p = 0; p < 3; p++) {
      for (let q = p + 1; q < 3; q++) {
        if (Math.abs(a[p][q]) < 1e-30) continue;
        const theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
        const t = Math.sign(theta || 1) / (Math.abs(theta) + Math.sqrt(theta * theta + 1));
        const c = 1 / Math.sqrt(t * t + 1);
        const s = t * c;
        for (let k = 0; k < 3; k++) {
          const akp = a[k][p], akq = a[k][q];
          a[k][p] = c * akp - s * akq; a[k][q] = s * akp + c * akq;
        }
        for (let k = 0; k < 3; k++) {
          const apk = a[p][k], aqk = a[q][k];
          a[p][k] = c * apk - s * aqk; a[q][k] = s * apk + c * aqk;
        }
        for (let k = 0; k < 3; k++) {
          const vkp = v[k][p], vkq = v[k][q];
          v[k][p] = c * vkp - s * vkq; v[k][q] = s * vkp + c * vkq;
        }
      }
    }
  }
  const order = [0, 1, 2].sort((i, j) => a[j][j] - a[i][i]);
  return order.map((i) => [v[0][i], v[1][i], v[2][i]]);
}

/** `bytes` of `format` as arrays to draw: welded, centred, optionally aligned, unit sphere. */
export async function meshArrays(bytes, format, align) {
  const g = normalizeGeometry(await parseMesh(bytes, format), align);
  return {
    position: g.attributes.position.array,
    normal: g.attributes.normal.array,
    index: g.index ? g.index.array : null,
  };
}
