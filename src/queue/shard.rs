//! Shards: which node holds which shape, and the scatter/gather of a search's first stage over
//! NATS request/reply (issue 12, `docs/scale-out.md` §3).
//!
//! | name | what |
//! | --- | --- |
//! | subject `shapeseek.search.<s>`, queue group of the same name | search requests for shard `s` (one replica of the shard answers each) |
//! | reply subject | the coordinator's inbox: one or more [`Reply`] chunks per shard |
//!
//! * **Assignment**: shard `s` of `n` holds the shapes whose id (16 hex digits, a counter) is
//!   `≡ s (mod n)` ([`ShardSpec::holds`]): stable, even, no routing table.
//! * **Request** ([`SearchRequest`] as JSON, then the query's [`Encoded`]): the first stage's
//!   query spec, `k`, the tag filter, an excluded id (search by id without `include_self`) and
//!   the coordinator's calibration (epoch and [`fingerprint`]). A shard whose calibration
//!   differs answers [`Reply::Mismatch`] with its epoch instead of ranking.
//! * **Answer**: the shard's local top-`k` by `(score, id)` with every candidate's id, name
//!   and encoding, so the coordinator runs the exact and reciprocal stages without the corpus
//!   (payloads of GW stages come from the store). Chunks of at most [`MAX_CHUNK_BYTES`]
//!   (NATS' default `max_payload` is 1 MiB; 200 candidates ≈ 0.7 MB); the last says so and
//!   carries how many shapes of the shard passed the filter.
//!
//! The merge is exact: the global top-`k` under `(score, id)` is a subset of the union of the
//! shards' local top-`k`s under the same order, and a single node's scan orders ties by
//! position, which is id order (ids are fixed-width hex, sorted).

use crate::bytes::{put_u16, put_u32, put_u64, ByteReader};
use crate::ranking::QuerySpec;
use crate::search::corpus::Encoded;
use crate::{Error, Result};
use axum::body::Bytes;
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use std::time::{Duration, Instant};

/// Most bytes of candidates in one reply chunk.
pub const MAX_CHUNK_BYTES: usize = 512 << 10;

/// This node's shard: `index` of `count`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardSpec {
    /// Which shard (`0..count`).
    pub index: u32,
    /// How many shards.
    pub count: u32,
}

/// The numeric value of a shape id (16 hex digits); `None` for another form.
pub fn id_number(id: &str) -> Option<u64> {
    u64::from_str_radix(id, 16).ok()
}

impl ShardSpec {
    /// Parses `S/N` (`0 ≤ S < N`).
    pub fn parse(s: &str) -> Result<ShardSpec> {
        let bad = || Error::InvalidArgument(format!("shard {s:?}: expected S/N with 0 <= S < N"));
        let (a, b) = s.trim().split_once('/').ok_or_else(bad)?;
        let index: u32 = a.trim().parse().map_err(|_| bad())?;
        let count: u32 = b.trim().parse().map_err(|_| bad())?;
        if count == 0 || index >= count {
            return Err(bad());
        }
        Ok(ShardSpec { index, count })
    }

    /// The shard of a shape id among `count` (an id that is not hex goes to shard 0).
    pub fn shard_of(id: &str, count: u32) -> u32 {
        id_number(id).map_or(0, |n| (n % u64::from(count)) as u32)
    }

    /// True when this shard holds the shape `id`.
    pub fn holds(&self, id: &str) -> bool {
        Self::shard_of(id, self.count) == self.index
    }
}

impl std::fmt::Display for ShardSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// The subject of shard `s`'s search requests (also its queue group).
pub fn search_subject(s: u32) -> String {
    format!("shapeseek.search.{s}")
}

/// A calibration's identity beyond its epoch: the first 8 bytes of the SHA-256 of its JSON (two
/// nodes could hold different provisional calibrations under one epoch).
pub fn fingerprint(cal: &crate::ranking::Calibration) -> u64 {
    use sha2::{Digest, Sha256};
    let json = serde_json::to_vec(cal).unwrap_or_default();
    let d = Sha256::digest(&json);
    u64::from_le_bytes(d[..8].try_into().expect("8 bytes"))
}

