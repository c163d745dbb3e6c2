//! Convolutions as one matrix product each (im2col) on CUDA.
//!
//! Without autotuning, burn-cuda runs every convolution through its direct kernel, and its backward pass
//! through a direct transposed convolution: on an H200 the `small` map and image tokenizers trained at
//! 1.0–1.4 rasters/s that way, almost all of it in those kernels. Here the `kh × kw` shifted views of the
//! padded input are stacked into columns `[b, c·kh·kw, ho·wo]` and multiplied by the weight `[o, c·kh·kw]`.
//! In training the product is one autodiff operation (`conv_op.rs`) whose backward pass rebuilds the
//! columns instead of keeping them: both gradients are matmuls, and the memory kept per convolution is its
//! input, as for burn's own convolution, not `kh·kw` copies of it.
//!
//! On the CPU backends burn's own convolution is faster (`tiny` tokenizers on this project's 2-core CI
//! machine: map 9.0 against 4.5 rasters/s, image 14 against 12), so [`conv2d`] takes the matrix products
//! only on `Cuda` and `Autodiff<Cuda>`. Parameters stay those of burn's [`Conv2d`] either way, so
//! checkpoints and trained tokenizers do not depend on the path.

use crate::conv_op::gemm_autodiff_for;
use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::backend::Backend;
use burn::tensor::ops::PadMode;
use burn::tensor::{Tensor, s};

/// `conv.forward(x)`: as matrix products on CUDA backends, burn's convolution elsewhere.
pub fn conv2d<B: Backend>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let Some(g) = Geometry::of(conv, x.dims()) else {
        return conv.forward(x);
    };
    let y = if let Some(op) = gemm_autodiff_for::<B>() {
        op(x, conv.weight.val(), g)
    } else if plain_gemm_backends().contains(&std::any::TypeId::of::<B>()) {
        product(conv.weight.val(), columns(x, &g), &g)
    } else {
        return conv.forward(x);
    };
    with_bias(conv, y)
}

fn with_bias<B: Backend>(conv: &Conv2d<B>, y: Tensor<B, 4>) -> Tensor<B, 4> {
    match &conv.bias {
        Some(bias) => {
            let o = bias.dims()[0];
            y + bias.val().reshape([1, o, 1, 1])
        }
        None => y,
    }
}

/// Backends without autodiff that take the matrix products (inference on CUDA).
fn plain_gemm_backends() -> Vec<std::any::TypeId> {
    #[cfg(feature = "cuda")]
    {
        vec![std::any::TypeId::of::<burn::backend::Cuda>()]
    }
    #[cfg(not(feature = "cuda"))]
    Vec::new()
}

/// The shape of one convolution: kernel, stride, padding (top, left, bottom, right), input and output
/// sizes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Geometry {
    kernel: [usize; 2],
    stride: [usize; 2],
    pad: [usize; 4],
    input: [usize; 4],
    out: [usize; 2],
}

impl Geometry {
    /// `conv` on an input of `dims`, if the matrix-product path supports it: one group, no dilation,
    /// explicit or no padding, a kernel that fits the padded input.
    pub fn of<B: Backend>(conv: &Conv2d<B>, dims: [usize; 4]) -> Option<Self> {
        let pad = match conv.padding {
            PaddingConfig2d::Valid => [0; 4],
            PaddingConfig2d::Explicit(t, l, b, r) => [t, l, b, r],
            PaddingConfig2d::Same => return None,
        };
        let ([kh, kw], [sh, sw]) = (conv.kernel_size, conv.stride);
        let (hp, wp) = (dims[2] + pad[0] + pad[2], dims[3] + pad[1] + pad[3]);
        let valid = conv.groups == 1 && conv.dilation == [1, 1] && sh > 0 && sw > 0 && hp >= kh && wp >= kw;
        valid.then(|| Self {
            kernel: [kh, kw],
            stride: [sh, sw],
            pad,
            input: dims,
            out: [(hp - kh) / sh + 1, (wp - kw) / sw + 1],
        })
    }

    /// For stride 1 (and padding below the kernel size on every side): the geometry in which convolving
    /// the output gradient `[b, out_channels, ho, wo]` with the flipped, transposed kernel gives the input
    /// gradient, so that the backward pass gathers columns like the forward pass instead of folding them.
    pub(crate) fn transposed(&self, out_channels: usize) -> Option<Self> {
        let ([kh, kw], [t, l, b, r]) = (self.kernel, self.pad);
        if self.stride != [1, 1] || t >= kh || b >= kh || l >= kw || r >= kw {
            return None;
        }
        let [n, _, h, w] = self.input;
        Some(Self {
            kernel: self.kernel,
            stride: [1, 1],
            pad: [kh - 1 - t, kw - 1 - l, kh - 1 - b, kw - 1 - r],
            input: [n, out_channels, self.out[0], self.out[1]],
            out: [h, w],
        })
    }

    /// Input size `[b, c, h, w]`.
    pub(crate) fn input(&self) -> [usize; 4] {
        self.input
    }

