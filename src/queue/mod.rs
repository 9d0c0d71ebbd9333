//! Work distribution and change propagation for a set of stateless nodes (issue 12):
//! PostgreSQL holds the jobs ([`jobs`]), NATS JetStream carries them ([`bus`]).
//!
//! # An upload's way through the queue
//!
//! 1. A serving node (`shapeseek serve --store postgres://… --queue nats://…`) hashes the upload.
//!    Stored already: answered at once (200). Otherwise the upload goes into the `jobs` table in
//!    one committed row ([`jobs::JobStore::enqueue`]; twin uploads share one job by SHA-256),
//!    then the job's id is published to the work-queue stream `SHAPESEEK_INGEST` with
//!    `Nats-Msg-Id` = the id, so a republish within the duplicate window is dropped by the
//!    server.
//! 2. A worker (`shapeseek worker`) pulls with explicit ack from the durable consumer
//!    `workers` (`ack_wait`, `max_deliver`), claims the job (counting the attempt), analyses
//!    the upload, inserts the shape under the job's id with [`crate::storage::ShapeStore::insert`]
//!    (idempotent by content hash), marks the job done, announces the change, and only then
//!    acks. While it analyses it sends "in progress" acks, so `ack_wait` bounds how long a dead
//!    worker's job waits for redelivery, not how long an analysis may take.
//! 3. A worker that dies never acks: JetStream redelivers after `ack_wait`. A redelivered job
//!    whose shape is stored is completed without analysis. An input that is refused for what it
//!    is (an unreadable mesh, a limit, degenerate geometry: a 4xx answer) is a dead letter at
//!    once: the job is marked failed with the status, code and message, and acked. Any other
//!    failure is retried (`nak` with a delay) until `max_deliver` deliveries, then recorded as a
//!    dead letter too. Workers also republish jobs left pending much longer than `ack_wait` (a
//!    serving node that died between the commit and the publish), so no committed job is lost.
//! 4. Every committed insert, delete and calibration is announced on the core subject
//!    `shapeseek.changes` ([`bus::Change`]); serving nodes apply it to their in-memory scan from
//!    the store (the message carries no data: the store is the truth), and a node that starts
//!    or misses messages reconciles its scan against the store (`src/server/replica.rs`).
//! 5. With shards (`serve --shard S/N`), a node holds only its part of the corpus and a search
//!    fans out over NATS request/reply ([`shard`]).

pub mod bus;
pub mod jobs;
pub mod shard;

pub use bus::{Bus, Change, QueueOptions};
pub use jobs::{DeadLetter, Job, JobInput, JobState, JobStore};

/// True for a `nats://` URL.
pub fn is_nats_url(target: &str) -> bool {
    target.starts_with("nats://")
}
