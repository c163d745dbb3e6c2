//! The backbone: embeddings, ego-action prediction, AMA, TAR, OAR and heads (paper §3.2).

use crate::ama::align;
use crate::config::BackboneConfig;
use crate::ego::{EgoModule, EgoSizes};
use crate::embed::FrameEmbedding;
use crate::error::{BackboneError, Result};
use crate::heads::Heads;
use crate::layers::{LayerSizes, SelfBlock};
use crate::ready::{oar_point, tar_point};
use crate::spec::BackboneSpec;
use crate::track::TrackProjection;
use burn::module::{Module, Param};
use burn::nn::{LayerNorm, LayerNormConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Int, Tensor, TensorData};
use umgen_ops::Kernels;
use umgen_ops::ready::ReadyPoints;

/// One TAR block: causal attention over time at each position, then bidirectional attention within
/// each frame.
#[derive(Module, Debug)]
pub struct TarBlock<B: Backend> {
    temporal: SelfBlock<B>,
    spatial: SelfBlock<B>,
}

impl<B: Backend> TarBlock<B> {
    fn forward(&self, x: Tensor<B, 4>, k: &Kernels) -> Tensor<B, 4> {
        let [b, t, n, d] = x.dims();
        let xt = self.temporal.forward_over_time(x, k);
        let xs = self.spatial.forward(xt.reshape([b * t, n, d]), false, k);
        xs.reshape([b, t, n, d])
    }
}

/// The TAR/OAR backbone.
#[derive(Module, Debug)]
pub struct Backbone<B: Backend> {
    /// Token embedding.
    pub embed: FrameEmbedding<B>,
    time: Param<Tensor<B, 2>>,
    /// Ego-action prediction.
    pub ego: Option<EgoModule<B>>,
    tar: Vec<TarBlock<B>>,
    ln_tar: LayerNorm<B>,
    oar_bos: Param<Tensor<B, 1>>,
    oar: Vec<SelfBlock<B>>,
    ln_oar: LayerNorm<B>,
    /// Projections of the moved slots' embeddings (`backbone.track`).
    track: Option<TrackProjection<B>>,
    /// Heads on the TAR output.
    pub tar_heads: Heads<B>,
    /// Heads on the OAR output.
    pub oar_heads: Heads<B>,
    spec: BackboneSpec,
}

impl<B: Backend> Backbone<B> {
    /// A freshly initialised backbone of `cfg` for frames of `spec`.
    pub fn new(cfg: &BackboneConfig, spec: &BackboneSpec, dev: &B::Device) -> Result<Self> {
        spec.validate(cfg)?;
        let d = cfg.d_model;
        let layer = LayerSizes {
            d,
            heads: cfg.heads,
            ratio: cfg.mlp_ratio,
            dropout: cfg.dropout,
            precision: cfg.precision,
        };
        let block = |_| SelfBlock::new(layer, dev);
        // How many leading ids of each segment start as a sinusoid: its value bins, or none.
        let ordinal: Vec<usize> = spec
            .segments
            .iter()
            .map(|s| if cfg.ordinal_init { s.ordinal } else { 0 })
            .collect();
        let ego = spec.action.as_ref().map(|a| {
            let s = &spec.segments[a.segment];
            let sizes = EgoSizes {
                layer,
                hist: cfg.ego_hist_layers,
                env: cfg.ego_env_layers,
                last: cfg.ego_last,
            };
            EgoModule::new(
                sizes,
                s.tokens,
                s.vocab,
                ordinal[a.segment],
                [s.block_start, s.block_len],
                s.offset,
                dev,
            )
        });
        // The module keeps the spec for shapes; codebooks already went into the tables.
        let mut light = spec.clone();
        for s in &mut light.segments {
            s.codebook = None;
        }
        Ok(Self {
            embed: FrameEmbedding::new(spec, cfg.embed(), d, cfg.dropout, cfg.precision, &ordinal, dev),
            time: Param::from_tensor(Tensor::random(
                [cfg.max_frames, d],
                Distribution::Normal(0.0, 0.02),
                dev,
            )),
            ego,
            tar: (0..cfg.tar_layers)
                .map(|i| TarBlock {
                    temporal: block(i),
                    spatial: block(i),
                })
                .collect(),
            ln_tar: LayerNormConfig::new(d).init(dev),
            oar_bos: Param::from_tensor(Tensor::random([d], Distribution::Normal(0.0, 0.02), dev)),
            oar: (0..cfg.oar_layers).map(block).collect(),
            ln_oar: LayerNormConfig::new(d).init(dev),
            track: spec.track.as_ref().map(|_| TrackProjection::new(d, dev)),
            tar_heads: Heads::new(&spec.segments, d, cfg.precision, &ordinal, dev),
            oar_heads: Heads::new(&spec.segments, d, cfg.precision, &ordinal, dev),
            spec: light,
        })
    }

