//! Admission of CPU work with a cost model: every request that costs CPU (ingest, the analysis
//! of an uploaded query, a search with its rerank stages) is admitted here, once, with an
//! estimated cost, and runs only once admitted.
//!
//! **Cost units.** One unit is roughly 10 ms of one core ([`Cost`]): a scan-only search costs
//! 1, a reciprocal stage over a shortlist of S costs S(S+1)/2 first-stage scores (20 000 per
//! unit), a spectral Gromov–Wasserstein stage 4 units per candidate (≈ 40 ms of one core each,
//! see [`crate::search::stage::MAX_GW_SHORTLIST`]; scaled by the outer iterations), the analysis of a mesh 10 units plus one
//! per 32 KiB of upload. The estimate only has to separate cheap from expensive work and order
//! expensive work by size; it is not a promise.
//!
//! **Two lanes, one mechanism.** Work of at most [`CHEAP_MAX_UNITS`] is *cheap*: it runs on
//! blocking threads, at most `workers` at once, `queue_capacity` more waiting. Anything else is
//! *heavy*: at most `heavy_threads` jobs at once, `queue_capacity` more waiting, run on a
//! dedicated rayon pool of `heavy_threads` threads at a lower scheduling priority
//! (`heavy_nice`), so their parallel loops never occupy the threads cheap work needs.
//! `heavy_threads` is `heavy_share` of the workers, and at most `workers − 1` when there are
//! two or more and `heavy_share` < 1, so cheap work always has a core that heavy work cannot
//! take: twelve GW searches over a shortlist of 200 queue behind each other in the heavy lane
//! while a scan-only search still answers in milliseconds. Inside a lane waiters form two
//! first-come-first-served classes (small and large jobs, see [`LARGE_UNITS`]) served
//! alternately; a job runs without queueing only when nothing waits.
//!
//! **Borrowing an idle server's cores.** With `heavy_share` < 1 a 2-core server would run an
//! expensive job on one thread even when nothing else runs. So when `heavy_borrow` is set, the
//! heavy threads are niced (`heavy_nice` > 0, Linux) and there are more workers than heavy
//! threads, a second pool of `workers` threads at the same nice value exists, and a heavy job
//! that starts while no other heavy job runs, no cheap job runs or waits, no format conversion
//! runs ([`Admission::outside_work`]: conversions have their own gate, outside the lanes) and
//! none of them has finished for [`BORROW_QUIET`] is run on it (counted in
//! `shapeseek_heavy_jobs_borrowed_total`). The quiet period keeps a server with a steady
//! stream of cheap searches from borrowing: there a cheap search would often find both cores
//! taken by niced threads. The choice is made once,
//! at start: a cheap job that arrives while such a job runs gets its core back from the
//! scheduler (a niced thread yields to a normal one), not from admission; heavy jobs that
//! start meanwhile use the narrow pool. Background work on the heavy pool
//! ([`Admission::on_heavy_pool`]: recalibration, recomputation) is not a lane job, so a job
//! that borrows while it runs shares the cores with it, all of them niced.
//!
//! **Refusal.** A lane whose queue is full refuses at once with 503 `server.busy` and
//! `Retry-After`; so does the heavy lane when the work already ahead of a job (the units of the
//! running and queued jobs, worked off at [`HEAVY_UNITS_PER_THREAD`] a second per heavy thread)
//! would take longer than the request timeout — the job would only time out in the queue.
//!
//! **Cancellation.** Each admitted job gets a [`Cancel`] token: it trips when the request's
//! deadline passes or when the request future is dropped (the per-request timeout fired, or
//! the client closed the connection and hyper dropped the request). Jobs check it between
//! stages, in the GW stage before each candidate, and in an upload's eigensolves before each
//! block of operator applications (through a [`crate::error::Interrupt`] reading the token);
//! a tripped job stops with
//! 503 `request.timeout` (nobody reads that answer) and is counted in
//! `shapeseek_jobs_cancelled_total`.

use super::problem::ApiError;
use axum::http::StatusCode;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Largest cost of a cheap job, units.
pub const CHEAP_MAX_UNITS: u32 = 8;

/// Units a heavy thread works off per second (1 unit ≈ 10 ms of one core).
pub const HEAVY_UNITS_PER_THREAD: u32 = 100;

/// How long the cheap lane must have been idle before a heavy job may borrow its cores.
pub const BORROW_QUIET: Duration = Duration::from_secs(1);

