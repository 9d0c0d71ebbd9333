"""Small test meshes written in code: subdivided icosahedra and tori as OBJ, PLY, OFF, STL, glTF.

Every mesh is closed and manifold; `variant` perturbs the shape a little (a smooth bump) so
that several distinct shapes of one class exist.
"""

from __future__ import annotations

import base64
import json
import math
import struct

Mesh = tuple[list[tuple[float, float, float]], list[tuple[int, int, int]]]


def icosphere(subdivisions: int = 2, bump: float = 0.0) -> Mesh:
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [
        (-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0),
        (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
        (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1),
    ]
    verts = [_unit(v) for v in verts]
    faces = [
        (0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11),
        (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6), (7, 1, 8),
        (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9),
        (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1),
    ]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a: int, b: int) -> int:
            key = (min(a, b), max(a, b))
            if key not in cache:
                p = tuple((verts[a][i] + verts[b][i]) / 2.0 for i in range(3))
                verts.append(_unit(p))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    if bump:
        verts = [tuple(x * (1.0 + bump * math.exp(-8.0 * ((v[2] - 1.0) ** 2))) for x in v) for v in verts]
    return verts, faces


def torus(major: int = 24, minor: int = 10, r_major: float = 1.0, r_minor: float = 0.35) -> Mesh:
    verts = []
    for i in range(major):
        u = 2.0 * math.pi * i / major
        for j in range(minor):
            v = 2.0 * math.pi * j / minor
            r = r_major + r_minor * math.cos(v)
            verts.append((r * math.cos(u), r * math.sin(u), r_minor * math.sin(v)))
    faces = []
    for i in range(major):
        for j in range(minor):
            a = i * minor + j
            b = ((i + 1) % major) * minor + j
            c = ((i + 1) % major) * minor + (j + 1) % minor
            d = i * minor + (j + 1) % minor
            faces += [(a, b, c), (a, c, d)]
    return verts, faces


def _unit(v):
    n = math.sqrt(sum(x * x for x in v))
    return tuple(x / n for x in v)


def obj(mesh: Mesh) -> bytes:
    v, f = mesh
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    return ("\n".join(lines) + "\n").encode()


def ply(mesh: Mesh) -> bytes:
    v, f = mesh
    head = [
        "ply", "format ascii 1.0", f"element vertex {len(v)}",
        "property float x", "property float y", "property float z",
        f"element face {len(f)}", "property list uchar int vertex_indices", "end_header",
    ]
    body = [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in v] + [f"3 {a} {b} {c}" for a, b, c in f]
    return ("\n".join(head + body) + "\n").encode()


def off(mesh: Mesh) -> bytes:
    v, f = mesh
    lines = ["OFF", f"{len(v)} {len(f)} 0"]
    lines += [f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in v]
    lines += [f"3 {a} {b} {c}" for a, b, c in f]
    return ("\n".join(lines) + "\n").encode()


def stl(mesh: Mesh) -> bytes:
    """Binary STL (80-byte header, count, 50 bytes per triangle)."""
    v, f = mesh
    out = bytearray(b"shapeseek client test".ljust(80, b" "))
    out += struct.pack("<I", len(f))
    for a, b, c in f:
        out += struct.pack("<3f", 0.0, 0.0, 0.0)
        for i in (a, b, c):
            out += struct.pack("<3f", *v[i])
        out += struct.pack("<H", 0)
    return bytes(out)


def gltf(mesh: Mesh) -> bytes:
    """glTF 2.0 JSON with the buffer embedded as a data URI."""
    v, f = mesh
    pos = b"".join(struct.pack("<3f", *p) for p in v)
    idx = b"".join(struct.pack("<3I", *t) for t in f)
    buf = pos + idx
    lo = [min(p[i] for p in v) for i in range(3)]
    hi = [max(p[i] for p in v) for i in range(3)]
    doc = {
        "asset": {"version": "2.0", "generator": "shapeseek client test"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "buffers": [{
            "byteLength": len(buf),
            "uri": "data:application/octet-stream;base64," + base64.b64encode(buf).decode(),
        }],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3", "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5125, "count": 3 * len(f), "type": "SCALAR"},
        ],
    }
    return json.dumps(doc).encode()
