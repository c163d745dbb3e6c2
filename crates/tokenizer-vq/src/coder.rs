//! The encoder (raster → continuous grid) and the decoder (code vectors → raster).

use crate::blocks::{Attention, Down, NormAct, ResBlock, Up, conv3};
use crate::config::VqConfig;
use crate::conv::conv2d;
use burn::module::Module;
use burn::nn::conv::Conv2d;
use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// One resolution level: residual blocks, then a resampling step (except at the end).
#[derive(Module, Debug)]
pub struct EncoderLevel<B: Backend> {
    blocks: Vec<ResBlock<B>>,
    down: Option<Down<B>>,
}

/// Residual blocks with an optional attention block between them.
#[derive(Module, Debug)]
pub struct Middle<B: Backend> {
    first: ResBlock<B>,
    attention: Option<Attention<B>>,
    second: ResBlock<B>,
}

impl<B: Backend> Middle<B> {
    fn new(c: usize, cfg: &VqConfig, dev: &B::Device) -> Self {
        Self {
            first: ResBlock::new(c, c, cfg.groups, dev),
            attention: cfg.attention.then(|| Attention::new(c, cfg.groups, dev)),
            second: ResBlock::new(c, c, cfg.groups, dev),
        }
    }

    fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let x = self.first.forward(x);
        let x = match &self.attention {
            Some(a) => a.forward(x),
            None => x,
        };
        self.second.forward(x)
    }
}

/// Raster `[B, channels, H, W]` → `[B, z_channels, H/f, W/f]`.
#[derive(Module, Debug)]
pub struct Encoder<B: Backend> {
    conv_in: Conv2d<B>,
    levels: Vec<EncoderLevel<B>>,
    middle: Middle<B>,
    out_act: NormAct<B>,
    conv_out: Conv2d<B>,
}

impl<B: Backend> Encoder<B> {
    /// An encoder of the configured size.
    pub fn new(cfg: &VqConfig, dev: &B::Device) -> Self {
        let mut cin = cfg.base;
        let n = cfg.mult.len();
        let levels = cfg
            .mult
            .iter()
            .enumerate()
            .map(|(i, m)| {
                let c = cfg.base * m;
                let blocks = (0..cfg.res_blocks)
                    .map(|_| {
                        let b = ResBlock::new(cin, c, cfg.groups, dev);
                        cin = c;
                        b
                    })
                    .collect();
                EncoderLevel {
                    blocks,
                    down: (i + 1 < n).then(|| Down::new(c, dev)),
                }
            })
            .collect();
        Self {
            conv_in: conv3(cfg.channels, cfg.base, dev),
            levels,
            middle: Middle::new(cin, cfg, dev),
            out_act: NormAct::new(cfg.groups, cin, dev),
            conv_out: conv3(cin, cfg.z_channels, dev),
        }
    }

    /// Applies it.
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let mut h = conv2d(&self.conv_in, x);
        for level in &self.levels {
            for b in &level.blocks {
                h = b.forward(h);
            }
            if let Some(d) = &level.down {
                h = d.forward(h);
            }
        }
        conv2d(&self.conv_out, self.out_act.forward(self.middle.forward(h)))
    }
}

/// One decoder level: residual blocks, then upsampling (except at the end).
#[derive(Module, Debug)]
pub struct DecoderLevel<B: Backend> {
    blocks: Vec<ResBlock<B>>,
    up: Option<Up<B>>,
}

/// `[B, embed_dim, h, w]` → raster `[B, channels, h·f, w·f]` (logits for binary output).
#[derive(Module, Debug)]
pub struct Decoder<B: Backend> {
    conv_in: Conv2d<B>,
    middle: Middle<B>,
    levels: Vec<DecoderLevel<B>>,
    out_act: NormAct<B>,
    conv_out: Conv2d<B>,
}

impl<B: Backend> Decoder<B> {
    /// A decoder mirroring the encoder of `cfg`.
    pub fn new(cfg: &VqConfig, dev: &B::Device) -> Self {
        let top = cfg.base * cfg.mult.last().copied().unwrap_or(1);
        let mut cin = top;
        let levels = cfg
            .mult
            .iter()
            .enumerate()
            .rev()
            .map(|(i, m)| {
                let c = cfg.base * m;
                let blocks = (0..=cfg.res_blocks)
                    .map(|_| {
                        let b = ResBlock::new(cin, c, cfg.groups, dev);
                        cin = c;
                        b
                    })
                    .collect();
                DecoderLevel {
                    blocks,
                    up: (i > 0).then(|| Up::new(c, dev)),
                }
            })
            .collect();
        Self {
            conv_in: conv3(cfg.embed_dim, top, dev),
            middle: Middle::new(top, cfg, dev),
            levels,
            out_act: NormAct::new(cfg.groups, cin, dev),
            conv_out: conv3(cin, cfg.channels, dev),
        }
    }

    /// Applies it.
    pub fn forward(&self, z: Tensor<B, 4>) -> Tensor<B, 4> {
        let mut h = self.middle.forward(conv2d(&self.conv_in, z));
        for level in &self.levels {
            for b in &level.blocks {
                h = b.forward(h);
            }
            if let Some(u) = &level.up {
                h = u.forward(h);
            }
        }
        conv2d(&self.conv_out, self.out_act.forward(h))
    }
}
