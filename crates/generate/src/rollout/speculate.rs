//! Speculative decoding with the TAR heads as the draft model.
//!
//! The TAR prior of every position of the new frame exists before the OAR starts, and the TAR heads turn
//! it into a distribution `q` per position that is close to the OAR's `p` (their losses differ by a few
//! percent). A block of `l` positions is drafted from `q`, the OAR runs over the block in one pass, and
//! each draft is accepted with probability `min(1, p/q)`; the first rejected position is drawn from
//! `max(0, p − q)` (normalised). The tokens so drawn have the OAR's distribution exactly (Leviathan et
//! al., 2023), while a one-scene rollout takes one OAR pass per accepted run instead of one per token.
//! With several scenes the block ends where the first scene rejects.

use super::{Generator, host_rows, ids_at};
use crate::error::{GenerateError, Result};
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor, TensorData};
use rand::Rng;
use umgen_backbone::OarCache;

/// Where a speculative block starts and what it may cover.
pub(super) struct Block<'t, B: Backend> {
    /// First position.
    pub(super) p: usize,
    /// Positions in the block (at least 2), all content of segment `s` without rules.
    pub(super) l: usize,
    /// The segment.
    pub(super) s: usize,
    /// The ids of position `p − 1` on the device, if they are there rather than in `out`.
    pub(super) prev: Option<Tensor<B, 1, Int>>,
    /// The TAR prior `[m, N, d]`.
    pub(super) h: &'t Tensor<B, 3>,
}

impl<B: Backend> Generator<'_, B> {
    /// Decodes a block speculatively into `out`; returns how many of its positions are now decided (at
    /// least one), with `cache` holding exactly those.
    pub(super) fn speculate_block(
        &mut self,
        block: Block<'_, B>,
        out: &mut [Vec<u32>],
        cache: &mut OarCache<B>,
        dev: &B::Device,
    ) -> Result<usize> {
        let Block { p, l, s, prev, h } = block;
        let (m, d) = (out.len(), h.dims()[2]);
        let smp = self.sampling[s];
        let model = self.model;
        // Drafts from the TAR heads (one read-back).
        let hp = h.clone().narrow(1, p, l);
        let q_rows = host_rows(model.logits_at(s, hp.clone().reshape([m * l, d]), true));
        let drafts: Vec<Vec<u32>> = (0..m)
            .map(|b| {
                (0..l)
                    .map(|j| smp.draw(&q_rows[b * l + j], &mut self.rng))
                    .collect()
            })
            .collect();
        // The OAR over the block: position p reads token p − 1, the others the drafts before them.
        let prev = match (prev, p) {
            (prev @ Some(_), _) => prev,
            (None, 0) => None,
            (None, _) => Some(ids_at(out, p - 1, dev)),
        };
        let first = model.oar_input_at(p, prev, hp.clone().narrow(1, 0, 1).reshape([m, d]));
        let drafted = Tensor::<B, 2, Int>::from_data(
            TensorData::new(
                drafts
                    .iter()
                    .flat_map(|r| r[..l - 1].iter().map(|&x| i64::from(x)))
                    .collect::<Vec<_>>(),
                [m, l - 1],
            ),
            dev,
        );
        let rest =
            model.embed.forward_block(p, drafted).ok_or_else(|| {
                GenerateError::Settings(format!("positions {p}..{} cross a segment", p + l))
            })? + hp.narrow(1, 1, l - 1);
        let w = Tensor::cat(vec![first.reshape([m, 1, d]), rest], 1);
        let o = model.oar_steps(w, cache)?;
        let p_rows = host_rows(model.logits_at(s, o.reshape([m * l, d]), false));
        // Accept drafts while every scene accepts; the first position any scene rejects is the last one
        // decided, drawn from the residual where rejected (`None`: every draft accepted).
        let mut rejected_at = None;
        for j in 0..l {
            let dists: Vec<_> = (0..m)
                .map(|b| {
                    let r = b * l + j;
                    (smp.distribution(&p_rows[r]), smp.distribution(&q_rows[r]))
                })
                .collect();
            let accepted: Vec<bool> = dists
                .iter()
                .zip(&drafts)
                .map(|((pd, qd), draft)| accepts(pd, qd, draft[j], &mut self.rng))
                .collect();
            if accepted.iter().all(|&a| a) {
                continue;
            }
            for (b, (pd, qd)) in dists.iter().enumerate() {
                out[b][p + j] = if accepted[b] {
                    drafts[b][j]
                } else {
                    residual_draw(pd, qd, &mut self.rng)
                };
            }
            rejected_at = Some(j);
            break;
        }
        // Drafts before the rejected position (all of them if none was) are the tokens.
        let kept = rejected_at.unwrap_or(l);
        for (row, draft) in out.iter_mut().zip(&drafts) {
            row[p..p + kept].copy_from_slice(&draft[..kept]);
        }
        let decided = rejected_at.map_or(l, |j| j + 1);
        cache.rewind(p + decided);
        Ok(decided)
    }
}