/// The first stage of a search, as sent to every shard.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SearchRequest {
    /// How many shards the coordinator fans out to (a shard of another layout refuses).
    pub shard_count: u32,
    /// The first stage's query spec.
    pub spec: QuerySpec,
    /// Candidates wanted (`max(top_k, largest shortlist)`).
    pub k: usize,
    /// Tags every candidate must have.
    pub tags: Vec<String>,
    /// A shape left out (the query itself).
    pub exclude: Option<String>,
    /// The coordinator's calibration epoch.
    pub epoch: u64,
    /// And its [`fingerprint`].
    pub fingerprint: u64,
    /// Milliseconds the shard has to answer.
    pub budget_ms: u64,
}

/// One candidate of a shard's answer.
#[derive(Debug, Clone, PartialEq)]
pub struct Candidate {
    /// First-stage score.
    pub score: f64,
    /// Shape id.
    pub id: String,
    /// Display name.
    pub name: String,
    /// Its encoding under the request's calibration.
    pub encoded: Encoded,
}

/// One message of a shard's answer.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// Candidates (in the shard's rank order); `last` closes the shard's answer.
    Part {
        /// The shard.
        shard: u32,
        /// Chunk number, from 0.
        seq: u32,
        /// True on the last chunk.
        last: bool,
        /// Shapes of the shard that passed the filter (meaningful on the last chunk).
        matched: u64,
        /// Candidates of this chunk.
        hits: Vec<Candidate>,
    },
    /// The shard ranks under another calibration (its epoch).
    Mismatch {
        /// The shard.
        shard: u32,
        /// Its epoch (0: none yet).
        epoch: u64,
    },
    /// The shard could not answer.
    Failed {
        /// The shard.
        shard: u32,
        /// HTTP status it would have answered.
        status: u16,
        /// Problem code.
        code: String,
        /// What went wrong.
        message: String,
    },
}

// ---------------------------------------------------------------------------------------------
// Wire format (little endian, length-prefixed)
// ---------------------------------------------------------------------------------------------

struct W(Vec<u8>);

impl W {
    fn u8(&mut self, x: u8) {
        self.0.push(x);
    }
    fn u16(&mut self, x: u16) {
        put_u16(&mut self.0, x);
    }
    fn u32(&mut self, x: u32) {
        put_u32(&mut self.0, x);
    }
    fn u64(&mut self, x: u64) {
        put_u64(&mut self.0, x);
    }
    fn len(&mut self, n: usize) {
        self.u32(u32::try_from(n).expect("length fits 32 bits"));
    }
    fn str(&mut self, s: &str) {
        self.len(s.len());
        self.0.extend_from_slice(s.as_bytes());
    }
    fn encoded(&mut self, e: &Encoded) {
        self.len(e.hist.len());
        e.hist.iter().for_each(|&x| self.u16(x));
        self.len(e.shift.len());
        self.0.extend_from_slice(&e.shift);
        self.len(e.groups.len());
        e.groups.iter().for_each(|&x| self.u32(x));
        self.len(e.mass.len());
        e.mass.iter().for_each(|&x| self.u64(x.to_bits()));
        self.len(e.present.len());
        e.present.iter().for_each(|&x| self.u8(x as u8));
        self.len(e.vectors.len());
        for v in &e.vectors {
            self.len(v.len());
            v.iter().for_each(|&x| self.u32(x.to_bits()));
        }
        // The second cut version: a flag, then its encoding (which has none).
        match &e.alt {
            Some(a) => {
                self.u8(1);
                self.encoded(a);
            }
            None => self.u8(0),
        }
    }
}

struct R<'a>(ByteReader<'a>);

fn short() -> Error {
    Error::Queue("shard message: truncated".into())
}

