//! Building blocks: residual blocks, down/upsampling, spatial self-attention.

use crate::conv::conv2d;
use crate::norm::group_norm;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{GroupNorm, GroupNormConfig, PaddingConfig2d};
use burn::tensor::Tensor;
use burn::tensor::activation::{silu, softmax};
use burn::tensor::backend::Backend;

/// A 3×3 convolution that keeps the size.
pub fn conv3<B: Backend>(cin: usize, cout: usize, dev: &B::Device) -> Conv2d<B> {
    Conv2dConfig::new([cin, cout], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init(dev)
}

/// A 1×1 convolution.
pub fn conv1<B: Backend>(cin: usize, cout: usize, dev: &B::Device) -> Conv2d<B> {
    Conv2dConfig::new([cin, cout], [1, 1]).init(dev)
}

/// GroupNorm then SiLU.
#[derive(Module, Debug)]
pub struct NormAct<B: Backend> {
    norm: GroupNorm<B>,
}

impl<B: Backend> NormAct<B> {
    /// Over `c` channels in `groups` groups.
    pub fn new(groups: usize, c: usize, dev: &B::Device) -> Self {
        Self {
            norm: GroupNormConfig::new(groups, c).with_epsilon(1e-6).init(dev),
        }
    }

    /// Applies it.
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        silu(group_norm(&self.norm, x))
    }
}

/// `x + conv(act(norm(conv(act(norm(x))))))`, with a 1×1 projection when the width changes.
#[derive(Module, Debug)]
pub struct ResBlock<B: Backend> {
    act1: NormAct<B>,
    conv1: Conv2d<B>,
    act2: NormAct<B>,
    conv2: Conv2d<B>,
    skip: Option<Conv2d<B>>,
}

impl<B: Backend> ResBlock<B> {
    /// A block from `cin` to `cout` channels.
    pub fn new(cin: usize, cout: usize, groups: usize, dev: &B::Device) -> Self {
        Self {
            act1: NormAct::new(groups, cin, dev),
            conv1: conv3(cin, cout, dev),
            act2: NormAct::new(groups, cout, dev),
            conv2: conv3(cout, cout, dev),
            skip: (cin != cout).then(|| conv1(cin, cout, dev)),
        }
    }

    /// Applies it.
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let h = conv2d(&self.conv1, self.act1.forward(x.clone()));
        let h = conv2d(&self.conv2, self.act2.forward(h));
        match &self.skip {
            Some(s) => conv2d(s, x) + h,
            None => x + h,
        }
    }
}

/// Halves height and width: a stride-2 3×3 convolution padded by one pixel at the right and bottom.
#[derive(Module, Debug)]
pub struct Down<B: Backend> {
    conv: Conv2d<B>,
}

impl<B: Backend> Down<B> {
    /// Over `c` channels.
    pub fn new(c: usize, dev: &B::Device) -> Self {
        let conv = Conv2dConfig::new([c, c], [3, 3])
            .with_stride([2, 2])
            .with_padding(PaddingConfig2d::Explicit(0, 0, 1, 1))
            .init(dev);
        Self { conv }
    }

    /// Applies it.
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        conv2d(&self.conv, x)
    }
}

/// Doubles height and width: nearest-neighbour repeat, then a 3×3 convolution.
#[derive(Module, Debug)]
pub struct Up<B: Backend> {
    conv: Conv2d<B>,
}

impl<B: Backend> Up<B> {
    /// Over `c` channels.
    pub fn new(c: usize, dev: &B::Device) -> Self {
        Self {
            conv: conv3(c, c, dev),
        }
    }

    /// Applies it.
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let [b, c, h, w] = x.dims();
        // Repeat by broadcasting: [b, c, h, 1, w, 1] → [b, c, h, 2, w, 2] → [b, c, 2h, 2w].
        let x = x
            .reshape([b, c, h, 1, w, 1])
            .expand([b, c, h, 2, w, 2])
            .reshape([b, c, 2 * h, 2 * w]);
        conv2d(&self.conv, x)
    }
}

/// Single-head self-attention over all positions of a feature map.
#[derive(Module, Debug)]
pub struct Attention<B: Backend> {
    norm: GroupNorm<B>,
    qkv: Conv2d<B>,
    proj: Conv2d<B>,
}

impl<B: Backend> Attention<B> {
    /// Over `c` channels.
    pub fn new(c: usize, groups: usize, dev: &B::Device) -> Self {
        Self {
            norm: GroupNormConfig::new(groups, c).with_epsilon(1e-6).init(dev),
            qkv: conv1(c, 3 * c, dev),
            proj: conv1(c, c, dev),
        }
    }

    /// Applies it (residual included).
    pub fn forward(&self, x: Tensor<B, 4>) -> Tensor<B, 4> {
        let [b, c, h, w] = x.dims();
        let qkv = conv2d(&self.qkv, group_norm(&self.norm, x.clone())).reshape([b, 3, c, h * w]);
        let q = qkv.clone().narrow(1, 0, 1).reshape([b, c, h * w]).swap_dims(1, 2);
        let k = qkv.clone().narrow(1, 1, 1).reshape([b, c, h * w]);
        let v = qkv.narrow(1, 2, 1).reshape([b, c, h * w]).swap_dims(1, 2);
        let att = softmax(q.matmul(k).div_scalar((c as f64).sqrt()), 2);
        let y = att.matmul(v).swap_dims(1, 2).reshape([b, c, h, w]);
        x + conv2d(&self.proj, y)
    }
}
