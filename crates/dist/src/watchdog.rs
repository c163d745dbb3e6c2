//! The watchdog: keeps the control connections to rank 0 alive and turns a dead, stopped or hung rank
//! into a failure of every rank, named, within the timeout.
//!
//! Every rank counts the collectives it has entered and finished and sends the counts to rank 0 once a
//! second; rank 0 answers with its own heartbeats. Rank 0 fails the job when a peer's connection closes
//! without a goodbye (the process died), when a peer sends nothing for the timeout (stopped), or when some
//! rank has waited in collective #k for the timeout while another rank has not reached it (hung). It then
//! tells every rank why (`Abort`). A failure shuts the ring sockets down, so that a TCP collective blocked
//! on a dead peer returns an error at once, and calls the failure hook, which the `umgen` binary uses to
//! exit: an NCCL collective waiting for a dead peer never returns on its own.

use crate::wire::{self, Control};
use std::net::{Shutdown, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

/// Called once with the reason when the job fails.
pub type FailureHook = Arc<dyn Fn(&str) + Send + Sync>;

const HEARTBEAT: Duration = Duration::from_millis(500);

#[derive(Debug, Clone, Copy)]
struct Progress {
    entered: u64,
    done: u64,
    since: Instant,
    bye: bool,
}

impl Progress {
    fn new() -> Self {
        Self {
            entered: 0,
            done: 0,
            since: Instant::now(),
            bye: false,
        }
    }

    fn update(&mut self, entered: u64, done: u64) {
        if entered != self.entered {
            self.since = Instant::now();
        }
        self.entered = entered;
        self.done = done;
    }
}

struct Shared {
    rank: usize,
    timeout: Duration,
    entered: AtomicU64,
    done: AtomicU64,
    finished: AtomicBool,
    failure: Mutex<Option<String>>,
    hook: FailureHook,
    /// Control writers: to rank 0 (other ranks), or to every peer by rank (rank 0; `None` for itself).
    writers: Vec<Option<Mutex<TcpStream>>>,
    /// Sockets shut down on failure.
    ring: Vec<TcpStream>,
    peers: Mutex<Vec<Progress>>,
}

impl Shared {
    fn fail(&self, reason: String) {
        {
            let mut f = self.failure.lock().unwrap_or_else(PoisonError::into_inner);
            if f.is_some() || self.finished.load(Ordering::SeqCst) {
                return;
            }
            *f = Some(reason.clone());
        }
        tracing::error!("rank {}: {reason}", self.rank);
        for s in &self.ring {
            let _ = s.shutdown(Shutdown::Both);
        }
        if self.rank == 0 {
            for w in self.writers.iter().flatten() {
                let mut w = w.lock().unwrap_or_else(PoisonError::into_inner);
                let _ = wire::send(
                    &mut *w,
                    &Control::Abort {
                        reason: reason.clone(),
                    },
                );
            }
        }
        (self.hook)(&reason);
    }

    fn send(&self, to: usize, m: &Control) -> std::io::Result<()> {
        match self.writers.get(to).and_then(Option::as_ref) {
            Some(w) => wire::send(&mut *w.lock().unwrap_or_else(PoisonError::into_inner), m),
            None => Ok(()),
        }
    }
}

/// The running watchdog of one rank.
#[derive(Clone)]
pub struct Watchdog {
    shared: Arc<Shared>,
}

impl std::fmt::Debug for Watchdog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Watchdog")
            .field("rank", &self.shared.rank)
            .field("failure", &self.failure())
            .finish()
    }
}

impl Watchdog {
    /// Starts the threads. `controls[r]` is the control connection to rank `r` (rank 0 holds one per
    /// peer; other ranks only `controls[0]`).
    pub(crate) fn start(
        rank: usize,
        controls: Vec<Option<TcpStream>>,
        ring: Vec<TcpStream>,
        timeout: Duration,
        hook: FailureHook,
    ) -> std::io::Result<Self> {
        let world = controls.len();
        let mut readers = Vec::new();
        let mut writers = Vec::new();
        for c in controls {
            match c {
                Some(s) => {
                    s.set_read_timeout(Some(timeout))?;
                    s.set_write_timeout(Some(timeout))?;
                    readers.push(Some(s.try_clone()?));
                    writers.push(Some(Mutex::new(s)));
                }
                None => {
                    readers.push(None);
                    writers.push(None);
                }
            }
        }
        let shared = Arc::new(Shared {
            rank,
            timeout,
            entered: AtomicU64::new(0),
            done: AtomicU64::new(0),
            finished: AtomicBool::new(false),
            failure: Mutex::new(None),
            hook,
            writers,
            ring,
            peers: Mutex::new(vec![Progress::new(); world]),
        });
        for (peer, r) in readers.into_iter().enumerate() {
            if let Some(r) = r {
                let s = shared.clone();
                std::thread::Builder::new()
                    .name(format!("umgen-watchdog-read-{peer}"))
                    .spawn(move || read_loop(&s, peer, r))?;
            }
        }
        let s = shared.clone();
        std::thread::Builder::new()
            .name("umgen-watchdog".into())
            .spawn(move || beat_loop(&s))?;
        Ok(Self { shared })
    }

    /// Marks the start of a collective; returns its number.
    pub fn enter(&self) -> u64 {
        self.shared.entered.fetch_add(1, Ordering::SeqCst) + 1
    }

    /// Marks the end of the current collective.
    pub fn leave(&self) {
        self.shared.done.fetch_add(1, Ordering::SeqCst);
    }

