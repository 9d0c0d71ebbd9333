//! The web viewer at `/`: a static page (HTML, CSS, one JavaScript bundle with three.js) built
//! from `web/src` into `web/dist` by `npm run build` in `web/` and committed, then compiled into
//! the binary here with `include_bytes!`, so a plain `cargo build` serves it with no Node.js and
//! nothing fetched at run time. The page talks only to the same-origin API.
//!
//! | path | what |
//! | --- | --- |
//! | `/`, `/index.html` | the page |
//! | `/assets/app.js` | the viewer (it imports `shared.js`) |
//! | `/assets/parse-worker.js` | the worker that reads mesh files (three.js's loaders) |
//! | `/assets/shared.js` | what both import: three.js's core, once |
//! | `/assets/style.css` | the style sheet |
//! | `/assets/icon.svg` | the page's icon |
//! | `/assets/THREE-LICENSE.txt` | three.js's licence |
//!
//! Responses carry a strong `ETag` (content hash) and `Cache-Control: no-cache`, so browsers
//! revalidate cheaply (304) and never keep an old bundle after an upgrade.

use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use sha2::{Digest, Sha256};
use std::sync::OnceLock;

/// One embedded file.
pub struct Asset {
    /// URL path.
    pub path: &'static str,
    /// Content type.
    pub content_type: &'static str,
    /// The bytes.
    pub bytes: &'static [u8],
}

/// Every embedded file of the viewer.
pub const ASSETS: [Asset; 7] = [
    Asset {
        path: "/",
        content_type: "text/html; charset=utf-8",
        bytes: include_bytes!("../../web/dist/index.html"),
    },
    Asset {
        path: "/assets/app.js",
        content_type: "text/javascript; charset=utf-8",
        bytes: include_bytes!("../../web/dist/app.js"),
    },
    Asset {
        path: "/assets/style.css",
        content_type: "text/css; charset=utf-8",
        bytes: include_bytes!("../../web/dist/style.css"),
    },
    Asset {
        path: "/assets/parse-worker.js",
        content_type: "text/javascript; charset=utf-8",
        bytes: include_bytes!("../../web/dist/parse-worker.js"),
    },
    Asset {
        path: "/assets/shared.js",
        content_type: "text/javascript; charset=utf-8",
        bytes: include_bytes!("../../web/dist/shared.js"),
    },
    Asset {
        path: "/assets/icon.svg",
        content_type: "image/svg+xml",
        bytes: include_bytes!("../../web/dist/icon.svg"),
    },
    Asset {
        path: "/assets/THREE-LICENSE.txt",
        content_type: "text/plain; charset=utf-8",
        bytes: include_bytes!("../../web/dist/THREE-LICENSE.txt"),
    },
];

/// Content-Security-Policy of the viewer: everything from this origin; `data:`/`blob:` for the
/// glTF loader's embedded buffers and images.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self'; \
                   img-src 'self' data: blob:; connect-src 'self' data: blob:; \
                   object-src 'none'; base-uri 'none'; frame-ancestors 'none'";

/// Content-Security-Policy of the mesh-reading worker: a worker takes its policy from its own
/// response, not from the page, so without one a glTF naming an image elsewhere made the
/// worker fetch it. It may import scripts from this origin (`shared.js`), compile WebAssembly
/// (`'wasm-unsafe-eval'`: meshoptimizer's decoder of meshopt-compressed glTF is a WebAssembly
/// module embedded in the bundle; this allows no JavaScript `eval`) and read `data:`/`blob:`
/// URLs and this origin, nothing else.
const WORKER_CSP: &str =
    "default-src 'none'; script-src 'self' 'wasm-unsafe-eval'; connect-src 'self' data: blob:";

fn etags() -> &'static [String; ASSETS.len()] {
    static TAGS: OnceLock<[String; ASSETS.len()]> = OnceLock::new();
    TAGS.get_or_init(|| {
        ASSETS.each_ref().map(|a| {
            let h = Sha256::digest(a.bytes);
            format!("\"{}\"", hex::encode(&h[..12]))
        })
    })
}

