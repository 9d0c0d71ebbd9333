"""The review's overload scenario against a release `shapeseek serve` (loopback only).

Usage: shapeseek bench meshes --out DIR/meshes --count 48 --size 2000
       python3 scripts/overload-probe.py PATH/TO/shapeseek DIR

Starts the server (SHAPESEEK_EIGENPAIRS=60) on DIR/idx, ingests DIR/meshes, measures 200
sequential scan-only searches idle, then sends 12 concurrent searches with a spectral-GW stage
of shortlist 200 while a scan-only probe runs back to back; prints statuses, Retry-After and
the probe's p50/p99/max. DIR/idx is left for the caller to remove.
"""
import json, os, subprocess, sys, threading, time, urllib.request, re
binp, d = sys.argv[1], sys.argv[2]
log = open(d + "/log", "w")
env = dict(os.environ, SHAPESEEK_EIGENPAIRS="60")
p = subprocess.Popen([binp, "serve", "--data", d + "/idx", "--addr", "127.0.0.1:0", "--log-format", "json"], stdout=log, stderr=log, env=env)
addr = None
for _ in range(300):
    m = re.search(r'"addr":"([^"]+)"', open(d + "/log").read())
    if m: addr = m.group(1); break
    time.sleep(0.1)
U = "http://" + addr
time.sleep(0.5)
def req(path, body=None, ctype="application/json"):
    r = urllib.request.Request(U + path, data=body, headers={"Content-Type": ctype})
    try:
        with urllib.request.urlopen(r, timeout=300) as f: return f.status, f.read(), dict(f.headers)
    except urllib.error.HTTPError as e: return e.code, e.read(), dict(e.headers)
ids = []
for f in sorted(os.listdir(d + "/meshes")):
    s, b, _ = req("/v1/shapes", open(d + "/meshes/" + f, "rb").read(), "model/off")
    ids.append(json.loads(b)["id"])
time.sleep(2)
def probe(n):
    out = []
    for i in range(n):
        t = time.monotonic(); s, b, _ = req("/v1/search", json.dumps({"id": ids[i % 48], "rerank": []}).encode()); out.append(((time.monotonic() - t) * 1e3, s))
    return out
idle = sorted(x[0] for x in probe(200))
print("idle scan-only: p50 %.1f ms p99 %.1f ms" % (idle[100], idle[197]))
res = []
def gw(i):
    t = time.monotonic(); s, b, h = req("/v1/search", json.dumps({"id": ids[i], "rerank": [{"stage": "spectral_gw", "shortlist": 200}]}).encode())
    res.append((s, time.monotonic() - t, h.get("Retry-After")))
t0 = time.monotonic()
ths = [threading.Thread(target=gw, args=(i,)) for i in range(12)]
[t.start() for t in ths]
time.sleep(0.3)
loaded = []
while any(t.is_alive() for t in ths):
    loaded += probe(1)
[t.join() for t in ths]
ls = sorted(x[0] for x in loaded)
print("12 GW: statuses", sorted(r[0] for r in res), "wall max %.1f s" % max(r[1] for r in res), "retry-after", set(r[2] for r in res))
print("scan-only during: n=%d p50 %.1f ms p99 %.1f ms max %.1f ms" % (len(ls), ls[len(ls)//2], ls[int(0.99*len(ls))-1 if len(ls)>1 else 0], ls[-1]))
p.terminate(); p.wait()
