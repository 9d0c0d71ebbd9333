#!/usr/bin/env python3
"""Issue 11, findings 4 and 5, from outside the process: uploads that cannot be a shape, and
files whose declared counts and lengths disagree with their data, must be refused (4xx with a
problem+json code), never stored.

    python3 scripts/degenerate-probe.py http://127.0.0.1:PORT

Prints one line per case (status, code, seconds) and exits 1 when any case is stored (2xx) or
answered with a 5xx, when the 20 000-gon takes more than 2 s, or when one of the two controls
(the same sphere, consistent) is not stored. Every input is generated here.
"""
import base64
import json
import math
import struct
import sys
import time
import urllib.error
import urllib.request


def uv_sphere(rings=20, segments=40):
    v = [(0.0, 0.0, 1.0)]
    for i in range(1, rings):
        th = math.pi * i / rings
        for j in range(segments):
            ph = 2 * math.pi * j / segments
            v.append((math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)))
    v.append((0.0, 0.0, -1.0))
    f = []
    ring = lambda i, j: 1 + (i - 1) * segments + j % segments
    for j in range(segments):
        f.append((0, ring(1, j), ring(1, j + 1)))
    for i in range(1, rings - 1):
        for j in range(segments):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            f += [(a, c, b), (b, c, d)]
    s = len(v) - 1
    for j in range(segments):
        f.append((s, ring(rings - 1, j + 1), ring(rings - 1, j)))
    return v, f


def obj(v, f):
    out = [f"v {x} {y} {z}" for x, y, z in v]
    out += ["f " + " ".join(str(i + 1) for i in face) for face in f]
    return ("\n".join(out) + "\n").encode()


def stl(v, f, declared=None):
    b = bytearray(80) + struct.pack("<I", len(f) if declared is None else declared)
    for a, c, d in f:
        b += struct.pack("<3f", 0, 0, 0)
        for i in (a, c, d):
            b += struct.pack("<3f", *v[i])
        b += b"\0\0"
    return bytes(b)


def gltf(v, f, version="2.0", short=0, extra_index=False):
    idx = [i for face in f for i in face] + ([0] if extra_index else [])
    pos = b"".join(struct.pack("<3f", *p) for p in v)
    ind = b"".join(struct.pack("<I", i) for i in idx)
    data = pos + ind
    lo = [min(p[k] for p in v) for k in range(3)]
    hi = [max(p[k] for p in v) for k in range(3)]
    doc = {
        "asset": {"version": version},
        "buffers": [{"byteLength": len(data) - short,
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(data).decode()}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(ind)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
                       "min": lo, "max": hi},
                      {"bufferView": 1, "componentType": 5125, "count": len(idx), "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0,
    }
    return json.dumps(doc).encode()


def cases():
    tri_v, tri_f = [(0, 0, 0), (1, 0, 0), (0, 1, 0)], [(0, 1, 2)]
    scat_v, scat_f = [], []
    for k in range(600):
        x, y = (k % 30) * 3.0, (k // 30) * 3.0
        scat_v += [(x, y, 0), (x + 1, y, 0), (x, y + 1, 0)]
        scat_f.append((3 * k, 3 * k + 1, 3 * k + 2))
    ply = (b"ply\nformat ascii 1.0\ncomment " + b"x" * (4 << 20)
           + b"\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
             b"element face 1\nproperty list uchar int vertex_indices\nend_header\n"
             b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    n = 20000
    gon_v = [(math.cos(2 * math.pi * k / n), math.sin(2 * math.pi * k / n), 0.0) for k in range(n)]
    sv, sf = uv_sphere()
    return [
        ("4: one triangle (OBJ)", "model/obj", obj(tri_v, tri_f)),
        ("4: 600 disconnected triangles (OBJ)", "model/obj", obj(scat_v, scat_f)),
        ("4: 500 identical triangles (STL)", "model/stl", stl(tri_v, tri_f * 500)),
        ("4: 4 MB comment + one triangle (PLY)", "application/octet-stream", ply),
        ("4: one 20 000-gon (OBJ)", "model/obj", obj(gon_v, [tuple(range(n))])),
        ("5: STL declaring one triangle less than it holds", "model/stl",
         stl(sv, sf, declared=len(sf) - 1)),
        ("5: glTF buffer byteLength shorter than its data", "model/gltf+json", gltf(sv, sf, short=12)),
        ("5: glTF index count not a multiple of 3", "model/gltf+json", gltf(sv, sf, extra_index=True)),
        ('5: glTF asset.version "1.0"', "model/gltf+json", gltf(sv, sf, version="1.0")),
        # Controls: the same sphere, consistent, must be stored (the generators are sound).
        ("control: the sphere as STL", "model/stl", stl(sv, sf)),
        ("control: the sphere as glTF", "model/gltf+json", gltf(sv, sf)),
    ]


def main():
    url = sys.argv[1].rstrip("/") + "/v1/shapes"
    bad = 0
    for name, ctype, body in cases():
        req = urllib.request.Request(url, data=body, method="POST", headers={"Content-Type": ctype})
        t = time.monotonic()
        try:
            with urllib.request.urlopen(req, timeout=300) as r:
                status, text = r.status, r.read()
        except urllib.error.HTTPError as e:
            status, text = e.code, e.read()
        dt = time.monotonic() - t
        try:
            code = json.loads(text).get("code", "")
        except ValueError:
            code = ""
        slow = "20 000-gon" in name and dt > 2.0
        if name.startswith("control"):
            ok = 200 <= status < 300
        else:
            ok = 400 <= status < 500 and not slow
        bad += not ok
        print(f"{'ok  ' if ok else 'FAIL'} {status} {code or '-':28s} {dt:6.2f} s  {name}")
    print(f"degenerate-probe: {bad} case(s) not refused as they should be")
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