/// An estimated cost, in units of ≈ 10 ms of one core.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Cost(pub u32);

impl Cost {
    /// A scan over `n` shapes (1 unit per 50 000 shapes, at least 1).
    pub fn scan(n: usize) -> Cost {
        Cost(1 + (n / 50_000) as u32)
    }

    /// An exact re-scoring of `s` candidates.
    pub fn exact(s: usize) -> Cost {
        Cost((s / 50_000) as u32)
    }

    /// A reciprocal-neighbourhood stage over `s` candidates (every pair scored).
    pub fn reciprocal(s: usize) -> Cost {
        let pairs = (s as u64) * (s as u64 + 1) / 2;
        Cost(pairs.div_ceil(20_000).min(u32::MAX as u64) as u32)
    }

    /// A spectral Gromov–Wasserstein stage over `s` candidates with `outer` linearisation
    /// iterations (4 units a candidate at the default 5), three times that with anchored
    /// starts (three solves a candidate; measured 2.1–2.5× the time on dev's payloads, up to
    /// 4.7× on symmetric generated shapes).
    pub fn gw(s: usize, outer: usize, anchored: bool) -> Cost {
        let solves = if anchored { 3 } else { 1 };
        Cost(
            (4 * solves * s * outer.max(1))
                .div_ceil(5)
                .min(u32::MAX as usize) as u32,
        )
    }

    /// Reading and analysing an upload of `bytes` (spectrum, signature, payload).
    pub fn analysis(bytes: usize) -> Cost {
        Cost(10 + (bytes / (32 << 10)).min(u32::MAX as usize / 2) as u32)
    }

    /// The estimated cost of a search over `n` shapes: the scan, then each stage over the
    /// shortlist it actually receives (never more than the index holds).
    pub fn search(n: usize, stages: &[crate::search::Stage]) -> Cost {
        let mut cost = Cost::scan(n);
        let mut avail = n;
        for st in stages {
            let s = st.shortlist().min(avail);
            avail = s;
            cost = cost.plus(match st {
                crate::search::Stage::Exact { .. } => Cost::exact(s),
                crate::search::Stage::Reciprocal(_) => Cost::reciprocal(s),
                crate::search::Stage::SpectralGw(g) => {
                    Cost::gw(s, g.gw.outer_iterations, g.gw.anchored_starts)
                }
            });
        }
        cost
    }

    /// The sum of two costs.
    pub fn plus(self, other: Cost) -> Cost {
        Cost(self.0.saturating_add(other.0))
    }

    /// True for work that runs in the cheap lane.
    pub fn is_cheap(self) -> bool {
        self.0 <= CHEAP_MAX_UNITS
    }
}

/// A job's cancellation token: its deadline, and a flag set when the request is abandoned.
#[derive(Clone, Debug)]
pub struct Cancel {
    flag: Arc<AtomicBool>,
    deadline: Option<Instant>,
    skipped: Arc<AtomicU64>,
}

impl Cancel {
    /// A token that never trips (work outside a request, tests).
    pub fn never() -> Cancel {
        Cancel {
            flag: Arc::new(AtomicBool::new(false)),
            deadline: None,
            skipped: Arc::new(AtomicU64::new(0)),
        }
    }

    /// A token that trips at `deadline` (work outside a request with a time limit of its own:
    /// a queued job's analysis).
    pub fn until(deadline: Instant) -> Cancel {
        Cancel {
            deadline: Some(deadline),
            ..Cancel::never()
        }
    }

    /// Counts one unit of work (a GW candidate) left undone because the job was cancelled.
    pub fn note_skipped(&self) {
        self.skipped.fetch_add(1, Ordering::Relaxed);
        metrics::counter!("shapeseek_work_items_skipped_total").increment(1);
    }

    /// True once the request was abandoned or its deadline passed.
    pub fn is_cancelled(&self) -> bool {
        self.flag.load(Ordering::Relaxed) || self.deadline.is_some_and(|d| Instant::now() >= d)
    }

    /// `Err(request.timeout)` once cancelled.
    pub fn check(&self) -> Result<(), ApiError> {
        if self.is_cancelled() {
            return Err(cancelled_error());
        }
        Ok(())
    }

    fn trip(&self) {
        self.flag.store(true, Ordering::Relaxed);
    }

