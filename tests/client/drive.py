"""Drives a running shapeseek server through a client generated from its own /openapi.yaml.

    python drive.py --url http://127.0.0.1:PORT --client-dir DIR --spec FILE

DIR holds the package `shapeseek_client` that openapi-python-client generated from FILE (the
document the server served). Every request goes through that generated client; the checks look
at its parsed models (an undeclared field the server sends ends up in a model's
`additional_properties` and fails the check). The last line is `N passed, M failed`; the exit
status is non-zero when a check failed.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import sys
import traceback
from typing import Any, Callable

import meshes

PASSED: list[str] = []
FAILED: list[str] = []


def check(name: str) -> Callable[[Callable[[], None]], Callable[[], None]]:
    """Runs the decorated function at once as one named check."""

    def run(fn: Callable[[], None]) -> Callable[[], None]:
        try:
            fn()
        except Exception as e:  # noqa: BLE001 - every failure is reported, then the run goes on
            FAILED.append(name)
            print(f"FAIL {name}: {type(e).__name__}: {e}")
            traceback.print_exc(limit=3)
        else:
            PASSED.append(name)
            print(f"ok   {name}")
        return fn

    return run


def expect(cond: bool, what: str) -> None:
    if not cond:
        raise AssertionError(what)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--client-dir", required=True)
    ap.add_argument("--spec", required=True)
    args = ap.parse_args()
    sys.path.insert(0, args.client_dir)

    # Everything below talks to the server only through the generated package.
    from shapeseek_client import Client
    from shapeseek_client.api.default import (
        delete_shape,
        get_shape,
        get_shape_mesh,
        get_shape_signature,
        healthz,
        index_info,
        ingest_shape,
        list_shapes,
        openapi,
        readyz,
        search,
    )
    from shapeseek_client.models import (
        Dissimilarity,
        DistributionValues,
        ExactStage,
        Health,
        IndexInfo,
        IngestResult,
        IngestUpload,
        MeshFormat,
        Metadata,
        Problem,
        Readiness,
        ReciprocalStage,
        SearchById,
        SearchOptions,
        SearchResult,
        SearchUpload,
        ShapePage,
        ShapeRecord,
        ShapeSignature,
        SpecOverrides,
        SpectralGwStage,
        VectorValues,
    )
    from shapeseek_client.types import UNSET, File

    client = Client(base_url=args.url, timeout=120.0, raise_on_unexpected_status=True)

    def undeclared(model: Any, path: str = "") -> list[str]:
        """Paths of fields the server sent that the spec does not declare (attrs models keep
        them in `additional_properties`); `ChannelKind` declares its keys that way on purpose."""
        out: list[str] = []
        if isinstance(model, list):
            for i, x in enumerate(model):
                out += undeclared(x, f"{path}[{i}]")
            return out
        if not hasattr(model, "__attrs_attrs__"):
            return out
        extra = getattr(model, "additional_properties", None)
        if extra and type(model).__name__ != "ChannelKind":
            out += [f"{path}.{k}" for k in extra]
        for a in model.__attrs_attrs__:
            if a.name != "additional_properties":
                out += undeclared(getattr(model, a.name), f"{path}.{a.name}")
        return out

    def fully_declared(model: Any) -> None:
        extra = undeclared(model, type(model).__name__)
        expect(not extra, f"undeclared fields: {extra}")

    def problem(resp: Any, status: int, code: str) -> None:
        expect(resp.status_code == status, f"status {resp.status_code}, expected {status}: {resp.content[:300]!r}")
        expect(resp.headers.get("content-type") == "application/problem+json", f"content-type {resp.headers.get('content-type')}")
        p = resp.parsed
        expect(isinstance(p, Problem), f"parsed as {type(p).__name__}, not Problem")
        expect(p.status == status and p.code == code, f"problem {p.status} {p.code}, expected {status} {code}")
        expect(p.type_ == f"urn:shapeseek:problem:{code}" and p.detail, f"problem type/detail {p.type_!r} {p.detail!r}")
        fully_declared(p)

    def raw(data: bytes) -> File:
        return File(payload=io.BytesIO(data))

    # --- the meshes (written in code) ---
    uploads: dict[str, tuple[bytes, MeshFormat]] = {
        "sphere-a": (meshes.obj(meshes.icosphere(2)), MeshFormat.OBJ),
        "sphere-b": (meshes.stl(meshes.icosphere(2, bump=0.15)), MeshFormat.STL),
        "sphere-c": (meshes.off(meshes.icosphere(2, bump=0.3)), MeshFormat.OFF),
        "torus-a": (meshes.ply(meshes.torus(24, 10)), MeshFormat.PLY),
        "torus-b": (meshes.gltf(meshes.torus(28, 10, 1.0, 0.3)), MeshFormat.GLTF),
        "torus-c": (meshes.obj(meshes.torus(20, 12, 1.0, 0.4)), MeshFormat.OBJ),
    }
    ids: dict[str, str] = {}

    @check("healthz and readyz parse into Health / Readiness")
    def _() -> None:
        h = healthz.sync(client=client)
        expect(isinstance(h, Health) and h.status.value == "ok", f"healthz {h!r}")
        r = readyz.sync(client=client)
        expect(isinstance(r, Readiness) and r.status.value == "ready", f"readyz {r!r}")
        fully_declared(h)
        fully_declared(r)

    @check("openapi: the served document is text and is the document the client came from")
    def _() -> None:
        text = openapi.sync(client=client)
        expect(isinstance(text, str), f"openapi returned {type(text).__name__}")
        with open(args.spec, encoding="utf-8") as f:
            expect(text == f.read(), "served document differs from the downloaded one")
        r = openapi.sync_detailed(client=client)
        expect(r.headers.get("content-type") == "application/yaml", f"content-type {r.headers.get('content-type')}")
        r = openapi.sync_detailed(client=client.with_headers({"Accept": "text/plain"}))
        expect(r.headers.get("content-type", "").startswith("text/plain") and r.parsed == text, "text/plain variant")

    @check("index_info parses into IndexInfo with a typed signature_spec")
    def _() -> None:
        info = index_info.sync(client=client)
        expect(isinstance(info, IndexInfo), f"index_info {info!r}")
        fully_declared(info)
        spec = info.signature_spec
        expect(spec.eigenpairs >= 1 and len(spec.signature.channels) >= 1, "signature_spec empty")
        expect(all(len(c.kind.additional_properties) == 1 for c in spec.signature.channels), "channel kind not one key")
        expect(len(info.default_query.channels) >= 1, "default_query without channels")

    for name, (data, fmt) in uploads.items():
        if name == "torus-a":
            continue  # ingested by multipart below

        @check(f"ingest raw {name} ({fmt.value}) -> 201 IngestResult")
        def _(name: str = name, data: bytes = data, fmt: MeshFormat = fmt) -> None:
            tags = "sphere" if name.startswith("sphere") else "torus"
            r = ingest_shape.sync_detailed(client=client, body=raw(data), name=name, tags=f"{tags},client")
            expect(r.status_code == 201, f"status {r.status_code}: {r.content[:300]!r}")
            res = r.parsed
            expect(isinstance(res, IngestResult), f"parsed {type(res).__name__}")
            ids[name] = res.id
            fully_declared(res)
            expect(res.created is True and res.timings is not UNSET, "created/timings")
            expect(res.shape.format_ == fmt, f"format {res.shape.format_}, expected {fmt}")
            expect(res.shape.name == name and res.shape.tags == [tags, "client"], "name/tags")
            expect(res.shape.sha256 == hashlib.sha256(data).hexdigest(), "sha256")
            expect(res.shape.bytes_ == len(data), "bytes")
            expect(r.headers.get("location") == f"/v1/shapes/{res.id}", f"location {r.headers.get('location')}")
            p = res.shape.prepare
            expect(p.vertices_in == p.vertices_out + p.welded_vertices + p.unreferenced_vertices, "prepare vertex balance")

    @check("ingest multipart torus-a (file + metadata) -> 201")
    def _() -> None:
        data, fmt = uploads["torus-a"]
        body = IngestUpload(
            file=File(payload=io.BytesIO(data), file_name="torus-a.ply", mime_type="application/ply"),
            metadata=Metadata(name="torus-a", tags=["torus", "client"]),
        )
        r = ingest_shape.sync_detailed(client=client, body=body)
        expect(r.status_code == 201, f"status {r.status_code}: {r.content[:300]!r}")
        res = r.parsed
        ids["torus-a"] = res.id
        fully_declared(res)
        expect(res.shape.name == "torus-a" and res.shape.tags == ["torus", "client"], "metadata not applied")
        expect(res.shape.format_ == fmt, f"format {res.shape.format_}")

    @check("ingest the same bytes again -> 200, same id, nothing computed")
    def _() -> None:
        data, _ = uploads["sphere-a"]
        r = ingest_shape.sync_detailed(client=client, body=raw(data), name="again")
        expect(r.status_code == 200, f"status {r.status_code}")
        expect(r.parsed.id == ids["sphere-a"] and r.parsed.created is False, "not the existing shape")
        expect(r.parsed.timings is UNSET, "timings sent for an existing shape")
        fully_declared(r.parsed)

    @check("list: pages of 2 cover every shape once, in ingest order; tag filter")
    def _() -> None:
        seen: list[str] = []
        cursor: Any = UNSET
        pages = 0
        while True:
            page = list_shapes.sync(client=client, limit=2, cursor=cursor)
            expect(isinstance(page, ShapePage), f"parsed {type(page).__name__}")
            fully_declared(page)
            expect(len(page.items) <= 2, "page larger than limit")
            seen += [s.id for s in page.items]
            pages += 1
            if page.next_cursor is None:
                break
            cursor = page.next_cursor
            expect(pages < 50, "paging does not end")
        expect(sorted(seen) == sorted(ids.values()) and len(seen) == len(set(seen)), f"listed {seen}, stored {ids}")
        expect(pages == (len(ids) + 1) // 2, f"{pages} pages for {len(ids)} shapes")
        expect(seen == sorted(seen), "not in ingest (id) order")
        tori = list_shapes.sync(client=client, tag="torus", limit=100)
        expect({s.id for s in tori.items} == {ids[n] for n in ids if n.startswith("torus")}, "tag filter")

    @check("get_shape returns the ShapeRecord")
    def _() -> None:
        rec = get_shape.sync(ids["torus-b"], client=client)
        expect(isinstance(rec, ShapeRecord), f"parsed {type(rec).__name__}")
        fully_declared(rec)
        expect(rec.id == ids["torus-b"] and rec.format_ == MeshFormat.GLTF, "record")
        expect(rec.content_type == "model/gltf+json", f"content_type {rec.content_type}")

    for name, (data, fmt) in uploads.items():

        @check(f"get_shape_mesh {name} ({fmt.value}) is the upload byte for byte")
        def _(name: str = name, data: bytes = data) -> None:
            r = get_shape_mesh.sync_detailed(ids[name], client=client)
            expect(r.status_code == 200, f"status {r.status_code}")
            expect(r.headers.get("content-type") == "application/octet-stream", f"content-type {r.headers.get('content-type')}")
            f = r.parsed
            expect(isinstance(f, File), f"parsed {type(f).__name__}")
            expect(f.payload.read() == data, "bytes differ from the upload")

    @check("get_shape_signature: typed channels (quantile sketches)")
    def _() -> None:
        sig = get_shape_signature.sync(ids["sphere-a"], client=client)
        expect(isinstance(sig, ShapeSignature), f"parsed {type(sig).__name__}")
        fully_declared(sig)
        s = sig.signature
        expect(s.vertices > 0 and s.area > 0 and s.quadrature_points > 0, "signature counts")
        expect(len(s.channels) >= 1, "no channels")
        for c in s.channels:
            expect(isinstance(c.values, (DistributionValues, VectorValues)), f"channel {c.name}: {type(c.values).__name__}")
            if isinstance(c.values, DistributionValues):
                q = c.values.distribution.quantiles
                expect(len(q) >= 2 and q == sorted(q), f"channel {c.name}: quantiles not monotone")

    def by_id(body: SearchById) -> SearchResult:
        r = search.sync_detailed(client=client, body=body)
        expect(r.status_code == 200, f"status {r.status_code}: {r.content[:300]!r}")
        expect(isinstance(r.parsed, SearchResult), f"parsed {type(r.parsed).__name__}")
        fully_declared(r.parsed)
        return r.parsed

    def same_class(q: str, res: SearchResult, n: int) -> None:
        kind = q.split("-")[0]
        names = [h.name for h in res.hits]
        expect(all(nm.startswith(kind) for nm in names[:n]), f"best {n} hits of {q}: {names}")

    @check("search by id, default stages (scan + reciprocal)")
    def _() -> None:
        res = by_id(SearchById(id=ids["sphere-a"], top_k=3))
        expect(res.stages == ["scan", "reciprocal"], f"stages {res.stages}")
        expect(len(res.hits) == 3 and ids["sphere-a"] not in [h.id for h in res.hits], "self excluded, 3 hits")
        expect([h.rank for h in res.hits] == [1, 2, 3], "ranks")
        expect(all(len(h.stage_scores) == 2 for h in res.hits), "stage_scores per stage")

    @check("search by id, scan alone (rerank: []) with include_self ranks the query first")
    def _() -> None:
        res = by_id(SearchById(id=ids["torus-a"], top_k=5, rerank=[], include_self=True))
        expect(res.stages == ["scan"], f"stages {res.stages}")
        expect(res.hits[0].id == ids["torus-a"], f"first hit {res.hits[0].name}")
        scores = [h.score for h in res.hits]
        expect(scores == sorted(scores), f"scores not ascending: {scores}")
        same_class("torus-a", res, 3)

    @check("search by id, exact stage with spec overrides")
    def _() -> None:
        st = ExactStage(shortlist=5, spec=SpecOverrides(dissimilarity=Dissimilarity.L1))
        expect(st.to_dict() == {"stage": "exact", "shortlist": 5, "spec": {"dissimilarity": "l1"}}, f"{st.to_dict()}")
        res = by_id(SearchById(id=ids["sphere-b"], top_k=4, rerank=[st]))
        expect(res.stages == ["scan", "exact"], f"stages {res.stages}")
        same_class("sphere-b", res, 2)

    @check("search by id, reciprocal stage without repeating its tag")
    def _() -> None:
        st = ReciprocalStage(shortlist=5, neighbourhoods=[1, 2])
        expect(st.to_dict()["stage"] == "reciprocal", f"{st.to_dict()}")
        expect(ReciprocalStage().to_dict() == {"stage": "reciprocal"}, "server defaults copied into the client")
        res = by_id(SearchById(id=ids["torus-c"], top_k=4, rerank=[st]))
        expect(res.stages == ["scan", "reciprocal"], f"stages {res.stages}")
        expect(len(res.hits) == 4, f"{len(res.hits)} hits")

    @check("search by id, spectral_gw stage")
    def _() -> None:
        res = by_id(SearchById(id=ids["torus-b"], top_k=3, rerank=[SpectralGwStage(shortlist=3)]))
        expect(res.stages == ["scan", "spectral_gw"], f"stages {res.stages}")
        expect(all(h.score is not None for h in res.hits), "GW scores")

    @check("search by upload (multipart file + query): the stored copy is the best hit")
    def _() -> None:
        data, _ = uploads["sphere-c"]
        body = SearchUpload(
            file=File(payload=io.BytesIO(data), file_name="q.off"),
            query=SearchOptions(top_k=3, rerank=[SpectralGwStage(shortlist=3)], tags=["client"]),
        )
        r = search.sync_detailed(client=client, body=body)
        expect(r.status_code == 200, f"status {r.status_code}: {r.content[:300]!r}")
        res = r.parsed
        fully_declared(res)
        expect(res.stages == ["scan", "spectral_gw"], f"stages {res.stages}")
        expect(res.timings.analysis is not UNSET, "no analysis timings for an upload")
        expect(res.hits[0].id == ids["sphere-c"], f"best hit {res.hits[0].name}")

    @check("search by upload (raw body, ?top_k=2): default stages")
    def _() -> None:
        data, _ = uploads["torus-c"]
        r = search.sync_detailed(client=client, body=raw(data), top_k=2)
        expect(r.status_code == 200, f"status {r.status_code}: {r.content[:300]!r}")
        res = r.parsed
        fully_declared(res)
        expect(len(res.hits) == 2 and res.stages == ["scan", "reciprocal"], f"{len(res.hits)} hits, {res.stages}")
        same_class("torus-c", res, 2)

    missing = "ffffffffffffffff"

    @check("errors: unknown id -> 404 Problem (get, mesh, signature, search, delete)")
    def _() -> None:
        problem(get_shape.sync_detailed(missing, client=client), 404, "shape.not_found")
        problem(get_shape_mesh.sync_detailed(missing, client=client), 404, "shape.not_found")
        problem(get_shape_signature.sync_detailed(missing, client=client), 404, "shape.not_found")
        problem(delete_shape.sync_detailed(missing, client=client), 404, "shape.not_found")
        problem(search.sync_detailed(client=client, body=SearchById(id=missing)), 404, "shape.not_found")

    @check("errors: bad stages -> 400 Problem")
    def _() -> None:
        for st in (
            SpectralGwStage(shortlist=500),
            ReciprocalStage(expansion=0),
            ExactStage(spec=SpecOverrides(channels=["no-such-channel"])),
        ):
            problem(search.sync_detailed(client=client, body=SearchById(id=ids["sphere-a"], rerank=[st])), 400, "request.invalid")

    @check("errors: bad meshes -> 415 / 422 Problem")
    def _() -> None:
        problem(ingest_shape.sync_detailed(client=client, body=raw(b"\x00\x01\x02 not a mesh")), 415, "mesh.format")
        problem(ingest_shape.sync_detailed(client=client, body=raw(b"v 0 0 0\nv 1 0 0\nf 1 2 9\n")), 422, "mesh.parse")
        problem(ingest_shape.sync_detailed(client=client, body=raw(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n")), 422, "mesh.empty")
        problem(search.sync_detailed(client=client, body=raw(b"ply\nformat ascii 1.0\nelement vertex x\n")), 422, "mesh.parse")

    @check("errors: bad list limit -> 400 Problem")
    def _() -> None:
        problem(list_shapes.sync_detailed(client=client, limit=0), 400, "request.invalid")

    @check("delete -> 204, then 404 and gone from the listing")
    def _() -> None:
        r = delete_shape.sync_detailed(ids["sphere-b"], client=client)
        expect(r.status_code == 204, f"status {r.status_code}")
        problem(get_shape.sync_detailed(ids["sphere-b"], client=client), 404, "shape.not_found")
        listed = {s.id for s in list_shapes.sync(client=client, limit=100).items}
        expect(ids["sphere-b"] not in listed and len(listed) == len(ids) - 1, f"listing after delete: {listed}")

    print(f"{len(PASSED)} passed, {len(FAILED)} failed")
    if FAILED:
        print("failed: " + json.dumps(FAILED))
    return 1 if FAILED else 0


if __name__ == "__main__":
    sys.exit(main())
