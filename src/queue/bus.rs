//! NATS: the JetStream work queue of ingest jobs and the core-NATS change feed.
//!
//! | name | what |
//! | --- | --- |
//! | stream `SHAPESEEK_INGEST`, subject `shapeseek.ingest` | work-queue retention, file storage, duplicate window 2 min; a message is a job id |
//! | consumer `workers` | durable pull consumer, explicit ack, `ack_wait`, `max_deliver` |
//! | subject `shapeseek.changes` | core NATS (no storage): [`Change`] as JSON, announced after each commit |

use crate::{Error, Result};
use async_nats::jetstream::{self, consumer::pull, stream};
use axum::body::Bytes;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Stream of ingest jobs.
pub const STREAM: &str = "SHAPESEEK_INGEST";
/// Subject of ingest jobs.
pub const JOBS_SUBJECT: &str = "shapeseek.ingest";
/// Durable consumer the workers share.
pub const CONSUMER: &str = "workers";
/// Subject of the change feed.
pub const CHANGES_SUBJECT: &str = "shapeseek.changes";

/// Work-queue settings (shared by the nodes that create the stream and consumer: the first
/// creates them, later ones use them as they are).
#[derive(Debug, Clone)]
pub struct QueueOptions {
    /// How long a delivered job may go without an ack (or an "in progress") before JetStream
    /// redelivers it.
    pub ack_wait: Duration,
    /// Deliveries of one job before it becomes a dead letter.
    pub max_deliver: i64,
}

impl Default for QueueOptions {
    fn default() -> Self {
        QueueOptions {
            ack_wait: Duration::from_secs(30),
            max_deliver: 5,
        }
    }
}

/// One committed change, announced on [`CHANGES_SUBJECT`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "lowercase")]
pub enum Change {
    /// A shape was stored.
    Insert {
        /// Its id.
        id: String,
    },
    /// A shape was deleted.
    Delete {
        /// Its id.
        id: String,
    },
    /// A calibration epoch was committed.
    Calibration {
        /// The epoch.
        epoch: u64,
    },
}

/// A connection to NATS with the work queue set up.
#[derive(Clone)]
pub struct Bus {
    client: async_nats::Client,
    js: jetstream::Context,
    opts: QueueOptions,
}

fn queue_err(what: &str) -> impl Fn(String) -> Error + '_ {
    move |e| Error::Queue(format!("{what}: {e}"))
}

impl Bus {
    /// Connects to `url` (`nats://HOST:PORT`) and creates the stream and the consumer when
    /// they do not exist yet.
    pub async fn connect(url: &str, opts: QueueOptions) -> Result<Bus> {
        let client = async_nats::ConnectOptions::new()
            .connection_timeout(Duration::from_secs(5))
            .connect(url)
            .await
            .map_err(|e| queue_err("connecting to NATS")(e.to_string()))?;
        let js = jetstream::new(client.clone());
        let bus = Bus { client, js, opts };
        bus.stream().await?;
        Ok(bus)
    }

    async fn stream(&self) -> Result<stream::Stream> {
        self.js
            .get_or_create_stream(stream::Config {
                name: STREAM.into(),
                subjects: vec![JOBS_SUBJECT.into()],
                retention: stream::RetentionPolicy::WorkQueue,
                storage: stream::StorageType::File,
                duplicate_window: Duration::from_secs(120),
                ..Default::default()
            })
            .await
            .map_err(|e| queue_err("creating the job stream")(e.to_string()))
    }

    /// The NATS connection (shard requests and replies, [`super::shard`]).
    pub fn client(&self) -> &async_nats::Client {
        &self.client
    }

    /// The settings this bus was opened with.
    pub fn options(&self) -> &QueueOptions {
        &self.opts
    }

    /// Publishes a job (its id) and waits for JetStream's ack (it is then stored in the
    /// stream). `dedupe` is the `Nats-Msg-Id`: a second publish with the same one within the
    /// duplicate window is dropped by the server.
    pub async fn publish_job(&self, id: &str, dedupe: &str) -> Result<()> {
        let msg = jetstream::message::PublishMessage::build()
            .payload(Bytes::copy_from_slice(id.as_bytes()))
            .message_id(dedupe);
        self.js
            .send_publish(JOBS_SUBJECT, msg)
            .await
            .map_err(|e| queue_err("publishing a job")(e.to_string()))?
            .await
            .map_err(|e| queue_err("publishing a job (ack)")(e.to_string()))?;
        Ok(())
    }

    /// The workers' durable pull consumer (explicit ack), created when missing.
    pub async fn worker_consumer(&self) -> Result<jetstream::consumer::Consumer<pull::Config>> {
        self.stream()
            .await?
            .get_or_create_consumer(
                CONSUMER,
                pull::Config {
                    durable_name: Some(CONSUMER.into()),
                    ack_policy: jetstream::consumer::AckPolicy::Explicit,
                    ack_wait: self.opts.ack_wait,
                    max_deliver: self.opts.max_deliver,
                    ..Default::default()
                },
            )
            .await
            .map_err(|e| queue_err("creating the worker consumer")(e.to_string()))
    }

    /// The next job of `consumer`, waiting up to `wait` for one (`None`: none came).
    ///
    /// One pull request per job, each on its own reply subscription, instead of the client's
    /// continuous `messages()` stream. With one message per pull, that stream sent no new pull
    /// request for 34.8 s between some jobs while jobs were queued (measured in the cluster's
    /// overhead runs: 30 jobs took 40 s instead of 5). 34.8 s is its pull request's 30 s expiry
    /// plus the 5 s safety timer after which it asks again when it believes a request is still
    /// owed messages; why it believed so was not pinned down.
    pub async fn next_job(
        consumer: &jetstream::consumer::Consumer<pull::Config>,
        wait: Duration,
    ) -> Result<Option<jetstream::Message>> {
        let mut batch = consumer
            .batch()
            .max_messages(1)
            .expires(wait)
            .messages()
            .await
            .map_err(|e| queue_err("pulling a job")(e.to_string()))?;
        match batch.next().await {
            Some(Ok(m)) => Ok(Some(m)),
            Some(Err(e)) => Err(queue_err("pulling a job")(e.to_string())),
            None => Ok(None),
        }
    }

    /// Announces a committed change (core NATS, flushed).
    pub async fn announce(&self, change: &Change) -> Result<()> {
        let body = serde_json::to_vec(change).map_err(|e| Error::Queue(e.to_string()))?;
        self.client
            .publish(CHANGES_SUBJECT, body.into())
            .await
            .map_err(|e| queue_err("announcing a change")(e.to_string()))?;
        self.client
            .flush()
            .await
            .map_err(|e| queue_err("announcing a change (flush)")(e.to_string()))
    }

    /// Subscribes to the change feed.
    pub async fn changes(&self) -> Result<async_nats::Subscriber> {
        self.client
            .subscribe(CHANGES_SUBJECT)
            .await
            .map_err(|e| queue_err("subscribing to changes")(e.to_string()))
    }
}