    /// Output size `[ho, wo]`.
    pub(crate) fn output(&self) -> [usize; 2] {
        self.out
    }

    fn taps(&self) -> usize {
        self.kernel[0] * self.kernel[1]
    }

    /// Whether the columns are the input itself (a 1×1 kernel, stride 1, no padding).
    fn pointwise(&self) -> bool {
        self.kernel == [1, 1] && self.stride == [1, 1] && self.pad == [0; 4]
    }

    /// The padded input's positions read by kernel tap `(i, j)`, one per output position.
    fn window(&self, i: usize, j: usize) -> [burn::tensor::Slice; 4] {
        let ([sh, sw], [ho, wo]) = (self.stride, self.out);
        s![.., .., i..i + sh * (ho - 1) + 1;sh, j..j + sw * (wo - 1) + 1;sw]
    }

    fn padded(&self) -> [usize; 4] {
        let [b, c, h, w] = self.input;
        [b, c, h + self.pad[0] + self.pad[2], w + self.pad[1] + self.pad[3]]
    }
}

/// The columns `[b, c·kh·kw, ho·wo]` of `x`: one shifted (strided) view of the padded input per kernel
/// tap, in the weight's (c, i, j) order.
pub(crate) fn columns<B: Backend>(x: Tensor<B, 4>, g: &Geometry) -> Tensor<B, 3> {
    let [b, c, h, w] = g.input;
    let [ho, wo] = g.out;
    if g.pointwise() {
        return x.reshape([b, c, h * w]);
    }
    let [top, left, bottom, right] = g.pad;
    let x = if g.pad == [0; 4] {
        x
    } else {
        x.pad((left, right, top, bottom), PadMode::Constant(0.0))
    };
    let taps: Vec<Tensor<B, 4>> = (0..g.kernel[0])
        .flat_map(|i| (0..g.kernel[1]).map(move |j| (i, j)))
        .map(|(i, j)| x.clone().slice(g.window(i, j)))
        .collect();
    Tensor::stack::<5>(taps, 2).reshape([b, c * g.taps(), ho * wo])
}

/// The adjoint of [`columns`]: column gradients `[b, c·kh·kw, ho·wo]` summed back onto the input
/// `[b, c, h, w]` (each input position receives the gradient of every tap that read it).
pub(crate) fn fold<B: Backend>(cols: Tensor<B, 3>, g: &Geometry) -> Tensor<B, 4> {
    let [b, c, h, w] = g.input;
    let [ho, wo] = g.out;
    if g.pointwise() {
        return cols.reshape([b, c, h, w]);
    }
    let cols = cols.reshape([b, c, g.taps(), ho * wo]);
    let mut padded = Tensor::<B, 4>::zeros(g.padded(), &cols.device());
    for i in 0..g.kernel[0] {
        for j in 0..g.kernel[1] {
            let tap = cols
                .clone()
                .narrow(2, i * g.kernel[1] + j, 1)
                .reshape([b, c, ho, wo]);
            let window = g.window(i, j);
            padded = padded.clone().slice_assign(window, padded.slice(window) + tap);
        }
    }
    let [top, left, ..] = g.pad;
    padded.slice([0..b, 0..c, top..top + h, left..left + w])
}

