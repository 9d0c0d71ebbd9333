//! Throwaway engines for the tests that need PostgreSQL or NATS (`tests/postgres.rs`,
//! `tests/cluster.rs`): finding the binaries, free ports, and a private PostgreSQL instance
//! (`initdb` + `pg_ctl` in a directory of the caller's, on a free port on 127.0.0.1, run as the
//! `postgres` user when the tests run as root). Include with
//! `#[path = "common/engines.rs"] mod engines;`.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// Directory of `initdb`/`pg_ctl`: `SHAPESEEK_PG_BIN`, the newest `/usr/lib/postgresql/*/bin`
/// (Debian's layout), or PATH.
pub fn pg_bin_dir() -> Option<PathBuf> {
    if let Ok(d) = std::env::var("SHAPESEEK_PG_BIN") {
        return Some(PathBuf::from(d));
    }
    let mut versions: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let v = e.file_name().to_string_lossy().parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").exists().then_some((v, bin))
        })
        .collect();
    versions.sort();
    if let Some((_, bin)) = versions.pop() {
        return Some(bin);
    }
    std::env::var_os("PATH").and_then(|p| {
        std::env::split_paths(&p).find(|d| d.join("initdb").exists() && d.join("pg_ctl").exists())
    })
}

/// `name` on PATH.
pub fn on_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|p| {
        std::env::split_paths(&p)
            .map(|d| d.join(name))
            .find(|f| f.exists())
    })
}

/// `nats-server`: PATH, or Debian's locations.
pub fn nats_bin() -> Option<PathBuf> {
    on_path("nats-server").or_else(|| {
        ["/usr/sbin/nats-server", "/usr/bin/nats-server"]
            .iter()
            .map(PathBuf::from)
            .find(|p| p.exists())
    })
}

/// True when the tests run as root (initdb refuses root: the instance then runs as `postgres`).
pub fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// `cmd` as a Command, run as `postgres` via runuser when we are root.
pub fn as_pg_user(root: bool, cmd: &Path) -> Command {
    if root {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(cmd);
        c
    } else {
        Command::new(cmd)
    }
}

/// Runs the shell command `then` once this test process is gone, however it ends: a process
/// killed outright (a CI watchdog) runs no `Drop`, so what it started would outlive it. Err
/// says why the watchdog could not start.
pub fn after_exit(then: &str) -> Result<(), String> {
    let script = format!(
        "while kill -0 {pid} 2>/dev/null; do sleep 1; done; {then}",
        pid = std::process::id()
    );
    Command::new("sh")
        .args(["-c", &script])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("watchdog: {e}"))?;
    Ok(())
}

/// A free TCP port on 127.0.0.1.
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port on 127.0.0.1")
}

/// A private PostgreSQL instance. It is not stopped on drop: the owner calls [`PrivatePg::stop`]
/// (or runs [`PrivatePg::stop_shell`] from a watchdog when the instance outlives the test).
pub struct PrivatePg {
    /// Its directory (`data/`, `log`, the socket).
    pub dir: PathBuf,
    bin: PathBuf,
    root: bool,
    /// Its port on 127.0.0.1.
    pub port: u16,
}

impl PrivatePg {
    /// Creates and starts an instance in `dir` (created if missing), listening on 127.0.0.1;
    /// Err says why not.
    pub fn start(bin: &Path, dir: &Path) -> Result<PrivatePg, String> {
        PrivatePg::start_with(bin, dir, &[], &[])
    }

    /// [`PrivatePg::start`] also listening on the addresses `listen` and trusting clients from
    /// the networks `clients` (CIDR; 127.0.0.1 is always trusted).
    pub fn start_with(
        bin: &Path,
        dir: &Path,
        listen: &[&str],
        clients: &[&str],
    ) -> Result<PrivatePg, String> {
        let root = is_root();
        std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        if root {
            let st = Command::new("chown")
                .args(["-R", "postgres:"])
                .arg(dir)
                .status()
                .map_err(|e| format!("chown: {e}"))?;
            if !st.success() {
                return Err("chown of the instance directory to postgres failed".into());
            }
        }
        let data = dir.join("data");
        let out = as_pg_user(root, &bin.join("initdb"))
            .arg("-D")
            .arg(&data)
            .args(["-U", "postgres", "-A", "trust", "-E", "UTF8", "--no-locale"])
            .arg("--no-sync")
            .output()
            .map_err(|e| format!("initdb: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "initdb failed: {}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        if !clients.is_empty() {
            use std::io::Write;
            let hba = data.join("pg_hba.conf");
            let mut f = std::fs::OpenOptions::new()
                .append(true)
                .open(&hba)
                .map_err(|e| format!("{}: {e}", hba.display()))?;
            for c in clients {
                writeln!(f, "host all all {c} trust").map_err(|e| format!("pg_hba: {e}"))?;
            }
        }
        let port = free_port();
        let addresses = std::iter::once("127.0.0.1")
            .chain(listen.iter().copied())
            .collect::<Vec<_>>()
            .join(",");
        let opts = format!(
            "-p {port} -k {} -c listen_addresses={addresses} -c max_connections=200",
            dir.display()
        );
        let out = as_pg_user(root, &bin.join("pg_ctl"))
            .arg("-D")
            .arg(&data)
            .arg("-l")
            .arg(dir.join("log"))
            .args(["-w", "-t", "60", "-o", &opts, "start"])
            .output()
            .map_err(|e| format!("pg_ctl: {e}"))?;
        if !out.status.success() {
            let log = std::fs::read_to_string(dir.join("log")).unwrap_or_default();
            return Err(format!(
                "pg_ctl start failed: {}{log}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        Ok(PrivatePg {
            dir: dir.to_path_buf(),
            bin: bin.to_path_buf(),
            root,
            port,
        })
    }

    /// `postgres://postgres@127.0.0.1:PORT` (no database).
    pub fn base_url(&self) -> String {
        format!("postgres://postgres@127.0.0.1:{}", self.port)
    }

    /// Stops the instance at once (`pg_ctl -m immediate stop`).
    pub fn stop(&self) {
        let _ = as_pg_user(self.root, &self.bin.join("pg_ctl"))
            .arg("-D")
            .arg(self.dir.join("data"))
            .args(["-m", "immediate", "stop"])
            .output();
    }

    /// The shell command that does what [`PrivatePg::stop`] does.
    pub fn stop_shell(&self) -> String {
        let pg_ctl = format!(
            "'{}' -D '{}' -m immediate stop",
            self.bin.join("pg_ctl").display(),
            self.dir.join("data").display()
        );
        if self.root {
            format!("runuser -u postgres -- {pg_ctl}")
        } else {
            pg_ctl
        }
    }
}