    /// A token for work a request runs outside the lanes (a conversion of a stored original):
    /// it trips at `deadline`, and when the returned guard is dropped (the request's future with
    /// it) before [`RequestGuard::done`].
    pub fn for_request(deadline: Option<Instant>) -> (Cancel, RequestGuard) {
        let cancel = Cancel {
            deadline,
            ..Cancel::never()
        };
        let guard = RequestGuard(TripOnDrop {
            cancel: cancel.clone(),
            done: false,
        });
        (cancel, guard)
    }
}

/// Trips its [`Cancel`] when dropped before [`RequestGuard::done`] (see [`Cancel::for_request`]).
pub struct RequestGuard(TripOnDrop);

impl RequestGuard {
    /// The work finished: dropping the guard no longer trips the token.
    pub fn done(mut self) {
        self.0.done = true;
    }
}

fn cancelled_error() -> ApiError {
    ApiError::new(
        StatusCode::SERVICE_UNAVAILABLE,
        "request.timeout",
        "the request was abandoned (deadline passed or client gone); its work was stopped",
    )
}

/// Sets the flag of a job whose request future is dropped before the job finished.
struct TripOnDrop {
    cancel: Cancel,
    done: bool,
}

impl Drop for TripOnDrop {
    fn drop(&mut self) {
        if !self.done {
            self.cancel.trip();
        }
    }
}

/// Live counts of one lane.
#[derive(Debug, Default)]
pub struct LaneStats {
    /// Jobs waiting.
    pub queued: AtomicUsize,
    /// Jobs running.
    pub running: AtomicUsize,
    /// Units waiting.
    pub queued_units: AtomicU64,
    /// Units running.
    pub running_units: AtomicU64,
    /// Jobs refused (503 `server.busy`).
    pub refused: AtomicU64,
}

/// Jobs of a lane at or below this cost form its *small* class, the others its *large* class.
pub const LARGE_UNITS: u32 = 100;

/// One lane: at most `jobs` running, waiters in two FIFO classes (small, large) served
/// alternately when both wait, so a stream of large jobs cannot starve small ones (ingests
/// behind GW searches) nor the reverse.
struct Lane {
    name: &'static str,
    jobs: usize,
    queue_capacity: usize,
    state: std::sync::Mutex<LaneState>,
    stats: Arc<LaneStats>,
    /// Per class: jobs and units waiting.
    class_queued: [AtomicUsize; 2],
    class_units: [AtomicU64; 2],
}

#[derive(Default)]
struct LaneState {
    running: usize,
    waiters: [std::collections::VecDeque<tokio::sync::oneshot::Sender<()>>; 2],
    /// The class served first at the next release.
    next: usize,
}