    /// The frame spec.
    pub fn spec(&self) -> &BackboneSpec {
        &self.spec
    }

    /// Ego-module logits `[b, t, q, vocab]` predicting frames `1..=t` from `e` `[b, t, N, d]`.
    pub fn ego_logits(&self, e: Tensor<B, 4>, last_only: bool) -> Option<Tensor<B, 4>> {
        self.ego_with(e, last_only, &Kernels::DEFAULT)
    }

    /// [`Self::ego_logits`] with the kernels `k`.
    pub(crate) fn ego_with(&self, e: Tensor<B, 4>, last_only: bool, k: &Kernels) -> Option<Tensor<B, 4>> {
        self.ego.as_ref().map(|m| m.forward(e, last_only, k))
    }

    /// Decoded action values `[b, t, 3]` (dx, dy, dθ at bin centres) of action tokens `[b, t, q]`.
    pub fn decode_action(&self, ids: Tensor<B, 3, Int>) -> Option<Tensor<B, 3>> {
        let a = self.spec.action.as_ref()?;
        let dev = ids.device();
        let lo: Vec<f32> = a.bins.iter().map(|b| b.0 as f32).collect();
        let width: Vec<f32> = a
            .bins
            .iter()
            .map(|b| ((b.1 - b.0) / f64::from(b.2)) as f32)
            .collect();
        let lo = Tensor::<B, 1>::from_data(TensorData::new(lo, [3]), &dev).reshape([1, 1, 3]);
        let width = Tensor::<B, 1>::from_data(TensorData::new(width, [3]), &dev).reshape([1, 1, 3]);
        Some(ids.narrow(2, 0, 3).float().add_scalar(0.5) * width + lo)
    }

    /// The TAR output `h` `[b, t, N, d]` for conditioning frames `tokens` `[b, t, N]` (embedded: `e`
    /// `[b, t, N, d]`), given the embeddings `e_next` `[b, t, N, d]` and action tokens `next_action`
    /// `[b, t, q]` of the frames that follow them: frame i's action block is replaced by frame i+1's, its
    /// map is moved by that action (AMA) and its tracked slots by their velocity and that action
    /// ([`crate::track`]).
    pub fn tar(
        &self,
        tokens: Tensor<B, 3, Int>,
        e: Tensor<B, 4>,
        e_next: Tensor<B, 4>,
        next_action: Option<Tensor<B, 3, Int>>,
    ) -> Tensor<B, 4> {
        self.tar_with(tokens, e, e_next, next_action, &Kernels::DEFAULT, None)
    }

    /// [`Self::tar`] with the kernels `k`.
    fn tar_with(
        &self,
        tokens: Tensor<B, 3, Int>,
        e: Tensor<B, 4>,
        e_next: Tensor<B, 4>,
        next_action: Option<Tensor<B, 3, Int>>,
        k: &Kernels,
        ready: Option<&ReadyPoints>,
    ) -> Tensor<B, 4> {
        let [b, t, _, d] = e.dims();
        let mut x = e;
        if let Some(a) = &self.spec.action {
            let s = &self.spec.segments[a.segment];
            let next = e_next.narrow(2, s.block_start, s.block_len);
            x = x.slice_assign(
                [0..b, 0..t, s.block_start..s.block_start + s.block_len, 0..d],
                next,
            );
        }
        let act = next_action.and_then(|ids| self.decode_action(ids));
        // The tracked slots moved one frame ahead, embedded `[b·t, L, d]`, at content offset `at`.
        let moved = act
            .as_ref()
            .and_then(|a| crate::track::embed_moved(&self.spec, &self.embed, tokens, a.clone(), k));
        let track = self.track.as_ref().zip(moved);
        if let Some((proj, (at, moved))) = &track {
            x = add_at(x, *at, proj.input(moved.clone(), self.embed.precision(), k));
        }
        if let (Some(al), Some(act)) = (&self.spec.align, act) {
            let s = &self.spec.segments[al.segment];
            let map = x.clone().narrow(2, s.offset, s.tokens);
            let moved = align(
                map.reshape([b * t, s.tokens, d]),
                act.reshape([b * t, 3]),
                al.rows,
                al.cols,
                al.cell_m,
            );
            x = add_at(x, s.offset, moved);
        }
        let mut x = x + self.time.val().narrow(0, 0, t).reshape([1, t, 1, d]);
        for (i, blk) in self.tar.iter().enumerate() {
            x = blk.forward(mark(ready, x, tar_point(i)), k);
        }
        let h = umgen_ops::norm::layer_norm(&self.ln_tar, x, k);
        match track {
            // Also straight into the output, where the heads and the OAR read it.
            Some((proj, (at, moved))) => add_at(h, at, proj.output(moved, self.embed.precision(), k)),
            None => h,
        }
    }

