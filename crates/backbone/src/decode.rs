//! Incremental decoding for generation: the OAR one position at a time over a key/value cache, so that a
//! frame of N tokens costs N small steps instead of N forward passes over growing prefixes.

use crate::error::BackboneError;
use crate::model::Backbone;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};

/// Keys and values of the positions decoded so far, per layer, in tensors of a fixed capacity (allocated
/// on the first step), so that every decoding step has the same shapes.
#[derive(Debug, Clone)]
pub struct OarCache<B: Backend> {
    pub(crate) layers: Vec<Option<(Tensor<B, 4>, Tensor<B, 4>)>>,
    len: usize,
    capacity: usize,
    /// `0..capacity` as `[1, 1, 1, capacity]`, uploaded once: each step's mask is a comparison with it.
    keys: Option<Tensor<B, 4>>,
}

impl<B: Backend> OarCache<B> {
    /// An empty cache of `layers` layers with room for `capacity` positions.
    fn new(layers: usize, capacity: usize) -> Self {
        Self {
            layers: vec![None; layers],
            len: 0,
            capacity,
            keys: None,
        }
    }

    /// Positions cached.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether nothing is cached yet.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Positions it has room for.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Takes the next position: its index and the additive mask `[1, 1, 1, capacity]` of the keys it
    /// may not see (0 up to it, −1e30 after, so that no −∞ meets a zero and makes a NaN).
    pub(crate) fn advance(&mut self, dev: &B::Device) -> Result<(usize, Tensor<B, 4>), BackboneError> {
        self.advance_by(1, dev)
    }

    /// Takes the next `l` positions: the first one's index and the mask `[1, 1, l, capacity]` in which
    /// row i hides the keys after position `pos + i` (causal within the block). The mask compares the key
    /// positions, uploaded once, with the query positions: for one position a scalar, so a decoding step
    /// uploads nothing.
    pub(crate) fn advance_by(
        &mut self,
        l: usize,
        dev: &B::Device,
    ) -> Result<(usize, Tensor<B, 4>), BackboneError> {
        let (pos, l) = (self.len, l.max(1));
        if pos + l > self.capacity {
            return Err(BackboneError::Input(format!(
                "the decoding cache holds {} positions and is full: no room for {l} more after {pos}",
                self.capacity
            )));
        }
        self.len += l;
        let capacity = self.capacity;
        let keys = self.keys.get_or_insert_with(|| {
            Tensor::<B, 1, Int>::arange(0..capacity as i64, dev)
                .float()
                .reshape([1, 1, 1, capacity])
        });
        let hidden = if l == 1 {
            keys.clone().greater_elem(pos as f64)
        } else {
            let rows = Tensor::<B, 1, Int>::arange(pos as i64..(pos + l) as i64, dev)
                .float()
                .reshape([1, 1, l, 1]);
            keys.clone().greater(rows)
        };
        Ok((pos, hidden.float().mul_scalar(-1e30)))
    }

    /// Forgets the positions from `len` on (they stay in the tensors, hidden by the mask, and are
    /// overwritten when decoded again): how a rejected speculative block is undone.
    pub fn rewind(&mut self, len: usize) {
        self.len = self.len.min(len);
    }
}

/// What position `p` of a frame holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// The start token of segment `.0` (its id is the segment's `vocab`).
    Start(usize),
    /// Content token `.1` of segment `.0`.
    Content(usize, usize),
    /// The end token of segment `.0` (id `vocab + 1`).
    End(usize),
}

impl<B: Backend> Backbone<B> {
    /// An empty cache for one frame (N positions).
    pub fn oar_cache(&self) -> OarCache<B> {
        OarCache::new(self.oar_layers(), self.spec().n)
    }

    /// The OAR input at position `p` of a frame: the learned start vector (p = 0) or the embedding of the
    /// previous token `prev` `[m]` (p > 0), plus the TAR prior `h_p` `[m, d]`.
    pub fn oar_input_at(&self, p: usize, prev: Option<Tensor<B, 1, Int>>, h_p: Tensor<B, 2>) -> Tensor<B, 2> {
        match (p, prev) {
            (0, _) | (_, None) => {
                let [m, d] = h_p.dims();
                self.oar_start().reshape([1, d]).expand([m, d]) + h_p
            }
            (p, Some(ids)) => self.embed.forward_at(p - 1, ids) + h_p,
        }
    }