/// `weight · columns` per batch entry: `[b, o, ho, wo]`.
pub(crate) fn product<B: Backend>(weight: Tensor<B, 4>, cols: Tensor<B, 3>, g: &Geometry) -> Tensor<B, 4> {
    let (b, o, k) = (g.input[0], weight.dims()[0], cols.dims()[1]);
    let weight = weight.reshape([1, o, k]).expand([b, o, k]);
    weight.matmul(cols).reshape([b, o, g.out[0], g.out[1]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conv_op::gemm_autodiff;
    use burn::backend::autodiff::checkpoint::strategy::NoCheckpointing;
    use burn::backend::{Autodiff, Flex};
    use burn::nn::conv::Conv2dConfig;
    use burn::tensor::{Distribution, Tolerance};

    type A = Autodiff<Flex>;

    /// The two matrix-product paths on the CPU training backend.
    #[derive(Debug, Clone, Copy)]
    enum Path {
        /// Columns and matmul differentiated op by op.
        Plain,
        /// The autodiff operation that rebuilds the columns in the backward pass.
        Op,
    }

    fn gemm(path: Path, conv: &Conv2d<A>, x: Tensor<A, 4>) -> Tensor<A, 4> {
        let g = Geometry::of(conv, x.dims()).expect("a supported convolution");
        let y = match path {
            Path::Plain => product(conv.weight.val(), columns(x, &g), &g),
            Path::Op => gemm_autodiff::<Flex, NoCheckpointing>(x, conv.weight.val(), g),
        };
        with_bias(conv, y)
    }

    fn check(
        path: Path,
        cin: usize,
        cout: usize,
        k: usize,
        stride: usize,
        pad: PaddingConfig2d,
        hw: [usize; 2],
    ) {
        let dev = Default::default();
        let conv: Conv2d<A> = Conv2dConfig::new([cin, cout], [k, k])
            .with_stride([stride, stride])
            .with_padding(pad.clone())
            .init(&dev);
        let x = Tensor::<A, 4>::random([2, cin, hw[0], hw[1]], Distribution::Normal(0.0, 1.0), &dev)
            .require_grad();
        let reference = conv.forward(x.clone());
        let ours = gemm(path, &conv, x.clone());
        assert_eq!(ours.dims(), reference.dims(), "{pad:?} stride {stride} k {k}");
        ours.clone()
            .into_data()
            .assert_approx_eq::<f32>(&reference.clone().into_data(), Tolerance::absolute(1e-4));
        // Every output element was written: the two paths agree on a poisoned-free random input above,
        // and no NaN slipped through.
        assert!(!ours.clone().is_nan().any().into_scalar(), "NaN in the output");
        // Gradients against the same upstream gradient: a random weighting of the outputs.
        let up = Tensor::<A, 4>::random(reference.dims(), Distribution::Normal(0.0, 1.0), &dev);
        let g_ref = (reference * up.clone()).sum().backward();
        let g_ours = (ours * up).sum().backward();
        let close = |ours: Tensor<Flex, 4>, reference: Tensor<Flex, 4>, what: &str| {
            let scale = reference.clone().abs().max().into_scalar().max(1.0);
            let err = (ours - reference).abs().max().into_scalar() / scale;
            assert!(
                err < 1e-4,
                "{what}: relative error {err} (k {k}, stride {stride}, {pad:?})"
            );
        };
        let grad4 = |t: &Tensor<A, 4>, g| t.grad(g).expect("a gradient");
        close(grad4(&x, &g_ours), grad4(&x, &g_ref), "input gradient");
        let weight = conv.weight.val();
        close(grad4(&weight, &g_ours), grad4(&weight, &g_ref), "weight gradient");
        let bias = conv.bias.as_ref().expect("bias").val();
        let (gb, gb_ref) = (
            bias.grad(&g_ours).expect("bias gradient"),
            bias.grad(&g_ref).expect("bias"),
        );
        close(
            gb.reshape([1, 1, 1, cout]),
            gb_ref.reshape([1, 1, 1, cout]),
            "bias gradient",
        );
    }

    #[test]
    fn matches_burn_convolution_forward_and_gradients() {
        for path in [Path::Plain, Path::Op] {
            // The tokenizer's convolutions: 3×3 same-size, stride-2 down with right/bottom padding, 1×1.
            check(path, 3, 5, 3, 1, PaddingConfig2d::Explicit(1, 1, 1, 1), [7, 6]);
            check(path, 4, 4, 3, 2, PaddingConfig2d::Explicit(0, 0, 1, 1), [8, 10]);
            check(path, 4, 6, 1, 1, PaddingConfig2d::Valid, [5, 3]);
            // Odd sizes with stride 2, asymmetric padding, a 5×5 kernel.
            check(path, 2, 3, 3, 2, PaddingConfig2d::Explicit(0, 0, 1, 1), [9, 7]);
            check(path, 2, 3, 5, 1, PaddingConfig2d::Explicit(2, 1, 2, 3), [6, 8]);
        }
    }

    #[test]
    fn unsupported_settings_are_not_taken() {
        let dev = Default::default();
        let same: Conv2d<A> = Conv2dConfig::new([2, 4], [3, 3])
            .with_padding(PaddingConfig2d::Same)
            .init(&dev);
        let dilated: Conv2d<A> = Conv2dConfig::new([2, 4], [3, 3]).with_dilation([2, 2]).init(&dev);
        let grouped: Conv2d<A> = Conv2dConfig::new([2, 4], [3, 3]).with_groups(2).init(&dev);
        for conv in [&same, &dilated, &grouped] {
            assert_eq!(Geometry::of(conv, [1, 2, 9, 9]), None, "{conv:?}");
        }
        let plain: Conv2d<A> = Conv2dConfig::new([2, 4], [3, 3]).init(&dev);
        assert!(Geometry::of(&plain, [1, 2, 9, 9]).is_some());
        // A kernel larger than the padded input: burn reports that error, not this path.
        assert_eq!(Geometry::of(&plain, [1, 2, 2, 9]), None);
    }

    #[test]
    fn cpu_backends_keep_burns_convolution() {
        assert!(gemm_autodiff_for::<A>().is_none());
        assert!(!plain_gemm_backends().contains(&std::any::TypeId::of::<Flex>()));
        // So conv2d is burn's convolution there, exactly.
        let dev = Default::default();
        let conv: Conv2d<A> = Conv2dConfig::new([2, 3], [3, 3]).init(&dev);
        let x = Tensor::<A, 4>::random([1, 2, 6, 6], Distribution::Normal(0.0, 1.0), &dev);
        assert_eq!(conv2d(&conv, x.clone()).into_data(), conv.forward(x).into_data());
    }
}
