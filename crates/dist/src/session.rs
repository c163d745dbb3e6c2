//! The rendezvous: every rank meets rank 0 at `MASTER_ADDR:MASTER_PORT`, rank 0 checks that all run the
//! same job (world size, config identity, distinct ranks) and hands out the ring addresses and a shared
//! payload (the NCCL unique id); then the ranks connect their ring and start the watchdog.

use crate::env::DistEnv;
use crate::error::{DistError, Result};
use crate::ring::Ring;
use crate::watchdog::{FailureHook, Watchdog};
use crate::wire::{self, Control};
use std::io::Write;
use std::net::{IpAddr, SocketAddr, TcpListener, TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// How a session behaves.
#[derive(Clone)]
pub struct SessionOptions {
    /// Longest wait for the rendezvous, for a peer's heartbeat, and for a collective that a peer has not
    /// joined; past it every rank fails with a message naming the rank.
    pub timeout: Duration,
    /// Called once when the job fails (after the sockets are shut down); the binary exits there.
    pub on_failure: FailureHook,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            timeout: Duration::from_secs(120),
            on_failure: Arc::new(|_| {}),
        }
    }
}

impl std::fmt::Debug for SessionOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SessionOptions")
            .field("timeout", &self.timeout)
            .finish()
    }
}

/// A rank that has met the others.
#[derive(Debug)]
pub struct Session {
    /// Who this process is.
    pub env: DistEnv,
    /// Rank 0's payload, on every rank.
    pub payload: Vec<u8>,
    pub(crate) ring: Option<Ring>,
    pub(crate) watchdog: Option<Watchdog>,
}

impl Session {
    /// A single process: no sockets, no threads.
    pub fn single(payload: Vec<u8>) -> Self {
        Self {
            env: DistEnv::single(),
            payload,
            ring: None,
            watchdog: None,
        }
    }

    /// Meets the other ranks. `identity` must be equal on every rank (e.g. a hash of the resolved config);
    /// rank 0 calls `payload` once and every rank receives the result.
    pub fn connect(
        env: DistEnv,
        identity: &str,
        options: &SessionOptions,
        payload: impl FnOnce() -> Result<Vec<u8>>,
    ) -> Result<Self> {
        if env.world_size == 1 {
            return Ok(Self::single(payload()?));
        }
        let deadline = Instant::now() + options.timeout;
        let err = |reason: String| DistError::Rendezvous {
            rank: env.rank,
            addr: env.master(),
            reason,
        };
        let io = |what: &str| {
            let err = &err;
            let what = what.to_string();
            move |e: std::io::Error| err(format!("{what}: {e}"))
        };
        let (controls, peers, payload, data) = if env.rank == 0 {
            let listener = TcpListener::bind(("0.0.0.0", env.master_port))
                .map_err(io(&format!("listening on port {}", env.master_port)))?;
            let data = TcpListener::bind(("0.0.0.0", 0)).map_err(io("listening for the ring"))?;
            let data_port = data.local_addr().map_err(io("ring port"))?.port();
            let (controls, peers, payload) =
                host(&env, identity, listener, data_port, deadline, payload).map_err(err)?;
            (controls, peers, payload, data)
        } else {
            let mut c = connect_until(&env.master(), deadline).map_err(err)?;
            let local_ip = c.local_addr().map_err(io("local address"))?.ip();
            let data = TcpListener::bind((local_ip, 0)).map_err(io("listening for the ring"))?;
            let data_port = data.local_addr().map_err(io("ring port"))?.port();
            let hello = Control::Hello {
                rank: env.rank,
                world_size: env.world_size,
                identity: identity.into(),
                data_port,
            };
            wire::send(&mut c, &hello).map_err(io("sending hello"))?;
            c.set_read_timeout(Some(remaining(deadline)))
                .map_err(io("socket"))?;
            let reply = wire::recv(&mut c).map_err(io("waiting for rank 0's answer"))?;
            let (peers, payload) = match reply {
                Control::Welcome { peers, payload } => (peers, payload),
                Control::Refused { reason } => {
                    return Err(DistError::Refused {
                        rank: env.rank,
                        reason,
                    });
                }
                other => return Err(err(format!("unexpected answer {other:?}"))),
            };
            let mut controls: Vec<Option<TcpStream>> = (0..env.world_size).map(|_| None).collect();
            controls[0] = Some(c);
            (controls, peers, payload, data)
        };
        let ring = connect_ring(&env, &peers, &data, deadline, options.timeout).map_err(err)?;
        let sockets = [&ring.next, &ring.prev]
            .iter()
            .filter_map(|s| s.try_clone().ok())
            .collect();
        let watchdog = Watchdog::start(
            env.rank,
            controls,
            sockets,
            options.timeout,
            options.on_failure.clone(),
        )
        .map_err(io("starting the watchdog"))?;
        tracing::debug!("rank {}: joined {} ranks", env.rank, env.world_size);
        Ok(Self {
            env,
            payload,
            ring: Some(ring),
            watchdog: Some(watchdog),
        })
    }