    /// The OAR output `[m, d]` of the next position, given its input `w` `[m, d]`; updates `cache`.
    /// Fails when the cache is full (more than N steps on one frame's cache).
    pub fn oar_step(&self, w: Tensor<B, 2>, cache: &mut OarCache<B>) -> Result<Tensor<B, 2>, BackboneError> {
        let [m, d] = w.dims();
        let (pos, hidden) = cache.advance(&w.device())?;
        let x = self.oar_blocks_step(w.reshape([m, 1, d]), &mut cache.layers, pos, hidden);
        Ok(x.reshape([m, d]))
    }

    /// The OAR outputs `[m, l, d]` of the next `l` positions at once, given their inputs `w` `[m, l, d]`
    /// (causal among them); updates `cache`. Equal to `l` calls of [`oar_step`](Self::oar_step).
    pub fn oar_steps(&self, w: Tensor<B, 3>, cache: &mut OarCache<B>) -> Result<Tensor<B, 3>, BackboneError> {
        let l = w.dims()[1];
        let (pos, hidden) = cache.advance_by(l, &w.device())?;
        Ok(self.oar_blocks_step(w, &mut cache.layers, pos, hidden))
    }

    /// Logits `[m, vocab]` of content slot of segment `s` from OAR (or TAR) features `[m, d]`.
    pub fn logits_at(&self, s: usize, x: Tensor<B, 2>, tar: bool) -> Tensor<B, 2> {
        if tar {
            self.tar_heads.logits_at(s, x)
        } else {
            self.oar_heads.logits_at(s, x)
        }
    }

    /// What each position of a frame holds.
    pub fn slots(&self) -> Vec<Slot> {
        let mut out = Vec::with_capacity(self.spec().n);
        for (i, s) in self.spec().segments.iter().enumerate() {
            for p in s.block_start..s.block_start + s.block_len {
                out.push(if p < s.offset {
                    Slot::Start(i)
                } else if p >= s.offset + s.tokens {
                    Slot::End(i)
                } else {
                    Slot::Content(i, p - s.offset)
                });
            }
        }
        out
    }
}

/// The baseline of the paper's Fig. 7: one causal transformer over the concatenated tokens of all frames
/// (no TAR), of the same width, decoding with a key/value cache that grows with the history. Only its
/// per-token cost matters, so it has no embedding tables: inputs are feature vectors.
#[derive(burn::module::Module, Debug)]
pub struct VanillaAr<B: Backend> {
    blocks: Vec<crate::layers::SelfBlock<B>>,
    ln: burn::nn::LayerNorm<B>,
    head: burn::nn::Linear<B>,
}

impl<B: Backend> VanillaAr<B> {
    /// `depth` causal layers of width `d` (products in `precision`) and a head over `vocab` ids.
    pub fn new(
        d: usize,
        heads: usize,
        ratio: usize,
        depth: usize,
        vocab: usize,
        precision: crate::config::Precision,
        dev: &B::Device,
    ) -> Self {
        Self {
            blocks: (0..depth)
                .map(|_| {
                    let sizes = crate::layers::LayerSizes {
                        d,
                        heads,
                        ratio,
                        dropout: 0.0,
                        precision,
                    };
                    crate::layers::SelfBlock::new(sizes, dev)
                })
                .collect(),
            ln: burn::nn::LayerNormConfig::new(d).init(dev),
            head: burn::nn::LinearConfig::new(d, vocab).with_bias(false).init(dev),
        }
    }

    /// A cache holding `len` earlier positions of `m` sequences (random keys and values: the cost of a
    /// step does not depend on them) with room for `room` more.
    pub fn filled_cache(
        &self,
        m: usize,
        len: usize,
        room: usize,
        heads: usize,
        dev: &B::Device,
    ) -> OarCache<B> {
        let d = self.ln.gamma.val().dims()[0];
        let kv = || {
            Tensor::<B, 4>::random(
                [m, heads, len + room, d / heads],
                burn::tensor::Distribution::Normal(0.0, 1.0),
                dev,
            )
        };
        let mut cache = OarCache::new(self.blocks.len(), len + room);
        cache.layers = self.blocks.iter().map(|_| Some((kv(), kv()))).collect();
        cache.len = len;
        cache
    }

    /// Logits `[m, vocab]` of the next position from input features `[m, d]`; updates `cache`. Fails
    /// when the cache is full.
    pub fn step(&self, x: Tensor<B, 2>, cache: &mut OarCache<B>) -> Result<Tensor<B, 2>, BackboneError> {
        let [m, d] = x.dims();
        let (pos, hidden) = cache.advance(&x.device())?;
        let mut h = x.reshape([m, 1, d]);
        for (blk, c) in self.blocks.iter().zip(cache.layers.iter_mut()) {
            h = blk.forward_step(h, c, pos, hidden.clone());
        }
        Ok(self.head.forward(self.ln.forward(h).reshape([m, d])))
    }
}
