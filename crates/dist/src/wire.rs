//! Messages of the control connections between rank 0 and the other ranks: length-prefixed JSON.

use serde::{Deserialize, Serialize};
use std::io::{self, Read, Write};

/// Larger frames are refused: the control plane only carries small messages.
const MAX_FRAME: usize = 1 << 20;

/// A control message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) enum Control {
    /// A rank introduces itself to rank 0.
    Hello {
        rank: usize,
        world_size: usize,
        identity: String,
        data_port: u16,
    },
    /// Rank 0 accepts: the ring addresses of all ranks and the shared payload (an NCCL id).
    Welcome { peers: Vec<String>, payload: Vec<u8> },
    /// Rank 0 refuses this rank.
    Refused { reason: String },
    /// Liveness and progress: collectives entered and finished.
    Heartbeat { entered: u64, done: u64 },
    /// A rank finished cleanly; its connection closing is not a failure.
    Bye,
    /// Rank 0 stops the job.
    Abort { reason: String },
}

pub(crate) fn send(w: &mut impl Write, m: &Control) -> io::Result<()> {
    let body = serde_json::to_vec(m).map_err(io::Error::other)?;
    let len = u32::try_from(body.len()).map_err(io::Error::other)?;
    let mut frame = len.to_le_bytes().to_vec();
    frame.extend_from_slice(&body);
    w.write_all(&frame)?;
    w.flush()
}

pub(crate) fn recv(r: &mut impl Read) -> io::Result<Control> {
    let mut len = [0u8; 4];
    r.read_exact(&mut len)?;
    let len = u32::from_le_bytes(len) as usize;
    if len > MAX_FRAME {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("control frame of {len} bytes (not a umgen peer?)"),
        ));
    }
    let mut body = vec![0u8; len];
    r.read_exact(&mut body)?;
    serde_json::from_slice(&body).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn frames_round_trip_and_garbage_is_refused() {
        let m = Control::Hello {
            rank: 2,
            world_size: 4,
            identity: "abc".into(),
            data_port: 4000,
        };
        let mut buf = Vec::new();
        send(&mut buf, &m).unwrap();
        send(&mut buf, &Control::Bye).unwrap();
        let mut r = buf.as_slice();
        assert_eq!(recv(&mut r).unwrap(), m);
        assert_eq!(recv(&mut r).unwrap(), Control::Bye);
        assert!(recv(&mut r).is_err(), "end of stream");
        let mut junk: &[u8] = b"GET / HTTP/1.1\r\n";
        assert!(recv(&mut junk).is_err());
    }
}