impl<'a> R<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        self.0.take(n).ok_or_else(short)
    }
    fn u8(&mut self) -> Result<u8> {
        self.0.u8().ok_or_else(short)
    }
    fn u16(&mut self) -> Result<u16> {
        self.0.u16().ok_or_else(short)
    }
    fn u32(&mut self) -> Result<u32> {
        self.0.u32().ok_or_else(short)
    }
    fn u64(&mut self) -> Result<u64> {
        self.0.u64().ok_or_else(short)
    }
    /// A length whose items (of `item` bytes at least) fit in what is left.
    fn len(&mut self, item: usize) -> Result<usize> {
        let n = self.u32()? as usize;
        if n.saturating_mul(item) > self.0.remaining() {
            return Err(short());
        }
        Ok(n)
    }
    fn str(&mut self) -> Result<String> {
        let n = self.len(1)?;
        String::from_utf8(self.take(n)?.to_vec())
            .map_err(|e| Error::Queue(format!("shard message: {e}")))
    }
    fn encoded(&mut self) -> Result<Encoded> {
        let n = self.len(2)?;
        let hist = (0..n).map(|_| self.u16()).collect::<Result<_>>()?;
        let n = self.len(1)?;
        let shift = self.take(n)?.to_vec();
        let n = self.len(4)?;
        let groups = (0..n).map(|_| self.u32()).collect::<Result<_>>()?;
        let n = self.len(8)?;
        let mass = (0..n)
            .map(|_| self.u64().map(f64::from_bits))
            .collect::<Result<_>>()?;
        let n = self.len(1)?;
        let present = (0..n)
            .map(|_| self.u8().map(|b| b != 0))
            .collect::<Result<_>>()?;
        let n = self.len(4)?;
        let mut vectors = Vec::with_capacity(n);
        for _ in 0..n {
            let m = self.len(4)?;
            vectors.push(
                (0..m)
                    .map(|_| self.u32().map(f32::from_bits))
                    .collect::<Result<_>>()?,
            );
        }
        let alt = match self.u8()? {
            0 => None,
            1 => {
                let a = self.encoded()?;
                if a.alt.is_some() {
                    return Err(Error::Queue("shard message: nested second version".into()));
                }
                Some(Box::new(a))
            }
            _ => {
                return Err(Error::Queue(
                    "shard message: bad second-version flag".into(),
                ))
            }
        };
        // The vectors' group sums are not sent: they follow from the vectors.
        let mut e = Encoded {
            hist,
            shift,
            groups,
            mass,
            present,
            vectors,
            vgroups: Vec::new(),
            alt,
        };
        e.fill_vector_groups();
        Ok(e)
    }
}

/// A request on the wire: its JSON, then the query's encoding.
pub fn encode_request(req: &SearchRequest, query: &Encoded) -> Vec<u8> {
    let json = serde_json::to_vec(req).expect("a request serialises");
    let mut w = W(Vec::with_capacity(json.len() + 8 * 1024));
    w.len(json.len());
    w.0.extend_from_slice(&json);
    w.encoded(query);
    w.0
}

/// Reads a request.
pub fn decode_request(b: &[u8]) -> Result<(SearchRequest, Encoded)> {
    let mut r = R(ByteReader::new(b));
    let n = r.len(1)?;
    let req: SearchRequest = serde_json::from_slice(r.take(n)?)
        .map_err(|e| Error::Queue(format!("shard request: {e}")))?;
    let q = r.encoded()?;
    Ok((req, q))
}

const PART: u8 = 0;
const MISMATCH: u8 = 1;
const FAILED: u8 = 2;

/// One reply message on the wire.
pub fn encode_reply(rep: &Reply) -> Vec<u8> {
    let mut w = W(Vec::new());
    match rep {
        Reply::Part {
            shard,
            seq,
            last,
            matched,
            hits,
        } => {
            w.u8(PART);
            w.u32(*shard);
            w.u32(*seq);
            w.u8(*last as u8);
            w.u64(*matched);
            w.len(hits.len());
            for h in hits {
                w.u64(h.score.to_bits());
                w.str(&h.id);
                w.str(&h.name);
                w.encoded(&h.encoded);
            }
        }
        Reply::Mismatch { shard, epoch } => {
            w.u8(MISMATCH);
            w.u32(*shard);
            w.u64(*epoch);
        }
        Reply::Failed {
            shard,
            status,
            code,
            message,
        } => {
            w.u8(FAILED);
            w.u32(*shard);
            w.u16(*status);
            w.str(code);
            w.str(message);
        }
    }
    w.0
}

