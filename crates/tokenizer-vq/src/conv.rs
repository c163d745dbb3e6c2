//! Convolutions as one matrix product each (im2col) on CUDA.
//!
//! Without autotuning, burn-cuda runs every convolution through its direct kernel, and its backward pass
//! through a direct transposed convolution: on an H200 the `small` map and image tokenizers trained at
//! 1.0–1.4 rasters/s that way, almost all of it in those kernels. Here the `kh × kw` shifted views of the
//! padded input are stacked into columns `[b, c·kh·kw, ho·wo]` and multiplied by the weight `[o, c·kh·kw]`,
//! so the forward pass and both gradients are batched matmuls (tensor cores on CUDA) plus copies. The
//! cost is memory: the columns hold `kh·kw` copies of the input and autodiff keeps them for the weight
//! gradient.
//!
//! On the CPU backends burn's own convolution is faster (`tiny` tokenizers on this project's 2-core CI
//! machine: map 9.0 against 4.5 rasters/s, image 14 against 12), so [`conv2d`] takes the matrix products
//! only on `Cuda` and `Autodiff<Cuda>`. Parameters stay those of burn's [`Conv2d`] either way, so
//! checkpoints and trained tokenizers do not depend on the path.

use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::backend::Backend;
use burn::tensor::ops::PadMode;
use burn::tensor::{Tensor, s};

/// `conv.forward(x)`: as matrix products on CUDA backends ([`gemm_conv2d`]), burn's convolution elsewhere.
pub fn conv2d<B: Backend>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    if prefers_gemm::<B>() {
        gemm_conv2d(conv, x)
    } else {
        conv.forward(x)
    }
}

/// Whether `B` is burn-cuda, with or without autodiff.
fn prefers_gemm<B: Backend>() -> bool {
    gemm_backends().contains(&std::any::TypeId::of::<B>())
}

fn gemm_backends() -> Vec<std::any::TypeId> {
    #[cfg(feature = "cuda")]
    {
        use burn::backend::autodiff::checkpoint::strategy::BalancedCheckpointing;
        use burn::backend::{Autodiff, Cuda};
        use std::any::TypeId;
        vec![
            TypeId::of::<Cuda>(),
            TypeId::of::<Autodiff<Cuda>>(),
            TypeId::of::<Autodiff<Cuda, BalancedCheckpointing>>(),
        ]
    }
    #[cfg(not(feature = "cuda"))]
    Vec::new()
}

/// `conv.forward(x)`, computed as an im2col matrix product where the convolution allows it (one group,
/// no dilation, explicit or no padding); otherwise burn's own convolution.
pub fn gemm_conv2d<B: Backend>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let (top, left, bottom, right) = match conv.padding {
        PaddingConfig2d::Valid => (0, 0, 0, 0),
        PaddingConfig2d::Explicit(t, l, b, r) => (t, l, b, r),
        PaddingConfig2d::Same => return conv.forward(x),
    };
    if conv.groups != 1 || conv.dilation != [1, 1] {
        return conv.forward(x);
    }
    let [b, c, h, w] = x.dims();
    let [kh, kw] = conv.kernel_size;
    let [sh, sw] = conv.stride;
    let (hp, wp) = (h + top + bottom, w + left + right);
    if hp < kh || wp < kw || sh == 0 || sw == 0 {
        // burn reports the shape error.
        return conv.forward(x);
    }
    let (ho, wo) = ((hp - kh) / sh + 1, (wp - kw) / sw + 1);
    let weight = conv.weight.val();
    let o = weight.dims()[0];
    let cols = if kh == 1 && kw == 1 && (top, left, bottom, right) == (0, 0, 0, 0) && sh == 1 && sw == 1 {
        x.reshape([b, c, h * w])
    } else {
        let x = if (top, left, bottom, right) == (0, 0, 0, 0) {
            x
        } else {
            x.pad((left, right, top, bottom), PadMode::Constant(0.0))
        };
        // One shifted (and strided) view per kernel tap, in the weight's (c, i, j) order.
        let taps: Vec<Tensor<B, 4>> = (0..kh)
            .flat_map(|i| (0..kw).map(move |j| (i, j)))
            .map(|(i, j)| {
                x.clone().slice(s![
                    ..,
                    ..,
                    i..i + sh * (ho - 1) + 1;sh,
                    j..j + sw * (wo - 1) + 1;sw
                ])
            })
            .collect();
        Tensor::stack::<5>(taps, 2).reshape([b, c * kh * kw, ho * wo])
    };
    let weight = weight.reshape([1, o, c * kh * kw]).expand([b, o, c * kh * kw]);
    let y = weight.matmul(cols);
    let y = match &conv.bias {
        Some(bias) => y + bias.val().reshape([1, o, 1]),
        None => y,
    };
    y.reshape([b, o, ho, wo])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, Flex};
    use burn::nn::conv::Conv2dConfig;
    use burn::tensor::{Distribution, Tolerance};

    type A = Autodiff<Flex>;

    fn check(cin: usize, cout: usize, k: usize, stride: usize, pad: PaddingConfig2d, hw: [usize; 2]) {
        let dev = Default::default();
        let conv: Conv2d<A> = Conv2dConfig::new([cin, cout], [k, k])
            .with_stride([stride, stride])
            .with_padding(pad.clone())
            .init(&dev);
        let x = Tensor::<A, 4>::random([2, cin, hw[0], hw[1]], Distribution::Normal(0.0, 1.0), &dev)
            .require_grad();
        let reference = conv.forward(x.clone());
        let ours = gemm_conv2d(&conv, x.clone());
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
        // The tokenizer's convolutions: 3×3 same-size, stride-2 down with right/bottom padding, 1×1.
        check(3, 5, 3, 1, PaddingConfig2d::Explicit(1, 1, 1, 1), [7, 6]);
        check(4, 4, 3, 2, PaddingConfig2d::Explicit(0, 0, 1, 1), [8, 10]);
        check(4, 6, 1, 1, PaddingConfig2d::Valid, [5, 3]);
        // Odd sizes with stride 2, asymmetric padding, a 5×5 kernel.
        check(2, 3, 3, 2, PaddingConfig2d::Explicit(0, 0, 1, 1), [9, 7]);
        check(2, 3, 5, 1, PaddingConfig2d::Explicit(2, 1, 2, 3), [6, 8]);
    }

    #[test]
    fn unsupported_settings_fall_back_to_burn() {
        let dev = Default::default();
        let conv: Conv2d<A> = Conv2dConfig::new([2, 4], [3, 3])
            .with_padding(PaddingConfig2d::Same)
            .with_dilation([2, 2])
            .init(&dev);
        let x = Tensor::<A, 4>::random([1, 2, 9, 9], Distribution::Normal(0.0, 1.0), &dev);
        gemm_conv2d(&conv, x.clone())
            .into_data()
            .assert_approx_eq::<f32>(&conv.forward(x).into_data(), Tolerance::absolute(1e-6));
    }

    #[test]
    fn cpu_backends_keep_burns_convolution() {
        assert!(!prefers_gemm::<A>());
        assert!(!prefers_gemm::<Flex>());
    }
}
