//! The shape index: a sled store (trees `meta`, `shapes`, `signatures`, `meshes`, `by_hash`),
//! its schema version and migrations runner, and the in-memory scan structure the server ranks
//! with. Signatures and scores come from an [`Engine`] (the retrieval framework).

pub mod engine;
pub mod fw_engine;
pub mod migrate;
pub mod scan;
pub mod store;

pub use engine::Engine;
pub use fw_engine::{default_engine, FwEngine};
pub use migrate::{migrate, MigrateOutcome};
pub use scan::ScanIndex;
pub use store::{Inserted, ShapeRecord, Store, SCHEMA_VERSION};