/// Reads one reply message.
pub fn decode_reply(b: &[u8]) -> Result<Reply> {
    let mut r = R(ByteReader::new(b));
    Ok(match r.u8()? {
        PART => {
            let shard = r.u32()?;
            let seq = r.u32()?;
            let last = r.u8()? != 0;
            let matched = r.u64()?;
            let n = r.len(8)?;
            let mut hits = Vec::with_capacity(n);
            for _ in 0..n {
                hits.push(Candidate {
                    score: f64::from_bits(r.u64()?),
                    id: r.str()?,
                    name: r.str()?,
                    encoded: r.encoded()?,
                });
            }
            Reply::Part {
                shard,
                seq,
                last,
                matched,
                hits,
            }
        }
        MISMATCH => Reply::Mismatch {
            shard: r.u32()?,
            epoch: r.u64()?,
        },
        FAILED => Reply::Failed {
            shard: r.u32()?,
            status: r.u16()?,
            code: r.str()?,
            message: r.str()?,
        },
        k => return Err(Error::Queue(format!("shard reply: unknown kind {k}"))),
    })
}

/// About the bytes of `e` on the wire, its second version's included.
fn encoded_size(e: &Encoded) -> usize {
    2 * e.hist.len()
        + 4 * e.groups.len()
        + 9 * e.mass.len()
        + e.present.len()
        + e.vectors.iter().map(|v| 4 * v.len() + 4).sum::<usize>()
        + 1
        + e.alt.as_deref().map_or(0, |a| 24 + encoded_size(a))
}

/// A shard's ranked candidates as reply messages of at most about [`MAX_CHUNK_BYTES`] each
/// (at least one message, the last flagged).
pub fn answer_messages(shard: u32, matched: u64, hits: Vec<Candidate>) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut chunk: Vec<Candidate> = Vec::new();
    let mut bytes = 0usize;
    let size = |c: &Candidate| 40 + c.id.len() + c.name.len() + encoded_size(&c.encoded);
    let n = hits.len();
    for (i, h) in hits.into_iter().enumerate() {
        bytes += size(&h);
        chunk.push(h);
        if bytes >= MAX_CHUNK_BYTES && i + 1 < n {
            out.push(encode_reply(&Reply::Part {
                shard,
                seq: out.len() as u32,
                last: false,
                matched,
                hits: std::mem::take(&mut chunk),
            }));
            bytes = 0;
        }
    }
    out.push(encode_reply(&Reply::Part {
        shard,
        seq: out.len() as u32,
        last: true,
        matched,
        hits: chunk,
    }));
    out
}

/// What one shard answered.
#[derive(Debug, Clone, PartialEq)]
pub enum ShardAnswer {
    /// Its candidates (rank order) and how many of its shapes passed the filter.
    Ranked {
        /// Candidates.
        hits: Vec<Candidate>,
        /// Shapes that passed the filter.
        matched: u64,
    },
    /// It ranks under another calibration epoch.
    Mismatch(u64),
    /// It failed: status, code, message.
    Failed(u16, String, String),
}

/// Why a scatter/gather got no answer from every shard.
#[derive(Debug)]
pub enum ScatterError {
    /// These shards did not answer completely before the deadline.
    Unavailable(Vec<u32>),
    /// NATS failed.
    Nats(String),
}

