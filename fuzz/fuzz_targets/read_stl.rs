//! Coverage-guided fuzzing of the STL reader (and of preparation on whatever it reads): any
//! input must give a mesh or a typed error, never a panic, a hang or an unbounded allocation.
#![no_main]

use libfuzzer_sys::fuzz_target;
use shapeseek::mesh::prepare::{prepare, PrepareOptions};
use shapeseek::mesh::read::{read_mesh, Format, ReadLimits};

fuzz_target!(|data: &[u8]| {
    let limits = ReadLimits {
        max_bytes: 1 << 20,
        max_vertices: 100_000,
        max_faces: 200_000,
        ..ReadLimits::default()
    };
    if let Ok(mesh) = read_mesh(data, Some(Format::Stl), &limits) {
        let _ = prepare(&mesh, &PrepareOptions::default());
    }
});