/// Whether the draft `x`, drawn from `q`, stands as a draw from `p`: with probability min(1, p(x)/q(x)).
fn accepts(p: &[(u32, f64)], q: &[(u32, f64)], x: u32, rng: &mut impl Rng) -> bool {
    let qx = prob(q, x);
    qx > 0.0 && rng.random::<f64>() < prob(p, x) / qx
}

/// The probability of `x` in a distribution of (id, probability) pairs.
fn prob(dist: &[(u32, f64)], x: u32) -> f64 {
    dist.iter().find(|(i, _)| *i == x).map_or(0.0, |(_, p)| *p)
}

/// A draw from `max(0, p − q)`, normalised (from `p` itself should that be empty, which a rejection
/// rules out up to rounding).
fn residual_draw(p: &[(u32, f64)], q: &[(u32, f64)], rng: &mut impl Rng) -> u32 {
    let r: Vec<(u32, f64)> = p.iter().map(|&(i, pi)| (i, (pi - prob(q, i)).max(0.0))).collect();
    let total: f64 = r.iter().map(|(_, x)| x).sum();
    let (dist, total) = if total > 0.0 { (&r[..], total) } else { (p, 1.0) };
    let mut u = rng.random::<f64>() * total;
    for &(i, x) in dist {
        if u < x {
            return i;
        }
        u -= x;
    }
    dist.last().map_or(0, |&(i, _)| i)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{SeedableRng, rngs::StdRng};

    #[test]
    fn accepted_drafts_and_residual_draws_follow_the_target() {
        // Target p, draft q with other support (id 3 only in q, id 0 more likely in p).
        let p = [(0, 0.5), (1, 0.3), (2, 0.2)];
        let q = [(2, 0.4), (0, 0.2), (1, 0.2), (3, 0.2)];
        let mut rng = StdRng::seed_from_u64(4);
        let n = 200_000;
        let mut c = [0usize; 4];
        for _ in 0..n {
            let mut u = rng.random::<f64>();
            let x = q.iter().find(|(_, w)| {
                let hit = u < *w;
                u -= w;
                hit
            });
            let x = x.map_or(3, |(i, _)| *i);
            let y = if accepts(&p, &q, x, &mut rng) {
                x
            } else {
                residual_draw(&p, &q, &mut rng)
            };
            c[y as usize] += 1;
        }
        for (i, want) in [(0, 0.5), (1, 0.3), (2, 0.2), (3, 0.0)] {
            let got = c[i] as f64 / n as f64;
            assert!((got - want).abs() < 0.005, "id {i}: {got} vs {want}");
        }
        // Equal distributions accept every draft; a draft outside p never stands.
        assert!((0..100).all(|_| accepts(&p, &p, 1, &mut rng)));
        assert!(!accepts(&p, &q, 3, &mut rng));
    }
}