    /// This rank.
    pub fn rank(&self) -> usize {
        self.env.rank
    }

    /// Number of ranks.
    pub fn world_size(&self) -> usize {
        self.env.world_size
    }
}

impl Drop for Session {
    /// A session dropped before [`Group::finish`](crate::Group::finish) abandons the job: its peers see
    /// the closed sockets and fail, naming this rank, instead of waiting for the timeout.
    fn drop(&mut self) {
        if let Some(w) = &self.watchdog {
            w.abandon();
        }
    }
}

fn remaining(deadline: Instant) -> Duration {
    deadline
        .saturating_duration_since(Instant::now())
        .max(Duration::from_millis(1))
}

fn connect_until(addr: &str, deadline: Instant) -> Result<TcpStream, String> {
    let mut last = String::from("no address");
    loop {
        match addr.to_socket_addrs() {
            Ok(addrs) => {
                for a in addrs {
                    match TcpStream::connect_timeout(&a, Duration::from_secs(2)) {
                        Ok(s) => {
                            let _ = s.set_nodelay(true);
                            return Ok(s);
                        }
                        Err(e) => last = e.to_string(),
                    }
                }
            }
            Err(e) => last = format!("resolving: {e}"),
        }
        if Instant::now() >= deadline {
            return Err(format!("could not connect before the timeout ({last})"));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

type Hosted = (Vec<Option<TcpStream>>, Vec<String>, Vec<u8>);

/// Rank 0's side: accept, check and welcome every other rank.
fn host(
    env: &DistEnv,
    identity: &str,
    listener: TcpListener,
    data_port: u16,
    deadline: Instant,
    payload: impl FnOnce() -> Result<Vec<u8>>,
) -> Result<Hosted, String> {
    let w = env.world_size;
    let mut controls: Vec<Option<TcpStream>> = (0..w).map(|_| None).collect();
    let mut peers = vec![String::new(); w];
    listener.set_nonblocking(true).map_err(|e| e.to_string())?;
    let mut problems = Vec::new();
    let mut joined = 1;
    while joined < w {
        let (mut s, addr) = match listener.accept() {
            Ok(x) => x,
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    let missing: Vec<String> = (1..w)
                        .filter(|r| controls[*r].is_none())
                        .map(|r| r.to_string())
                        .collect();
                    return Err(format!("timed out waiting for rank(s) {}", missing.join(", ")));
                }
                std::thread::sleep(Duration::from_millis(10));
                continue;
            }
            Err(e) => return Err(format!("accepting: {e}")),
        };
        let setup = s
            .set_nonblocking(false)
            .and_then(|()| s.set_nodelay(true))
            .and_then(|()| s.set_read_timeout(Some(remaining(deadline))));
        if let Err(e) = setup {
            return Err(format!("connection from {addr}: {e}"));
        }
        let hello = match wire::recv(&mut s) {
            Ok(Control::Hello {
                rank,
                world_size,
                identity: theirs,
                data_port,
            }) => (rank, world_size, theirs, data_port),
            // Not a umgen rank (a port scanner, a stale process): ignore it.
            Ok(_) | Err(_) => continue,
        };
        let (rank, world_size, theirs, their_port) = hello;
        let problem = if world_size != w {
            Some(format!(
                "rank {rank} runs with world size {world_size}, rank 0 with {w}"
            ))
        } else if rank == 0 || rank >= w {
            Some(format!("a process claims rank {rank} of {w}"))
        } else if controls[rank].is_some() {
            Some(format!("two processes claim rank {rank}"))
        } else if theirs != identity {
            Some(format!(
                "rank {rank} runs another configuration (identity {theirs}, rank 0 has {identity})"
            ))
        } else {
            None
        };
        if let Some(p) = problem {
            let _ = wire::send(&mut s, &Control::Refused { reason: p.clone() });
            problems.push(p);
            // Stop at once: the job cannot succeed; tell the ranks already here.
            refuse_all(&mut controls, &problems.join("; "));
            return Err(problems.join("; "));
        }
        peers[rank] = format!("{}:{their_port}", addr.ip());
        controls[rank] = Some(s);
        joined += 1;
    }
    let payload = match payload() {
        Ok(p) => p,
        Err(e) => {
            refuse_all(&mut controls, &format!("rank 0 failed: {e}"));
            return Err(e.to_string());
        }
    };
    // Rank 0's ring address as its peers see it: the address they reached it at.
    let own_ip = controls
        .iter()
        .flatten()
        .next()
        .and_then(|s| s.local_addr().ok())
        .map_or(IpAddr::from([127, 0, 0, 1]), |a| a.ip());
    peers[0] = SocketAddr::new(own_ip, data_port).to_string();
    for s in controls.iter_mut().flatten() {
        wire::send(
            s,
            &Control::Welcome {
                peers: peers.clone(),
                payload: payload.clone(),
            },
        )
        .map_err(|e| format!("welcoming a rank: {e}"))?;
    }
    Ok((controls, peers, payload))
}

fn refuse_all(controls: &mut [Option<TcpStream>], reason: &str) {
    for s in controls.iter_mut().flatten() {
        let _ = wire::send(
            s,
            &Control::Refused {
                reason: reason.into(),
            },
        );
    }
}

/// Connects to the next rank and accepts the previous one.
fn connect_ring(
    env: &DistEnv,
    peers: &[String],
    data: &TcpListener,
    deadline: Instant,
    timeout: Duration,
) -> Result<Ring, String> {
    let w = env.world_size;
    let (next_rank, prev_rank) = ((env.rank + 1) % w, (env.rank + w - 1) % w);
    let mut next = connect_until(&peers[next_rank], deadline)
        .map_err(|e| format!("ring connection to rank {next_rank} at {}: {e}", peers[next_rank]))?;
    next.write_all(&(env.rank as u64).to_le_bytes())
        .map_err(|e| e.to_string())?;
    data.set_nonblocking(true).map_err(|e| e.to_string())?;
    let prev = loop {
        match data.accept() {
            Ok((mut s, _)) => {
                s.set_nonblocking(false).map_err(|e| e.to_string())?;
                s.set_read_timeout(Some(remaining(deadline)))
                    .map_err(|e| e.to_string())?;
                let mut who = [0u8; 8];
                if std::io::Read::read_exact(&mut s, &mut who).is_ok()
                    && u64::from_le_bytes(who) == prev_rank as u64
                {
                    break s;
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                if Instant::now() >= deadline {
                    return Err(format!(
                        "timed out waiting for the ring connection from rank {prev_rank}"
                    ));
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            Err(e) => return Err(format!("ring accept: {e}")),
        }
    };
    for s in [&next, &prev] {
        s.set_nodelay(true)
            // Longer than the watchdog's timeout, so that the watchdog, which knows which rank is
            // missing, speaks first; this only catches a stalled network.
            .and_then(|()| s.set_read_timeout(Some(2 * timeout)))
            .and_then(|()| s.set_write_timeout(Some(2 * timeout)))
            .map_err(|e| e.to_string())?;
    }
    Ok(Ring {
        rank: env.rank,
        world: w,
        next,
        prev,
    })
}
