//! An in-process `shapeseek serve` on a free port of 127.0.0.1 and a response-head parser, for
//! the HTTP tests (`tests/server.rs`, `tests/reliability.rs`). Include with
//! `#[path = "common/in_process.rs"] mod in_process;`.

use shapeseek::server::{start, Running, ServerConfig};
use std::net::SocketAddr;
use std::path::Path;

/// Eigenpairs of the test servers: enough for the default's ShapeDNA channel (50 + 1), few
/// enough to keep the tests' analyses quick.
pub const EIGENPAIRS: usize = 60;

/// A running server and the runtime that drives it.
pub struct Server {
    rt: tokio::runtime::Runtime,
    running: Option<Running>,
    /// Where it listens.
    pub addr: SocketAddr,
}

impl Server {
    /// A server over the data directory `data`: [`EIGENPAIRS`] eigenpairs, two workers,
    /// `grace_secs` of shutdown grace, then whatever `tweak` changes.
    pub fn start(data: &Path, grace_secs: f64, tweak: impl FnOnce(&mut ServerConfig)) -> Server {
        let mut cfg = ServerConfig {
            data: data.to_path_buf(),
            addr: "127.0.0.1:0".into(),
            eigenpairs: EIGENPAIRS,
            workers: 2,
            shutdown_grace_secs: grace_secs,
            ..Default::default()
        };
        tweak(&mut cfg);
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let running = rt.block_on(start(cfg)).expect("server starts");
        let addr = running.addr;
        Server {
            rt,
            running: Some(running),
            addr,
        }
    }

    /// Shuts it down cleanly (in-flight requests finish within the grace).
    pub fn stop(mut self) {
        let r = self.running.take().unwrap();
        self.rt.block_on(r.shutdown()).expect("clean shutdown");
    }
}

/// The status and the headers (names in lower case, values trimmed) of an HTTP/1.1 response
/// head, given without its final blank line.
pub fn parse_head(head: &str) -> (u16, Vec<(String, String)>) {
    let mut lines = head.split("\r\n");
    let status: u16 = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status line in {head:?}"));
    let headers = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    (status, headers)
}