    /// OAR input for a frame: position 0 gets the learned start vector, position p the embedding of token
    /// p − 1 (`e` `[m, N, d]`), each plus the TAR prior `h` `[m, N, d]` at p.
    pub fn oar_input(&self, e: Tensor<B, 3>, h: Tensor<B, 3>) -> Tensor<B, 3> {
        let [m, n, d] = e.dims();
        let bos = self.oar_bos.val().reshape([1, 1, d]).expand([m, 1, d]);
        Tensor::cat(vec![bos, e.narrow(1, 0, n - 1)], 1) + h
    }

    /// The frame embedding, the TAR blocks (temporal, spatial), the TAR's norm, the OAR's start vector, the
    /// OAR layers, the OAR's norm and the tracked slots' projections.
    #[allow(clippy::type_complexity)]
    pub(crate) fn parts(
        &self,
    ) -> (
        &Param<Tensor<B, 2>>,
        Vec<(&SelfBlock<B>, &SelfBlock<B>)>,
        &LayerNorm<B>,
        &Param<Tensor<B, 1>>,
        &[SelfBlock<B>],
        &LayerNorm<B>,
        Option<(&burn::nn::Linear<B>, &burn::nn::Linear<B>)>,
    ) {
        (
            &self.time,
            self.tar.iter().map(|b| (&b.temporal, &b.spatial)).collect(),
            &self.ln_tar,
            &self.oar_bos,
            &self.oar,
            &self.ln_oar,
            self.track.as_ref().map(|t| t.linears()),
        )
    }

    /// The parameters whose gradients are complete at each ready point, indexed by point: TAR block
    /// `i`'s at point `i`, then OAR block `j`'s at point `tar blocks + j`. Each block's parameters are
    /// read only by operations on the block's marked input; the rest of the model (embeddings, ego
    /// module, norms, heads) is at no point.
    pub fn ready_groups(&self) -> Vec<Vec<burn::module::ParamId>> {
        let tar = self.tar.iter().map(crate::ready::ids::<B, _>);
        tar.chain(self.oar.iter().map(crate::ready::ids::<B, _>))
            .collect()
    }

    /// Longest window of frames the TAR takes (rows of the frame embedding).
    pub fn max_frames(&self) -> usize {
        self.time.val().dims()[0]
    }

    /// Model width d.
    pub fn embed_width(&self) -> usize {
        self.time.val().dims()[1]
    }

    /// OAR layers.
    pub(crate) fn oar_layers(&self) -> usize {
        self.oar.len()
    }

    /// The learned vector of OAR position 0 `[d]`.
    pub(crate) fn oar_start(&self) -> Tensor<B, 1> {
        self.oar_bos.val()
    }

    /// The OAR blocks and final norm on one new position `[m, 1, d]` over cached earlier positions.
    pub(crate) fn oar_blocks_step(
        &self,
        x: Tensor<B, 3>,
        caches: &mut [Option<(Tensor<B, 4>, Tensor<B, 4>)>],
        pos: usize,
        hidden: Tensor<B, 4>,
    ) -> Tensor<B, 3> {
        let mut x = x;
        for (blk, cache) in self.oar.iter().zip(caches.iter_mut()) {
            x = blk.forward_step(x, cache, pos, hidden.clone());
        }
        self.ln_oar.forward(x)
    }