/// Sends `req` (with `query`) to every shard `0..req.shard_count` and gathers their answers
/// until `deadline`: one inbox, one publish per shard, chunks gathered in order.
pub async fn scatter(
    client: &async_nats::Client,
    req: &SearchRequest,
    query: &Encoded,
    deadline: Instant,
) -> std::result::Result<Vec<ShardAnswer>, ScatterError> {
    let nats = |what: &'static str| move |e: String| ScatterError::Nats(format!("{what}: {e}"));
    let n = req.shard_count as usize;
    let inbox = client.new_inbox();
    let mut sub = client
        .subscribe(inbox.clone())
        .await
        .map_err(|e| nats("subscribing to the reply inbox")(e.to_string()))?;
    let body = Bytes::from(encode_request(req, query));
    for s in 0..req.shard_count {
        client
            .publish_with_reply(search_subject(s), inbox.clone(), body.clone())
            .await
            .map_err(|e| nats("publishing a shard request")(e.to_string()))?;
    }
    client
        .flush()
        .await
        .map_err(|e| nats("flushing shard requests")(e.to_string()))?;
    let mut answers: Vec<Option<ShardAnswer>> = vec![None; n];
    // Chunks so far per shard (a shard answers through one replica, in order).
    let mut partial: Vec<(u32, Vec<Candidate>)> = vec![(0, Vec::new()); n];
    while answers.iter().any(Option::is_none) {
        let left = deadline.saturating_duration_since(Instant::now());
        let msg = match tokio::time::timeout(left, sub.next()).await {
            Ok(Some(m)) => m,
            Ok(None) => return Err(ScatterError::Nats("reply inbox closed".into())),
            Err(_) => break,
        };
        let rep = match decode_reply(&msg.payload) {
            Ok(r) => r,
            Err(e) => {
                tracing::warn!(error = %e, "unreadable shard reply");
                continue;
            }
        };
        match rep {
            Reply::Part {
                shard,
                seq,
                last,
                matched,
                hits,
            } => {
                let s = shard as usize;
                if s >= n || answers[s].is_some() {
                    continue;
                }
                let (next, got) = &mut partial[s];
                if seq != *next {
                    // A lost or reordered chunk: this shard's answer is incomplete.
                    answers[s] = Some(ShardAnswer::Failed(
                        503,
                        "search.shard_unavailable".into(),
                        format!("shard {shard}: chunk {seq} arrived, {next} expected"),
                    ));
                    continue;
                }
                *next += 1;
                got.extend(hits);
                if last {
                    answers[s] = Some(ShardAnswer::Ranked {
                        hits: std::mem::take(got),
                        matched,
                    });
                }
            }
            Reply::Mismatch { shard, epoch } => {
                if let Some(a) = answers.get_mut(shard as usize) {
                    a.get_or_insert(ShardAnswer::Mismatch(epoch));
                }
            }
            Reply::Failed {
                shard,
                status,
                code,
                message,
            } => {
                if let Some(a) = answers.get_mut(shard as usize) {
                    a.get_or_insert(ShardAnswer::Failed(status, code, message));
                }
            }
        }
    }
    let _ = sub.unsubscribe().await;
    let missing: Vec<u32> = (0..req.shard_count)
        .filter(|&s| answers[s as usize].is_none())
        .collect();
    if !missing.is_empty() {
        return Err(ScatterError::Unavailable(missing));
    }
    Ok(answers.into_iter().map(|a| a.expect("answered")).collect())
}

/// Subscribes shard `spec.index`'s responder (queue group: one replica answers a request).
pub async fn subscribe(
    client: &async_nats::Client,
    spec: ShardSpec,
) -> Result<async_nats::Subscriber> {
    let subject = search_subject(spec.index);
    client
        .queue_subscribe(subject.clone(), subject)
        .await
        .map_err(|e| Error::Queue(format!("subscribing to shard requests: {e}")))
}

/// Publishes a shard's reply messages to `reply` and flushes.
pub async fn send_reply(
    client: &async_nats::Client,
    reply: async_nats::Subject,
    messages: Vec<Vec<u8>>,
) -> Result<()> {
    for m in messages {
        client
            .publish(reply.clone(), Bytes::from(m))
            .await
            .map_err(|e| Error::Queue(format!("answering a shard request: {e}")))?;
    }
    client
        .flush()
        .await
        .map_err(|e| Error::Queue(format!("answering a shard request (flush): {e}")))
}