impl Lane {
    fn new(name: &'static str, jobs: usize, queue_capacity: usize) -> Arc<Lane> {
        Arc::new(Lane {
            name,
            jobs: jobs.max(1),
            queue_capacity,
            state: std::sync::Mutex::new(LaneState::default()),
            stats: Arc::new(LaneStats::default()),
            class_queued: Default::default(),
            class_units: Default::default(),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, LaneState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A running slot at once when one is free and nobody waits.
    fn try_run(self: &Arc<Self>) -> Option<RunSlot> {
        let mut st = self.lock();
        let waiting = st.waiters.iter().any(|q| q.iter().any(|w| !w.is_closed()));
        if st.running < self.jobs && !waiting {
            st.running += 1;
            return Some(RunSlot(self.clone()));
        }
        None
    }

    /// Waits in `class` for a running slot (handed over by a finishing job).
    async fn wait_run(self: &Arc<Self>, class: usize) -> RunSlot {
        let (tx, rx) = tokio::sync::oneshot::channel();
        {
            let mut st = self.lock();
            if st.running < self.jobs && st.waiters.iter().all(|q| q.is_empty()) {
                st.running += 1;
                return RunSlot(self.clone());
            }
            // Waiters whose request was dropped leave here (and when they would be served).
            st.waiters[class].retain(|w| !w.is_closed());
            st.waiters[class].push_back(tx);
        }
        // The sender is only dropped after a hand-over (then the slot is ours) or with the
        // lane itself, which outlives its requests.
        let mut waiting = Waiting {
            rx: Some(rx),
            lane: self.clone(),
        };
        if let Some(rx) = waiting.rx.as_mut() {
            let _ = rx.await;
        }
        waiting.rx = None;
        RunSlot(self.clone())
    }

    /// A finished job: its slot goes to the next live waiter, alternating the classes.
    fn release(&self) {
        let mut st = self.lock();
        loop {
            let first = st.next;
            let class = if !st.waiters[first].is_empty() {
                first
            } else if !st.waiters[1 - first].is_empty() {
                1 - first
            } else {
                st.running -= 1;
                return;
            };
            let w = st.waiters[class].pop_front().expect("non-empty");
            if w.send(()).is_ok() {
                st.next = 1 - class;
                return;
            }
        }
    }
}

/// A waiter of a lane; dropped while waiting (its request was abandoned) it gives back a slot
/// that was handed to it in the meantime.
struct Waiting {
    rx: Option<tokio::sync::oneshot::Receiver<()>>,
    lane: Arc<Lane>,
}

impl Drop for Waiting {
    fn drop(&mut self) {
        if let Some(mut rx) = self.rx.take() {
            rx.close();
            if rx.try_recv().is_ok() {
                self.lane.release();
            }
        }
    }
}

/// A running slot of a lane, released on drop.
struct RunSlot(Arc<Lane>);

impl Drop for RunSlot {
    fn drop(&mut self) {
        self.0.release();
    }
}

/// The admission of CPU work (see the module documentation).
pub struct Admission {
    cheap: Arc<Lane>,
    heavy: Arc<Lane>,
    heavy_pool: Arc<rayon::ThreadPool>,
    /// `workers` niced threads for a heavy job that starts on an otherwise idle server.
    wide_pool: Option<Arc<rayon::ThreadPool>>,
    heavy_threads: usize,
    borrow_quiet: Duration,
    /// When the last cheap job (or work outside the lanes) finished: milliseconds since
    /// `epoch` + 1 (0: none yet).
    last_cheap_done: Arc<AtomicU64>,
    /// Work outside the lanes running now ([`Admission::outside_work`]).
    outside_running: Arc<AtomicUsize>,
    epoch: Instant,
    retry_after: u64,
    request_timeout: Duration,
    /// Heavy jobs run on the wide pool.
    pub borrowed: Arc<AtomicU64>,
    /// Jobs stopped by their cancellation token.
    pub cancelled: Arc<AtomicU64>,
    /// Work items (GW candidates) skipped by cancelled jobs.
    pub skipped: Arc<AtomicU64>,
}

/// What [`Admission::new`] is told.
#[derive(Debug, Clone)]
pub struct AdmissionConfig {
    /// Cheap jobs at once (and the worker count heavy threads are a share of).
    pub workers: usize,
    /// Share of the workers heavy work may use, (0, 1].
    pub heavy_share: f64,
    /// Jobs waiting per lane.
    pub queue_capacity: usize,
    /// Nice value of the heavy threads (Linux; 0 = same priority as the rest).
    pub heavy_nice: i32,
    /// Run a heavy job that starts on an otherwise idle server on `workers` threads (see the
    /// module documentation).
    pub heavy_borrow: bool,
    /// How long the cheap lane must have been idle before a heavy job borrows
    /// ([`BORROW_QUIET`] in the server).
    pub borrow_quiet: Duration,
    /// `Retry-After` seconds of a refusal.
    pub retry_after: u64,
    /// The per-request time limit.
    pub request_timeout: Duration,
}

impl Admission {
    /// Builds the lanes and the heavy pool.
    pub fn new(c: &AdmissionConfig) -> crate::Result<Admission> {
        let workers = c.workers.max(1);
        let mut heavy_threads = ((workers as f64 * c.heavy_share).floor() as usize).max(1);
        if workers >= 2 && c.heavy_share < 1.0 {
            heavy_threads = heavy_threads.min(workers - 1);
        }
        let nice = c.heavy_nice;
        let pool = |threads: usize, name: &'static str| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(move |i| format!("shapeseek-{name}-{i}"))
                .start_handler(move |_| lower_priority(nice))
                .build()
                .map(Arc::new)
                .map_err(|e| crate::Error::Io(std::io::Error::other(e.to_string())))
        };
        let niced = cfg!(target_os = "linux") && nice > 0;
        let wide_pool = if c.heavy_borrow && niced && workers > heavy_threads {
            Some(pool(workers, "wide")?)
        } else {
            None
        };
        Ok(Admission {
            cheap: Lane::new("cheap", workers, c.queue_capacity),
            heavy: Lane::new("heavy", heavy_threads, c.queue_capacity),
            heavy_pool: pool(heavy_threads, "heavy")?,
            wide_pool,
            heavy_threads,
            borrow_quiet: c.borrow_quiet,
            last_cheap_done: Arc::new(AtomicU64::new(0)),
            outside_running: Arc::new(AtomicUsize::new(0)),
            epoch: Instant::now(),
            borrowed: Arc::new(AtomicU64::new(0)),
            retry_after: c.retry_after,
            request_timeout: c.request_timeout,
            cancelled: Arc::new(AtomicU64::new(0)),
            skipped: Arc::new(AtomicU64::new(0)),
        })
    }

    /// Threads of the heavy pool.
    pub fn heavy_threads(&self) -> usize {
        self.heavy_threads
    }

    /// Threads a heavy job that starts on an otherwise idle server runs on.
    pub fn borrow_threads(&self) -> usize {
        self.wide_pool
            .as_ref()
            .map_or(self.heavy_threads, |p| p.current_num_threads())
    }

    /// Counts CPU work that runs outside the lanes (format conversions, which have a gate of
    /// their own) until the guard is dropped: a heavy job does not borrow the cheap lane's
    /// cores while such work runs or within `borrow_quiet` after it ended, as for a cheap job.
    /// It holds no lane slot, so the lanes' wait estimates do not count it.
    pub fn outside_work(&self) -> OutsideWork {
        self.outside_running.fetch_add(1, Ordering::Relaxed);
        OutsideWork {
            running: self.outside_running.clone(),
            done: self.last_cheap_done.clone(),
            epoch: self.epoch,
        }
    }

    /// The pool of a heavy job that has just been counted as running: the wide pool when it
    /// exists, no other heavy job runs, no cheap job runs or waits, no work outside the lanes
    /// runs, and none of them finished within `borrow_quiet`; else the heavy pool.
    fn heavy_pool_for_new_job(&self) -> Arc<rayon::ThreadPool> {
        if let Some(wide) = &self.wide_pool {
            let (cheap, heavy) = (&self.cheap.stats, &self.heavy.stats);
            // The counts first, then the time of the last end: a job marks its end before it
            // stops counting (a `Release` decrement), so a count read as 0 (`Acquire`) comes
            // with that job's mark.
            let idle = heavy.running.load(Ordering::Acquire) == 1
                && cheap.running.load(Ordering::Acquire) == 0
                && cheap.queued.load(Ordering::Acquire) == 0
                && self.outside_running.load(Ordering::Acquire) == 0;
            let last = self.last_cheap_done.load(Ordering::Relaxed);
            let quiet = last == 0
                || mark_since(self.epoch).saturating_sub(last)
                    >= self.borrow_quiet.as_millis() as u64;
            if idle && quiet {
                self.borrowed.fetch_add(1, Ordering::Relaxed);
                metrics::counter!("shapeseek_heavy_jobs_borrowed_total").increment(1);
                return wide.clone();
            }
        }
        self.heavy_pool.clone()
    }

    /// Counts of the cheap and heavy lanes.
    pub fn stats(&self) -> (&LaneStats, &LaneStats) {
        (&self.cheap.stats, &self.heavy.stats)
    }

    /// Runs `f` on the heavy pool from the calling (blocking) thread: background work such as
    /// recalibration, which no request waits for, shares the heavy lane's threads.
    pub fn on_heavy_pool<T: Send>(&self, f: impl FnOnce() -> T + Send) -> T {
        self.heavy_pool.install(f)
    }

    /// How long a job of `class` would wait: the running work, the work of its class already
    /// waiting, and as many jobs of the other class (at their mean cost) as are served
    /// alternately before it; worked off at [`HEAVY_UNITS_PER_THREAD`] a second per job slot.
    fn wait_estimate(&self, lane: &Lane, class: usize) -> Duration {
        let st = &lane.stats;
        let mine = lane.class_queued[class].load(Ordering::Relaxed) as u64;
        let other_n = lane.class_queued[1 - class].load(Ordering::Relaxed) as u64;
        let other_u = lane.class_units[1 - class].load(Ordering::Relaxed);
        let interleaved = other_u
            .checked_div(other_n)
            .map_or(0, |mean| mean * other_n.min(mine + 1));
        let ahead = st.running_units.load(Ordering::Relaxed)
            + lane.class_units[class].load(Ordering::Relaxed)
            + interleaved;
        Duration::from_secs_f64(ahead as f64 / (lane.jobs as f64 * HEAVY_UNITS_PER_THREAD as f64))
    }

    fn busy(&self, lane: &Lane, why: &str) -> ApiError {
        lane.stats.refused.fetch_add(1, Ordering::Relaxed);
        metrics::counter!("shapeseek_jobs_refused_total", "lane" => lane.name).increment(1);
        let mut e = ApiError::busy(self.retry_after);
        e.detail = format!("{why}; retry later");
        e
    }

    /// Admits a job of `cost` whose request must answer by `deadline`, runs it once admitted
    /// (cheap: on a blocking thread; heavy: on the heavy pool) and returns its result. 503
    /// `server.busy` at once when its lane cannot take it. The job receives its [`Cancel`]
    /// token; dropping the returned future while the job waits removes it from the queue, and
    /// while it runs trips the token.
    pub async fn run<T, F>(
        &self,
        cost: Cost,
        deadline: Option<Instant>,
        job: F,
    ) -> Result<T, ApiError>
    where
        T: Send + 'static,
        F: FnOnce(&Cancel) -> Result<T, ApiError> + Send + 'static,
    {
        let heavy = !cost.is_cheap();
        let lane = if heavy { &self.heavy } else { &self.cheap };
        let units = cost.0 as u64;
        let st = lane.stats.clone();
        let class = usize::from(cost.0 > LARGE_UNITS);
        let run = match lane.try_run() {
            Some(run) => run,
            None => {
                if st.queued.load(Ordering::Relaxed) >= lane.queue_capacity {
                    return Err(self.busy(lane, "the work queue is full"));
                }
                if heavy {
                    let drain = self.wait_estimate(lane, class);
                    if drain > self.request_timeout {
                        return Err(self.busy(
                            lane,
                            &format!(
                                "the expensive work ahead needs about {:.0} s",
                                drain.as_secs_f64()
                            ),
                        ));
                    }
                }
                st.queued.fetch_add(1, Ordering::Relaxed);
                st.queued_units.fetch_add(units, Ordering::Relaxed);
                lane.class_queued[class].fetch_add(1, Ordering::Relaxed);
                lane.class_units[class].fetch_add(units, Ordering::Relaxed);
                let queued = Counted {
                    stats: st.clone(),
                    units,
                    running: false,
                    class: Some((lane.clone(), class)),
                };
                let run = lane.wait_run(class).await;
                drop(queued);
                run
            }
        };
        let running = Counted {
            stats: st.clone(),
            units,
            running: true,
            class: None,
        };
        st.running.fetch_add(1, Ordering::Relaxed);
        st.running_units.fetch_add(units, Ordering::Relaxed);
        let cancel = Cancel {
            flag: Arc::new(AtomicBool::new(false)),
            deadline,
            skipped: self.skipped.clone(),
        };
        let cancelled = self.cancelled.clone();
        let mut guard = TripOnDrop {
            cancel: cancel.clone(),
            done: false,
        };
        let pool = heavy.then(|| self.heavy_pool_for_new_job());
        // A cheap job marks when it finished (before it stops counting as running).
        let cheap_done = (!heavy).then(|| (self.last_cheap_done.clone(), self.epoch));
        let handle = tokio::task::spawn_blocking(move || {
            let out = match pool {
                Some(p) => p.install(|| job(&cancel)),
                None => job(&cancel),
            };
            if cancel.is_cancelled() && out.is_err() {
                cancelled.fetch_add(1, Ordering::Relaxed);
                metrics::counter!("shapeseek_jobs_cancelled_total").increment(1);
            }
            if let Some((mark, epoch)) = cheap_done {
                mark.store(mark_since(epoch), Ordering::Relaxed);
            }
            drop(running);
            drop(run);
            out
        });
        let out = handle
            .await
            .map_err(|e| ApiError::internal(format!("job failed: {e}")))?;
        guard.done = true;
        out
    }
}

/// Work outside the lanes, counted while it lives ([`Admission::outside_work`]).
#[must_use = "the work is counted only while the guard lives"]
pub struct OutsideWork {
    running: Arc<AtomicUsize>,
    done: Arc<AtomicU64>,
    epoch: Instant,
}

impl Drop for OutsideWork {
    fn drop(&mut self) {
        // Marked before it stops counting, as a cheap job's end is.
        self.done.store(mark_since(self.epoch), Ordering::Relaxed);
        self.running.fetch_sub(1, Ordering::Release);
    }
}

/// Milliseconds since `epoch`, + 1 (so that 0 can mean "never").
fn mark_since(epoch: Instant) -> u64 {
    epoch.elapsed().as_millis() as u64 + 1
}

/// Decrements a lane's counts when a job leaves the queue or finishes.
struct Counted {
    stats: Arc<LaneStats>,
    units: u64,
    running: bool,
    class: Option<(Arc<Lane>, usize)>,
}

impl Drop for Counted {
    fn drop(&mut self) {
        if let Some((lane, c)) = &self.class {
            lane.class_queued[*c].fetch_sub(1, Ordering::Relaxed);
            lane.class_units[*c].fetch_sub(self.units, Ordering::Relaxed);
        }
        let (n, u) = if self.running {
            (&self.stats.running, &self.stats.running_units)
        } else {
            (&self.stats.queued, &self.stats.queued_units)
        };
        // Release: a cheap job's end mark, stored before, is seen by whoever reads this count
        // (`heavy_pool_for_new_job`).
        n.fetch_sub(1, Ordering::Release);
        u.fetch_sub(self.units, Ordering::Relaxed);
    }
}

/// Lowers the calling thread's scheduling priority by `nice` (Linux: per thread).
fn lower_priority(nice: i32) {
    #[cfg(target_os = "linux")]
    if nice > 0 {
        // SAFETY: plain system calls on the calling thread's own id.
        unsafe {
            let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
            let _ = libc::setpriority(libc::PRIO_PROCESS, tid, nice.min(19));
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = nice;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn adm(workers: usize, queue: usize) -> Admission {
        Admission::new(&AdmissionConfig {
            workers,
            heavy_share: 0.5,
            queue_capacity: queue,
            heavy_nice: 0,
            heavy_borrow: false,
            borrow_quiet: BORROW_QUIET,
            retry_after: 3,
            request_timeout: Duration::from_secs(60),
        })
        .unwrap()
    }

    #[test]
    fn costs_separate_scans_from_gw() {
        assert!(Cost::scan(48).is_cheap());
        assert!(Cost::scan(48).plus(Cost::reciprocal(200)).is_cheap());
        assert!(!Cost::scan(48).plus(Cost::gw(20, 5, false)).is_cheap());
        assert!(!Cost::analysis(1000).is_cheap());
        assert_eq!(Cost::gw(200, 5, false), Cost(800));
        assert_eq!(Cost::gw(200, 5, true), Cost(2400));
        assert!(Cost::reciprocal(1000).0 > CHEAP_MAX_UNITS);
    }

    #[test]
    fn heavy_threads_leave_a_core_to_cheap_work() {
        assert_eq!(adm(1, 1).heavy_threads(), 1);
        assert_eq!(adm(2, 1).heavy_threads(), 1);
        assert_eq!(adm(8, 1).heavy_threads(), 4);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_full_lane_refuses_with_retry_after_and_cheap_work_passes_heavy_work() {
        let a = Arc::new(adm(2, 1));
        let (tx, rx) = std::sync::mpsc::channel::<()>();
        let rx = Arc::new(std::sync::Mutex::new(rx));
        // One heavy job runs (blocked), one waits, the third is refused.
        let mut running = Vec::new();
        for _ in 0..2 {
            let a = a.clone();
            let rx = rx.clone();
            running.push(tokio::spawn(async move {
                a.run(Cost(50), None, move |_| {
                    let _ = rx.lock().unwrap().recv();
                    Ok(())
                })
                .await
            }));
        }
        while a.heavy.stats.running.load(Ordering::Relaxed) < 1
            || a.heavy.stats.queued.load(Ordering::Relaxed) < 1
        {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let e = a.run(Cost(50), None, |_| Ok(())).await.unwrap_err();
        assert_eq!(e.code, "server.busy");
        assert_eq!(e.retry_after, Some(3));
        // Cheap work still runs while the heavy lane is full.
        let t = Instant::now();
        a.run(Cost(1), None, |_| Ok(())).await.unwrap();
        assert!(t.elapsed() < Duration::from_secs(2));
        tx.send(()).unwrap();
        tx.send(()).unwrap();
        for r in running {
            r.await.unwrap().unwrap();
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_dropped_request_trips_the_token_of_its_running_job() {
        let a = Arc::new(adm(2, 4));
        let seen = Arc::new(AtomicBool::new(false));
        let s2 = seen.clone();
        let fut = a.run(Cost(1), None, move |c| {
            let t = Instant::now();
            while t.elapsed() < Duration::from_secs(10) {
                if c.check().is_err() {
                    s2.store(true, Ordering::Relaxed);
                    return Err(cancelled_error());
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            Ok(())
        });
        let _ = tokio::time::timeout(Duration::from_millis(100), fut).await;
        let t = Instant::now();
        while !seen.load(Ordering::Relaxed) {
            assert!(t.elapsed() < Duration::from_secs(2), "job not cancelled");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        while a.cheap.stats.running.load(Ordering::Relaxed) > 0 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(a.cancelled.load(Ordering::Relaxed), 1);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_heavy_job_borrows_every_worker_only_on_an_idle_server() {
        let make = |borrow: bool| {
            Arc::new(
                Admission::new(&AdmissionConfig {
                    workers: 4,
                    heavy_share: 0.5,
                    queue_capacity: 4,
                    heavy_nice: 5,
                    heavy_borrow: borrow,
                    borrow_quiet: Duration::from_millis(400),
                    retry_after: 3,
                    request_timeout: Duration::from_secs(60),
                })
                .unwrap(),
            )
        };
        let width = |a: Arc<Admission>| async move {
            a.run(Cost(50), None, |_| Ok(rayon::current_num_threads()))
                .await
                .unwrap()
        };
        let a = make(true);
        assert_eq!(a.heavy_threads(), 2);
        if !cfg!(target_os = "linux") {
            // Without per-thread nice values borrowing would compete with cheap work.
            assert_eq!(width(a.clone()).await, 2);
            return;
        }
        assert_eq!(a.borrow_threads(), 4);
        // Idle: the job gets all four workers.
        assert_eq!(width(a.clone()).await, 4);
        assert_eq!(a.borrowed.load(Ordering::Relaxed), 1);
        // A job of `cost` that runs until told, and answers its pool's width.
        let blocked = |cost: Cost| {
            let (tx, rx) = std::sync::mpsc::channel::<()>();
            let a = a.clone();
            let job = tokio::spawn(async move {
                a.run(cost, None, move |_| {
                    let _ = rx.recv();
                    Ok(rayon::current_num_threads())
                })
                .await
            });
            (tx, job)
        };
        // A cheap job running: the heavy pool's two threads.
        let (tx, cheap) = blocked(Cost(1));
        while a.cheap.stats.running.load(Ordering::Relaxed) < 1 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(width(a.clone()).await, 2);
        tx.send(()).unwrap();
        cheap.await.unwrap().unwrap();
        // Just after it finished: still the heavy pool; once the lane was quiet 400 ms, all.
        assert_eq!(width(a.clone()).await, 2);
        tokio::time::sleep(Duration::from_millis(450)).await;
        assert_eq!(width(a.clone()).await, 4);
        assert_eq!(a.borrowed.load(Ordering::Relaxed), 2);
        // A conversion (work outside the lanes) running: the heavy pool; after it, as after a
        // cheap job.
        let outside = a.outside_work();
        assert_eq!(width(a.clone()).await, 2);
        drop(outside);
        assert_eq!(width(a.clone()).await, 2);
        tokio::time::sleep(Duration::from_millis(450)).await;
        assert_eq!(width(a.clone()).await, 4);
        assert_eq!(a.borrowed.load(Ordering::Relaxed), 3);
        // Another heavy job running: the second one gets the heavy pool.
        let (tx, first) = blocked(Cost(50));
        while a.heavy.stats.running.load(Ordering::Relaxed) < 1 {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(width(a.clone()).await, 2);
        tx.send(()).unwrap();
        assert_eq!(first.await.unwrap().unwrap(), 4);
        assert_eq!(a.borrowed.load(Ordering::Relaxed), 4);
        // Switched off: never.
        let off = make(false);
        assert_eq!(off.borrow_threads(), 2);
        assert_eq!(width(off.clone()).await, 2);
        assert_eq!(off.borrowed.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn a_passed_deadline_cancels() {
        let c = Cancel {
            deadline: Some(Instant::now()),
            ..Cancel::never()
        };
        assert!(c.check().is_err());
        assert!(Cancel::never().check().is_ok());
    }
}