    /// OAR output `[m, L, d]` of inputs `[m, L, d]` (causal).
    pub fn oar(&self, w: Tensor<B, 3>) -> Tensor<B, 3> {
        self.oar_with(w, &Kernels::DEFAULT, None)
    }

    /// [`Self::oar`] with the kernels `k`.
    fn oar_with(&self, w: Tensor<B, 3>, k: &Kernels, ready: Option<&ReadyPoints>) -> Tensor<B, 3> {
        let mut x = w;
        for (i, blk) in self.oar.iter().enumerate() {
            x = blk.forward(mark(ready, x, oar_point(self.tar.len(), i)), true, k);
        }
        umgen_ops::norm::layer_norm(&self.ln_oar, x, k)
    }

    /// The teacher-forced pass over windows `[b, t + 1, N]`: frames `0..t` condition, frame `i + 1` is
    /// the target of frame `i`. With `prior_drop` > 0, each predicted frame's OAR input goes without its
    /// TAR prior with that probability, drawn on the device from the backend's seed. Every operation runs
    /// on the kernels `k`. With `ready`, each TAR and OAR block's input is marked as that block's point
    /// (`ready.rs`).
    pub(crate) fn teacher_forced(
        &self,
        tokens: Tensor<B, 3, Int>,
        prior_drop: f64,
        k: &Kernels,
        ready: Option<&ReadyPoints>,
    ) -> Result<Forward<B>> {
        let [b, f, n] = tokens.dims();
        if f < 2 || n != self.spec.n {
            return Err(BackboneError::Input(format!(
                "windows of {f} frames × {n} tokens; need ≥ 2 frames × {}",
                self.spec.n
            )));
        }
        let t = f - 1;
        let e_all = self.embed.forward(tokens.clone(), k);
        let (e, e_next) = (e_all.clone().narrow(1, 0, t), e_all.narrow(1, 1, t));
        let target = tokens.clone().narrow(1, 1, t);
        let next_action = self.spec.action.as_ref().map(|a| {
            let s = &self.spec.segments[a.segment];
            target.clone().narrow(2, s.offset, s.tokens)
        });
        let h = self.tar_with(
            tokens.narrow(1, 0, t),
            e.clone(),
            e_next.clone(),
            next_action.clone(),
            k,
            ready,
        );
        let d = h.dims()[3];
        let prior = h.clone().reshape([b * t, n, d]);
        let prior = if prior_drop > 0.0 {
            let keep = Tensor::<B, 3>::random(
                [b * t, 1, 1],
                Distribution::Bernoulli(1.0 - prior_drop),
                &prior.device(),
            );
            prior * keep
        } else {
            prior
        };
        let o = self.oar_with(self.oar_input(e_next.reshape([b * t, n, d]), prior), k, ready);
        Ok(Forward {
            e,
            h: h.reshape([b * t, n, d]),
            o,
            target: target.reshape([b * t, n]),
            next_action,
        })
    }
}

/// What [`Backbone::teacher_forced`] computes for windows of `b` × (`t` + 1) frames of N tokens.
pub(crate) struct Forward<B: Backend> {
    /// Embeddings of the conditioning frames `[b, t, N, d]`.
    pub e: Tensor<B, 4>,
    /// The TAR output `[b·t, N, d]`.
    pub h: Tensor<B, 3>,
    /// The OAR output `[b·t, N, d]`.
    pub o: Tensor<B, 3>,
    /// The target frames `[b·t, N]`.
    pub target: Tensor<B, 2, Int>,
    /// The target frames' action tokens `[b, t, q]`, when the model has an ego action.
    pub next_action: Option<Tensor<B, 3, Int>>,
}

/// `x`, marked as `point` where there are points.
fn mark<B: Backend, const D: usize>(
    ready: Option<&ReadyPoints>,
    x: Tensor<B, D>,
    point: usize,
) -> Tensor<B, D> {
    match ready {
        Some(r) => r.mark(x, point),
        None => x,
    }
}

/// `x` `[b, t, N, d]` with `y` `[b·t, L, d]` added at positions `at..at + L`.
fn add_at<B: Backend>(x: Tensor<B, 4>, at: usize, y: Tensor<B, 3>) -> Tensor<B, 4> {
    let [b, t, _, d] = x.dims();
    let l = y.dims()[1];
    let own = x.clone().narrow(2, at, l);
    x.slice_assign([0..b, 0..t, at..at + l, 0..d], own + y.reshape([b, t, l, d]))
}
