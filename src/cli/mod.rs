//! Subcommands of the `shapeseek` binary whose flags are not the library's.

pub mod eval;
