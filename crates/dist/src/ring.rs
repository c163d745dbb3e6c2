//! Ring collectives over TCP on host buffers: each rank sends to the next rank and receives from the
//! previous one. All-reduce is reduce-scatter then all-gather (each rank sends 2·(W−1)/W of the buffer),
//! and every rank ends with bit-identical values because each chunk is summed once, by its owner's ring
//! order, and then copied.

use std::io::{self, Read, Write};
use std::net::TcpStream;

/// A rank's two ring connections.
#[derive(Debug)]
pub(crate) struct Ring {
    pub(crate) rank: usize,
    pub(crate) world: usize,
    pub(crate) next: TcpStream,
    pub(crate) prev: TcpStream,
}

fn bounds(len: usize, world: usize, chunk: usize) -> std::ops::Range<usize> {
    (chunk * len / world)..((chunk + 1) * len / world)
}

fn to_bytes(v: &[f32]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

impl Ring {
    /// Sends `out` to the next rank while receiving `into.len()` floats from the previous one; both at
    /// once, since with large chunks each side's send would otherwise wait for the other's receive.
    fn exchange(&mut self, out: &[f32], into: &mut [f32]) -> io::Result<()> {
        let bytes = to_bytes(out);
        let next = &mut self.next;
        let prev = &mut self.prev;
        std::thread::scope(|sc| {
            let sender = sc.spawn(move || next.write_all(&bytes).and_then(|()| next.flush()));
            let mut buf = vec![0u8; into.len() * 4];
            let got = prev.read_exact(&mut buf);
            let sent = sender
                .join()
                .unwrap_or_else(|_| Err(io::Error::other("ring sender thread panicked")));
            got?;
            sent?;
            for (x, b) in into.iter_mut().zip(buf.chunks_exact(4)) {
                *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
            Ok(())
        })
    }

    /// Sums `buf` over all ranks, in place.
    pub(crate) fn all_reduce_sum(&mut self, buf: &mut [f32]) -> io::Result<()> {
        let (r, w, len) = (self.rank, self.world, buf.len());
        if w == 1 {
            return Ok(());
        }
        let mut incoming = Vec::new();
        for s in 0..w - 1 {
            let send = bounds(len, w, (r + w - s) % w);
            let recv = bounds(len, w, (r + 2 * w - s - 1) % w);
            incoming.resize(recv.len(), 0.0);
            let out = buf[send].to_vec();
            self.exchange(&out, &mut incoming)?;
            for (x, y) in buf[recv].iter_mut().zip(&incoming) {
                *x += y;
            }
        }
        for s in 0..w - 1 {
            let send = bounds(len, w, (r + 1 + w - s) % w);
            let recv = bounds(len, w, (r + w - s) % w);
            let out = buf[send].to_vec();
            self.exchange(&out, &mut buf[recv])?;
        }
        Ok(())
    }

    /// Copies `root`'s `buf` to every rank along the ring.
    pub(crate) fn broadcast(&mut self, buf: &mut [f32], root: usize) -> io::Result<()> {
        let w = self.world;
        if w == 1 {
            return Ok(());
        }
        if self.rank != root {
            let mut bytes = vec![0u8; buf.len() * 4];
            self.prev.read_exact(&mut bytes)?;
            for (x, b) in buf.iter_mut().zip(bytes.chunks_exact(4)) {
                *x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
        if (self.rank + 1) % w != root {
            self.next.write_all(&to_bytes(buf))?;
            self.next.flush()?;
        }
        Ok(())
    }
}
