//! The shape index: a sled store (trees `meta`, `shapes`, `signatures`, `meshes`, `by_hash`),
//! its schema version and migrations runner, and the in-memory scan structure the server ranks
//! with ([`ScanIndex`], over a [`crate::search::Corpus`]). What is computed per shape and the
//! default ranking come from the [`Engine`] configuration.

pub mod engine;
pub mod migrate;
pub mod scan;
pub mod store;

pub use engine::{default_engine, Engine};
pub use migrate::{migrate, MigrateOutcome};
pub use scan::ScanIndex;
pub use store::{Inserted, ShapeRecord, Store, SCHEMA_VERSION};