/// How long a coordinator waits for its shards by default.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(5);

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(seed: u16) -> Encoded {
        Encoded {
            hist: vec![seed, 2, 3, u16::MAX],
            shift: vec![1, 8],
            groups: vec![7, u32::MAX],
            mass: vec![0.5, f64::MIN_POSITIVE],
            present: vec![true, false, true],
            vectors: vec![Box::default(), vec![1.0, -2.5, f32::NAN].into()],
            vgroups: Vec::new(),
            alt: None,
        }
    }

    #[test]
    fn shard_assignment_is_the_id_modulo_the_count() {
        let s = ShardSpec::parse("1/3").unwrap();
        assert_eq!(s, ShardSpec { index: 1, count: 3 });
        assert!(s.holds("0000000000000004"));
        assert!(!s.holds("0000000000000005"));
        assert!(ShardSpec::parse("000000000000000a/1").is_err());
        for bad in ["", "1", "2/2", "0/0", "a/b", "-1/2"] {
            assert!(ShardSpec::parse(bad).is_err(), "{bad}");
        }
        assert_eq!(ShardSpec::shard_of("00000000000000ff", 16), 15);
        assert_eq!(s.to_string(), "1/3");
    }

    #[test]
    fn requests_and_replies_round_trip_bit_for_bit() {
        let req = SearchRequest {
            shard_count: 2,
            spec: crate::index::default_engine().default_query(),
            k: 200,
            tags: vec!["a".into()],
            exclude: Some("0000000000000001".into()),
            epoch: 7,
            fingerprint: 99,
            budget_ms: 1000,
        };
        let mut q = enc(1);
        q.alt = Some(Box::new(enc(5))); // a second cut version travels with the query
        let (r2, q2) = decode_request(&encode_request(&req, &q)).unwrap();
        assert_eq!(r2.k, 200);
        assert_eq!(r2.exclude.as_deref(), Some("0000000000000001"));
        assert_eq!(q2.hist, q.hist);
        assert_eq!(q2.vectors[1][2].to_bits(), q.vectors[1][2].to_bits());
        // The vectors' group sums are recomputed on arrival (NaN: a group holding a NaN).
        let vgroups: Vec<u32> = q2.vgroups.iter().map(|x| x.to_bits()).collect();
        let mut sent = q.clone();
        sent.fill_vector_groups();
        assert_eq!(vgroups.len(), 16);
        assert_eq!(&q2.vgroups[8..10], &[1.0, -2.5]);
        assert!(q2.vgroups[10].is_nan());
        assert_eq!(
            vgroups,
            sent.vgroups.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        );
        let alt = q2.alt.as_deref().expect("second version");
        assert_eq!(
            (alt.hist.as_slice(), alt.alt.is_none()),
            (enc(5).hist.as_slice(), true)
        );
        let hits: Vec<Candidate> = (0..400)
            .map(|i| Candidate {
                score: i as f64 * 0.1,
                id: format!("{i:016x}"),
                name: format!("m{i}.obj"),
                encoded: Encoded {
                    hist: vec![i as u16; 1536],
                    // Every other candidate with a second version, as large as its first: the
                    // chunks must count it.
                    alt: (i % 2 == 0).then(|| {
                        Box::new(Encoded {
                            hist: vec![7; 1536],
                            ..enc(i as u16)
                        })
                    }),
                    ..enc(i as u16)
                },
            })
            .collect();
        let msgs = answer_messages(1, 1234, hits.clone());
        assert!(msgs.len() >= 2, "chunked: {}", msgs.len());
        let mut got = Vec::new();
        for (i, m) in msgs.iter().enumerate() {
            assert!(m.len() <= MAX_CHUNK_BYTES + 8192);
            match decode_reply(m).unwrap() {
                Reply::Part {
                    shard,
                    seq,
                    last,
                    matched,
                    hits,
                } => {
                    assert_eq!(
                        (shard, seq, last, matched),
                        (1, i as u32, i + 1 == msgs.len(), 1234)
                    );
                    got.extend(hits);
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(got.len(), hits.len());
        for (a, b) in got.iter().zip(&hits) {
            assert_eq!(a.score.to_bits(), b.score.to_bits());
            assert_eq!(
                (&a.id, &a.name, &a.encoded.hist),
                (&b.id, &b.name, &b.encoded.hist)
            );
        }
        let others = [
            Reply::Mismatch { shard: 3, epoch: 9 },
            Reply::Failed {
                shard: 0,
                status: 503,
                code: "server.busy".into(),
                message: "x".into(),
            },
        ];
        for r in &others {
            assert_eq!(&decode_reply(&encode_reply(r)).unwrap(), r);
        }
        assert!(decode_reply(&[0, 1]).is_err());
        assert!(decode_request(&[255, 255, 255, 255]).is_err());
        // Every cut short message is an error, never a panic nor a shorter message.
        let whole = encode_request(&req, &q);
        for n in 0..whole.len() {
            assert!(decode_request(&whole[..n]).is_err(), "request cut at {n}");
        }
        let one = encode_reply(&Reply::Part {
            shard: 0,
            seq: 0,
            last: true,
            matched: 1,
            hits: hits[..1].to_vec(),
        });
        for whole in std::iter::once(one).chain(others.iter().map(encode_reply)) {
            assert!(decode_reply(&whole).is_ok());
            for n in 0..whole.len() {
                assert!(decode_reply(&whole[..n]).is_err(), "reply cut at {n}");
            }
        }
    }
}
