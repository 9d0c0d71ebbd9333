//! How much memory sled keeps after reading a tree once: the measurement behind
//! `docs/scale-out.md`'s paragraph on the sled node's memory.
//!
//! ```text
//! shapeseek bench populate --data DIR --count 100000
//! cargo run --release --example sled_memory -- DIR/db signatures CACHE_BYTES
//! cargo run --release --example sled_memory -- write NEW_DIR VALUE_BYTES COUNT
//! cargo run --release --example sled_memory -- NEW_DIR t CACHE_BYTES
//! ```
//!
//! The read form opens a sled directory (a server's is `DIR/db`) with `cache_capacity`
//! CACHE_BYTES and reads every value of a tree once, printing the bytes read and the process's
//! resident set (VmRSS, VmHWM) as it goes. The write form fills the tree `t` of a new directory
//! with COUNT values of VALUE_BYTES each, for the read form to read in a process of its own.

fn memory() -> String {
    std::fs::read_to_string("/proc/self/status")
        .unwrap_or_default()
        .lines()
        .filter(|l| l.starts_with("VmHWM") || l.starts_with("VmRSS"))
        .map(|l| l.split_whitespace().collect::<Vec<_>>().join(" "))
        .collect::<Vec<_>>()
        .join(", ")
}

fn open(path: &str, cache: u64) -> sled::Db {
    sled::Config::new()
        .path(path)
        .cache_capacity(cache)
        .open()
        .unwrap_or_else(|e| panic!("opening {path}: {e}"))
}

fn read_all(tree: &sled::Tree) {
    let t = std::time::Instant::now();
    let (mut n, mut bytes) = (0usize, 0usize);
    for kv in tree.iter() {
        let (_, v) = kv.expect("a readable value");
        n += 1;
        bytes += v.len();
        if n % 20_000 == 0 {
            println!("{n} values, {} MB read: {}", bytes >> 20, memory());
        }
    }
    println!(
        "read {n} values, {} MB, in {:.1} s: {}",
        bytes >> 20,
        t.elapsed().as_secs_f64(),
        memory()
    );
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let usage =
        "usage: sled_memory DIR TREE CACHE_BYTES | sled_memory write NEW_DIR VALUE_BYTES COUNT";
    let arg = |i: usize| -> &str {
        a.get(i).map(String::as_str).unwrap_or_else(|| {
            eprintln!("{usage}");
            std::process::exit(2)
        })
    };
    if arg(1) == "write" {
        let path = arg(2);
        let size: usize = arg(3).parse().expect("VALUE_BYTES: a number");
        let count: u64 = arg(4).parse().expect("COUNT: a number");
        assert!(
            !std::path::Path::new(path).exists(),
            "{path} exists: give a new directory"
        );
        let db = open(path, 1 << 30);
        let tree = db.open_tree("t").expect("the tree");
        let mut v: Vec<u8> = (0..size.max(8)).map(|i| (i * 7 % 251) as u8).collect();
        for i in 0..count {
            v[..8].copy_from_slice(&i.to_le_bytes());
            tree.insert(i.to_be_bytes(), v.as_slice()).expect("insert");
        }
        db.flush().expect("flush");
        println!("written {count} values of {size} bytes to {path}");
        return;
    }
    let cache: u64 = arg(3).parse().expect("CACHE_BYTES: a number");
    let db = open(arg(1), cache);
    println!("opened: {}", memory());
    read_all(&db.open_tree(arg(2)).expect("the tree"));
}
