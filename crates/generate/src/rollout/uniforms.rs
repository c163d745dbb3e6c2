//! The uniform numbers of a frame's device draws, uploaded a block of positions at a time.
//!
//! A device draw needs `m × width` uniform numbers from the host's seeded generator. Uploading them at
//! every position is one host-to-device copy per decoded token; here they are drawn in position order
//! from a generator of their own and uploaded for as many of the coming positions as fit in a block, so
//! that the draws are the same whatever the block size.

use crate::device_draw::uniforms;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};
use rand::rngs::StdRng;

/// Uniform numbers for the device-drawn positions of one frame, in order.
pub(super) struct UniformBlocks<B: Backend> {
    /// Numbers each coming position takes (`m × width`), in order.
    sizes: Vec<usize>,
    /// The next position to hand out.
    next: usize,
    /// The uploaded block: its first position and, per position, its offset in the block.
    block: Option<(Tensor<B, 1>, usize, Vec<usize>)>,
    /// Most numbers per block (at least one position's).
    cap: usize,
}

impl<B: Backend> UniformBlocks<B> {
    /// Blocks of at most `cap` numbers for positions taking `sizes` numbers each, in this order.
    pub(super) fn new(sizes: Vec<usize>, cap: usize) -> Self {
        Self {
            sizes,
            next: 0,
            block: None,
            cap: cap.max(1),
        }
    }

    /// The `[m, width]` numbers of the next position, drawing and uploading the next block from `rng`
    /// when the current one is used up.
    pub(super) fn take(&mut self, m: usize, width: usize, rng: &mut StdRng, dev: &B::Device) -> Tensor<B, 2> {
        let (i, n) = (self.next, m * width);
        self.next += 1;
        if self.sizes.get(i) != Some(&n) {
            // A position that was not announced gets numbers of its own: the draw stays valid.
            self.block = None;
            return Tensor::from_data(TensorData::new(uniforms(rng, n), [m, width]), dev);
        }
        let held =
            matches!(&self.block, Some((_, first, offsets)) if (*first..first + offsets.len()).contains(&i));
        if !held {
            let mut offsets = Vec::new();
            let mut total = 0;
            for &size in &self.sizes[i..] {
                if !offsets.is_empty() && total + size > self.cap {
                    break;
                }
                offsets.push(total);
                total += size;
            }
            let block = Tensor::from_data(TensorData::new(uniforms(rng, total), [total]), dev);
            self.block = Some((block, i, offsets));
        }
        match &self.block {
            Some((block, first, offsets)) => {
                block.clone().narrow(0, offsets[i - first], n).reshape([m, width])
            }
            None => Tensor::from_data(TensorData::new(uniforms(rng, n), [m, width]), dev),
        }
    }
}