fn serve(i: usize, headers: &HeaderMap) -> Response {
    let a = &ASSETS[i];
    let etag = &etags()[i];
    let fresh = super::if_none_match(headers, etag);
    let mut resp = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, a.content_type)], a.bytes).into_response()
    };
    let h = resp.headers_mut();
    if let Ok(v) = HeaderValue::from_str(etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    let csp = match a.path {
        "/" => Some(CSP),
        "/assets/parse-worker.js" => Some(WORKER_CSP),
        _ => None,
    };
    if let Some(csp) = csp {
        h.insert(
            header::CONTENT_SECURITY_POLICY,
            HeaderValue::from_static(csp),
        );
    }
    resp
}

/// Whether `path` is one of the viewer's (the node serves them while its index loads too).
pub fn is_page(path: &str) -> bool {
    path == "/index.html" || ASSETS.iter().any(|a| a.path == path)
}

/// The viewer's routes, merged into the API router (any state): every asset at its path, the
/// page at `/index.html` too.
pub fn routes<S: Clone + Send + Sync + 'static>() -> Router<S> {
    let mut r = Router::new().route(
        "/index.html",
        get(|h: HeaderMap| async move { serve(0, &h) }),
    );
    for (i, a) in ASSETS.iter().enumerate() {
        r = r.route(a.path, get(move |h: HeaderMap| async move { serve(i, &h) }));
    }
    r
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The embedded asset at `path`, as text.
    fn text(path: &str) -> &'static str {
        let a = ASSETS.iter().find(|a| a.path == path).expect(path);
        std::str::from_utf8(a.bytes).unwrap()
    }

    #[test]
    fn the_page_references_only_embedded_same_origin_assets() {
        let html = text("/");
        for p in ["/assets/app.js", "/assets/style.css", "/assets/icon.svg"] {
            assert!(html.contains(p), "index.html links {p}");
        }
        // Its own icon: the browser asks for /favicon.ico otherwise, a 404 in the console.
        assert!(text("/assets/icon.svg").starts_with("<svg xmlns=\"http://www.w3.org/2000/svg\""));
        assert!(
            !html.contains("http://") && !html.contains("https://"),
            "no external URL"
        );
        let js = text("/assets/app.js");
        let shared = text("/assets/shared.js");
        assert!(shared.len() > 100_000, "the shared chunk holds three.js");
        let worker = text("/assets/parse-worker.js");
        for (name, code) in [("app.js", js), ("parse-worker.js", worker)] {
            assert!(
                code.contains("./shared.js"),
                "{name} imports the shared chunk"
            );
        }
        assert!(
            !js.contains("import(\"http") && !js.contains("from\"http"),
            "no remote import"
        );
        // The page starts the mesh reader from the worker bundle's path, next to its own.
        assert!(js.contains("parse-worker.js"), "app.js starts the worker");
        assert!(
            worker.contains("binary_little_endian"),
            "the worker bundle holds the loaders (PLY's among them)"
        );
        let lic = text("/assets/THREE-LICENSE.txt");
        assert!(lic.contains("MIT License") && lic.contains("three.js authors"));
    }

    #[test]
    fn etag_revalidation_answers_304() {
        let first = serve(1, &HeaderMap::new());
        assert_eq!(first.status(), StatusCode::OK);
        let tag = first.headers()[header::ETAG].clone();
        let mut h = HeaderMap::new();
        h.insert(header::IF_NONE_MATCH, tag);
        assert_eq!(serve(1, &h).status(), StatusCode::NOT_MODIFIED);
        h.insert(header::IF_NONE_MATCH, HeaderValue::from_static("\"other\""));
        assert_eq!(serve(1, &h).status(), StatusCode::OK);
    }

    #[test]
    fn the_page_and_the_worker_carry_their_own_security_policies() {
        let csp = |i: usize| {
            serve(i, &HeaderMap::new())
                .headers()
                .get(header::CONTENT_SECURITY_POLICY)
                .map(|v| v.to_str().unwrap().to_string())
        };
        assert_eq!(csp(0).as_deref(), Some(CSP));
        assert_eq!(ASSETS[3].path, "/assets/parse-worker.js");
        assert_eq!(csp(3).as_deref(), Some(WORKER_CSP));
        assert_eq!(
            csp(1),
            None,
            "a script takes the policy of the page that loads it"
        );
    }
}
