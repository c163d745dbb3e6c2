//! Attention heads as a tensor axis: `[b, l, h·dh]` ↔ `[b, h, l, dh]`, and a kv product's two halves.

use burn::tensor::Tensor;
use burn::tensor::backend::Backend;

/// `[b, l, h·dh]` → `[b, h, l, dh]`.
pub fn split_heads<B: Backend>(x: Tensor<B, 3>, heads: usize) -> Tensor<B, 4> {
    let [b, l, d] = x.dims();
    x.reshape([b, l, heads, d / heads]).swap_dims(1, 2)
}

/// `[b, h, l, dh]` → `[b, l, h·dh]`.
pub fn merge_heads<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 3> {
    let [b, h, l, dh] = x.dims();
    x.swap_dims(1, 2).reshape([b, l, h * dh])
}

/// Keys and values of `kv` `[b, l, 2d]`, split into `heads` heads `[b, heads, l, d / heads]` (views).
pub fn split_kv<B: Backend>(kv: Tensor<B, 3>, heads: usize) -> (Tensor<B, 4>, Tensor<B, 4>) {
    let d = kv.dims()[2] / 2;
    (
        split_heads(kv.clone().narrow(2, 0, d), heads),
        split_heads(kv.narrow(2, d, d), heads),
    )
}
