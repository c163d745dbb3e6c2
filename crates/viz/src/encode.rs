//! PNG and GIF files.

use crate::image::Rgb;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

/// What can go wrong writing a picture.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// The file cannot be written.
    #[error("{path}: {message}")]
    Write {
        /// The file.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

/// Result with [`VizError`].
pub type Result<T, E = VizError> = std::result::Result<T, E>;

fn err(path: &Path) -> impl Fn(String) -> VizError + '_ {
    move |message| VizError::Write {
        path: path.into(),
        message,
    }
}

/// Writes one image as PNG.
pub fn write_png(path: &Path, img: &Rgb) -> Result<()> {
    let e = err(path);
    let f = std::fs::File::create(path).map_err(|x| e(x.to_string()))?;
    let mut enc = png::Encoder::new(BufWriter::new(f), img.width as u32, img.height as u32);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(|x| e(x.to_string()))?;
    w.write_image_data(&img.bytes()).map_err(|x| e(x.to_string()))?;
    w.finish().map_err(|x| e(x.to_string()))
}

/// Writes frames as a looping animated GIF, `delay_s` seconds per frame. Frames must share one size.
pub fn write_gif(path: &Path, frames: &[Rgb], delay_s: f64) -> Result<()> {
    let e = err(path);
    let Some(first) = frames.first() else {
        return Err(e("no frames".into()));
    };
    let (w, h) = (u16::try_from(first.width), u16::try_from(first.height));
    let (Ok(w), Ok(h)) = (w, h) else {
        return Err(e(format!(
            "{}×{} is too large for GIF",
            first.width, first.height
        )));
    };
    let f = std::fs::File::create(path).map_err(|x| e(x.to_string()))?;
    let mut enc = gif::Encoder::new(BufWriter::new(f), w, h, &[]).map_err(|x| e(x.to_string()))?;
    enc.set_repeat(gif::Repeat::Infinite)
        .map_err(|x| e(x.to_string()))?;
    let delay = (delay_s * 100.0).round().clamp(1.0, 65535.0) as u16;
    for img in frames {
        if (img.width, img.height) != (first.width, first.height) {
            return Err(e("frames differ in size".into()));
        }
        let mut frame = gif::Frame::from_rgb_speed(w, h, &img.bytes(), 10);
        frame.delay = delay;
        enc.write_frame(&frame).map_err(|x| e(x.to_string()))?;
    }
    Ok(())
}
