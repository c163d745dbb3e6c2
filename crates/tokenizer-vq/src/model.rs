//! The VQ model: encoder → projection → quantiser → projection → decoder.

use crate::blocks::conv1;
use crate::coder::{Decoder, Encoder};
use crate::config::VqConfig;
use crate::conv::conv2d;
use crate::quantizer::{Quantized, Quantizer};
use burn::module::Module;
use burn::nn::conv::Conv2d;
use burn::tensor::backend::Backend;
use burn::tensor::{Int, Tensor};

/// A VQ tokenizer's network.
#[derive(Module, Debug)]
pub struct VqModel<B: Backend> {
    /// Raster → continuous grid.
    pub encoder: Encoder<B>,
    quant_conv: Conv2d<B>,
    /// The codebook.
    pub quantizer: Quantizer<B>,
    post_quant_conv: Conv2d<B>,
    /// Codes → raster.
    pub decoder: Decoder<B>,
}

/// The parameters that gradients train: all but the codebook, which moves by moving averages. They are
/// what data-parallel ranks average (averaging the codebook's absent gradients as zeros would hand it to
/// the optimizer).
#[derive(Module, Debug)]
pub struct Trainable<B: Backend> {
    encoder: Encoder<B>,
    quant_conv: Conv2d<B>,
    post_quant_conv: Conv2d<B>,
    decoder: Decoder<B>,
}

/// One training forward pass.
#[derive(Debug, Clone)]
pub struct Forward<B: Backend> {
    /// Reconstruction `[B, C, H, W]` (logits for binary output).
    pub recon: Tensor<B, 4>,
    /// The quantisation of every grid cell (rows in `[batch, row, col]` order).
    pub quantized: Quantized<B>,
}

impl<B: Backend> VqModel<B> {
    /// A freshly initialised model.
    pub fn new(cfg: &VqConfig, dev: &B::Device) -> Self {
        Self {
            encoder: Encoder::new(cfg, dev),
            quant_conv: conv1(cfg.z_channels, cfg.embed_dim, dev),
            quantizer: Quantizer::new(cfg.codebook_size, cfg.embed_dim, dev),
            post_quant_conv: conv1(cfg.embed_dim, cfg.embed_dim, dev),
            decoder: Decoder::new(cfg, dev),
        }
    }

    /// The gradient-trained parameters (sharing this model's tensors and ids).
    pub fn trainable(&self) -> Trainable<B> {
        Trainable {
            encoder: self.encoder.clone(),
            quant_conv: self.quant_conv.clone(),
            post_quant_conv: self.post_quant_conv.clone(),
            decoder: self.decoder.clone(),
        }
    }

    /// Encoder outputs as rows `[B·h·w, D]` and the grid size.
    pub fn encode_rows(&self, x: Tensor<B, 4>) -> (Tensor<B, 2>, [usize; 3]) {
        let z = conv2d(&self.quant_conv, self.encoder.forward(x));
        let [b, d, h, w] = z.dims();
        (z.permute([0, 2, 3, 1]).reshape([b * h * w, d]), [b, h, w])
    }

    fn decode_rows(&self, rows: Tensor<B, 2>, [b, h, w]: [usize; 3]) -> Tensor<B, 4> {
        let d = rows.dims()[1];
        let z = rows.reshape([b, h, w, d]).permute([0, 3, 1, 2]);
        self.decoder.forward(conv2d(&self.post_quant_conv, z))
    }

    /// The training pass.
    pub fn forward(&self, x: Tensor<B, 4>) -> Forward<B> {
        let (rows, grid) = self.encode_rows(x);
        let quantized = self.quantizer.quantize(rows);
        let recon = self.decode_rows(quantized.z_q.clone(), grid);
        Forward { recon, quantized }
    }

    /// Code ids `[B, h, w]` of rasters.
    pub fn encode(&self, x: Tensor<B, 4>) -> Tensor<B, 3, Int> {
        let (rows, [b, h, w]) = self.encode_rows(x);
        self.quantizer.quantize(rows).indices.reshape([b, h, w])
    }

    /// Rasters (logits for binary output) from code ids `[B, h, w]`.
    pub fn decode(&self, ids: Tensor<B, 3, Int>) -> Tensor<B, 4> {
        let [b, h, w] = ids.dims();
        let rows = self.quantizer.lookup(ids.reshape([b * h * w]));
        self.decode_rows(rows, [b, h, w])
    }
}