    /// Why the job failed, if it did.
    pub fn failure(&self) -> Option<String> {
        self.shared
            .failure
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Runs collective `op` of `rank`, counted so that rank 0 can tell who is missing. On failure, after
    /// `grace` (time for the watchdog to learn why a socket broke), the watchdog's reason — which names
    /// the peer — replaces `f`'s error when it has one.
    pub(crate) fn track<T>(
        dog: Option<&Watchdog>,
        rank: usize,
        op: &'static str,
        grace: Duration,
        f: impl FnOnce() -> crate::Result<T>,
    ) -> crate::Result<T> {
        if let Some(d) = dog {
            d.enter();
        }
        let out = f();
        if let Some(d) = dog {
            d.leave();
        }
        out.map_err(|e| {
            std::thread::sleep(grace);
            match dog.and_then(Watchdog::failure) {
                Some(reason) => crate::DistError::Collective { rank, op, reason },
                None => e,
            }
        })
    }

    /// Leaves the job without a goodbye, as a crashed process would: closes every socket, so that the
    /// other ranks fail (and name this rank) at once.
    pub(crate) fn abandon(&self) {
        let s = &self.shared;
        if s.finished.swap(true, Ordering::SeqCst) {
            return;
        }
        for w in s.writers.iter().flatten() {
            let _ = w
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .shutdown(Shutdown::Both);
        }
        for r in &s.ring {
            let _ = r.shutdown(Shutdown::Both);
        }
    }

    /// Ends cleanly: other ranks say goodbye; rank 0 waits (up to the timeout) for every goodbye, so
    /// that no rank mistakes another's exit for a crash. Call after a final barrier.
    pub fn finish(&self) {
        let s = &self.shared;
        if s.rank != 0 {
            let _ = s.send(0, &Control::Bye);
            s.finished.store(true, Ordering::SeqCst);
            return;
        }
        let deadline = Instant::now() + s.timeout;
        while Instant::now() < deadline && self.failure().is_none() {
            let all = s
                .peers
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .iter()
                .skip(1)
                .all(|p| p.bye);
            if all {
                break;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        s.finished.store(true, Ordering::SeqCst);
    }
}

fn read_loop(s: &Shared, peer: usize, mut r: TcpStream) {
    loop {
        let msg = wire::recv(&mut r);
        if s.finished.load(Ordering::SeqCst) {
            return;
        }
        match msg {
            Ok(Control::Heartbeat { entered, done }) => {
                let mut p = s.peers.lock().unwrap_or_else(PoisonError::into_inner);
                p[peer].update(entered, done);
            }
            Ok(Control::Bye) => {
                s.peers.lock().unwrap_or_else(PoisonError::into_inner)[peer].bye = true;
                return;
            }
            Ok(Control::Abort { reason }) => {
                return s.fail(format!("rank {peer} stopped the job: {reason}"));
            }
            Ok(other) => {
                return s.fail(format!("rank {peer} sent an unexpected {other:?}"));
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return s.fail(format!(
                    "rank {peer} sent nothing for {} s (stopped or hung)",
                    s.timeout.as_secs()
                ));
            }
            Err(e) => {
                return s.fail(format!("rank {peer} exited or lost its connection ({e})"));
            }
        }
    }
}

fn beat_loop(s: &Shared) {
    while !s.finished.load(Ordering::SeqCst) && s.failure.lock().is_ok_and(|f| f.is_none()) {
        let (entered, done) = (s.entered.load(Ordering::SeqCst), s.done.load(Ordering::SeqCst));
        let beat = Control::Heartbeat { entered, done };
        for to in 0..s.writers.len() {
            // A broken connection is reported by its reader.
            let _ = s.send(to, &beat);
        }
        if s.rank == 0 {
            let mut peers = s.peers.lock().unwrap_or_else(PoisonError::into_inner);
            peers[0].update(entered, done);
            if let Some(reason) = straggler(&peers, s.timeout) {
                drop(peers);
                return s.fail(reason);
            }
        }
        std::thread::sleep(HEARTBEAT);
    }
}

/// A rank that others have waited for in a collective longer than `timeout`.
fn straggler(peers: &[Progress], timeout: Duration) -> Option<String> {
    let waiting = peers
        .iter()
        .filter(|p| p.entered > p.done && p.since.elapsed() > timeout)
        .max_by_key(|p| p.entered)?;
    let (r, late) = peers
        .iter()
        .enumerate()
        .find(|(_, p)| p.entered < waiting.entered && !p.bye)?;
    Some(format!(
        "rank {r} has not reached collective #{} for {} s (it is at #{}; hung?)",
        waiting.entered,
        timeout.as_secs(),
        late.entered
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rank_behind_a_long_wait_is_named() {
        let long_ago = Instant::now() - Duration::from_secs(10);
        let at = |entered, done, since| Progress {
            entered,
            done,
            since,
            bye: false,
        };
        let t = Duration::from_secs(5);
        let peers = [at(7, 6, long_ago), at(6, 6, long_ago), at(7, 6, Instant::now())];
        let msg = straggler(&peers, t).unwrap_or_default();
        assert!(msg.starts_with("rank 1 has not reached collective #7"), "{msg}");
        // Everybody inside the same collective: slow, not hung.
        assert_eq!(straggler(&[at(7, 6, long_ago), at(7, 6, long_ago)], t), None);
        // A short wait is not a hang.
        assert_eq!(
            straggler(&[at(7, 6, Instant::now()), at(6, 6, long_ago)], t),
            None
        );
    }
}
